"""The gray-level model (engine/evaluation/gray_levels.py): known contrast and offset changes are recovered,
a crack does not bend the map, and a volume in blocks fits the map of the whole volume."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.evaluation.gray_levels import (
    CellSums,
    GrayLevelMap,
    block_sums,
    cells_shape,
    deming_slope,
    fit_gray_levels,
    map_from_sums,
)
from napari_dvc_correct.engine.evaluation.gray_noise import PairNoise, pair_noise, scan_noises
from napari_dvc_correct.engine.fields import warp
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume


@pytest.fixture(scope="module")
def texture():
    # as a CT scan's material: mean 100, standard deviation 30 (the real rock: 113 and 28)
    volume = synthetic.textured_volume((64, 64, 64), 2.0, seed=5)
    return (100.0 + 30.0 * (volume - volume.mean()) / volume.std()).astype(np.float32)


def test_a_global_brightness_and_contrast_change_is_recovered(texture):
    # the loaded scan darker and flatter: F = 0.4 G + 10, so G = 2.5 F - 25
    moved = 0.4 * texture + 10.0
    fitted = fit_gray_levels(texture, moved, cell=0)
    assert fitted.contrast == pytest.approx(2.5, rel=1e-4)
    assert fitted.offset == pytest.approx(-25.0, abs=0.02)
    assert np.max(np.abs(fitted.apply(moved) - texture)) < 1e-3
    assert not fitted.is_local


def test_no_change_gives_the_identity_and_noise_in_the_moved_scan_is_taken_out(texture):
    fitted = fit_gray_levels(texture, texture.copy())
    assert fitted.contrast == pytest.approx(1.0, abs=1e-6)
    assert fitted.offset == pytest.approx(0.0, abs=1e-3)
    # independent noise in the moved scan only: least squares attenuates the slope by
    # var(G) / (var(G) + sigma^2) (the best prediction of G); with that noise known the
    # errors-in-variables fit does not
    sigma = 0.3 * float(np.std(texture))
    noisy = synthetic.add_noise(texture, sigma, seed=3)
    plain = fit_gray_levels(texture, noisy, cell=0, fit="least squares")
    expected = np.var(texture) / (np.var(texture) + sigma**2)
    assert plain.contrast == pytest.approx(expected, rel=0.05)
    noise = PairNoise(reference=0.0, moved=sigma**2)
    fitted = fit_gray_levels(texture, noisy, cell=0, noise=noise)
    assert fitted.contrast == pytest.approx(1.0, abs=0.01)
    # a loaded scan free of noise: Deming is least squares
    assert noise.ratio == 0.0 and PairNoise(1.0, 0.0).ratio == np.inf


def test_a_smooth_local_change_is_followed_by_the_local_map(texture):
    # the contrast drifts along x from 0.5 to 0.7 (a beam-hardening-like ramp)
    x = np.arange(64, dtype=np.float32)[None, None, :]
    moved = (0.5 + 0.2 * x / 63.0) * texture + 5.0
    local = fit_gray_levels(texture, moved, cell=16)
    plain = fit_gray_levels(texture, moved, cell=0)
    assert local.is_local and local.local_contrast.shape == (4, 4, 4)
    local_error = np.mean(np.abs(local.apply(moved) - texture))
    plain_error = np.mean(np.abs(plain.apply(moved) - texture))
    assert local_error < 0.8 * plain_error
    # the local contrast follows 1 / (0.5 .. 0.7) from one side to the other
    assert local.local_contrast[..., 0].mean() > local.local_contrast[..., -1].mean() + 0.2


def test_a_crack_in_the_loaded_scan_does_not_bend_the_map(texture):
    moved = 0.5 * texture + 20.0
    cracked = moved.copy()
    cracked[30:34] = 5.0  # an open gap: 6 % of the voxels far darker than the material
    fitted = fit_gray_levels(texture, cracked, cell=0)
    assert fitted.contrast == pytest.approx(2.0, rel=0.01)
    assert fitted.offset == pytest.approx(-40.0, abs=1.0)
    # and the crack stays in the residual at full strength
    residual = np.abs(fitted.apply(cracked) - texture)
    assert np.median(residual[30:34]) > 50.0 * np.median(residual[:28])


def test_sums_of_blocks_equal_those_of_the_whole_volume(texture):
    moved = 0.6 * texture + 3.0
    moved[5, 5, 5] = np.nan
    shape, cell = texture.shape, 16
    whole = block_sums(texture, moved, tuple(slice(0, n) for n in shape), shape, cell)
    parts = CellSums.zeros(cells_shape(shape, cell))
    for z0 in range(0, 64, 24):
        for x0 in range(0, 64, 40):
            region = (slice(z0, min(z0 + 24, 64)), slice(0, 64), slice(x0, min(x0 + 40, 64)))
            parts.add(block_sums(texture[region], moved[region], region, shape, cell))
    for a, b in zip(whole.total(), parts.total()):
        assert a == pytest.approx(b, rel=1e-12)
    assert whole.total()[0] == texture.size - 1  # the NaN voxel is left out
    for fit in ("errors in variables", "deming", "least squares"):
        noise = PairNoise(reference=30.0, moved=20.0)
        a = map_from_sums(whole, shape, cell, noise=noise, fit=fit)
        b = map_from_sums(parts, shape, cell, noise=noise, fit=fit)
        np.testing.assert_allclose(a.local_contrast, b.local_contrast, rtol=1e-10)


def test_the_map_travels_as_metadata(texture):
    x = np.arange(64, dtype=np.float32)[None, None, :]
    fitted = fit_gray_levels(texture, (0.5 + 0.002 * x) * texture - 7.0, cell=32)
    back = GrayLevelMap.from_dict(fitted.to_dict())
    region = (slice(3, 40), slice(0, 64), slice(10, 20))
    np.testing.assert_allclose(
        back.apply(texture[region], region), fitted.apply(texture[region], region), atol=1e-3
    )
    assert "G ≈" in fitted.describe()
    assert GrayLevelMap.from_dict(None).is_identity
    # the fit and the noise it took out travel too; maps written before them were least squares
    noise = PairNoise(reference=4.0, moved=2.5)
    fitted = fit_gray_levels(texture, 0.5 * texture + 3.0, cell=32, noise=noise)
    back = GrayLevelMap.from_dict(fitted.to_dict())
    assert back.fit == "errors in variables" and back.noise == noise
    assert "fit: errors in variables" in back.describe()
    old = {k: v for k, v in fitted.to_dict().items() if k not in ("fit", "noise")}
    assert GrayLevelMap.from_dict(old).fit == "least squares"


def test_bad_input_is_refused(texture):
    with pytest.raises(ValueError, match="same shape|one shape"):
        fit_gray_levels(texture, texture[:10])
    with pytest.raises(ValueError, match="cell"):
        fit_gray_levels(texture, texture, cell=-1)
    # nothing defined: the identity, not an exception
    assert fit_gray_levels(texture, np.full_like(texture, np.nan)).is_identity


@pytest.fixture(scope="module")
def ct_pair():
    """A CT-like texture and its copy moved by a sub-voxel translation (the pull-back then
    interpolates: F~ keeps only part of F's noise), with the true field on a grid."""
    truth = synthetic.translation((0.4, -1.3, 0.25))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.concrete_ct_volume(s, seed=8), (64, 64, 64), truth, margin=12
    )
    origin, step, shape = grid_for_volume((64, 64, 64), 15, 5)
    base = DisplacementField.zeros(origin, step, shape)
    u = synthetic.sample_displacement(truth, base.points).reshape((*shape, 3))
    return reference, deformed, base.replace(u=u)


def _noisy_fit(ct_pair, fraction, contrast=1.0, offset=0.0, crack=False, cell=0, fit=None):
    """Noise of ``fraction`` of the gray range on both scans, ``G`` = contrast·texture + offset
    before its noise (a gray change whose noise stays), the fitted map and its noise."""
    reference, deformed, field = ct_pair
    sigma = synthetic.ct_noise_sigma(reference, fraction)
    g = synthetic.add_noise(contrast * reference + offset, sigma, seed=1)
    f = synthetic.add_noise(deformed, sigma, seed=2)
    moved = warp.pull_back(f, field, cval=np.nan)
    if crack:  # a slab of vanished material: far darker than anything in the loaded scan
        moved[30:34] = np.nanmin(moved) - 3.0 * np.nanstd(moved)
    noise = pair_noise(*scan_noises(g, f), field.displacement)
    return fit_gray_levels(g, moved, cell=cell, noise=noise, fit=fit), noise, g, moved


@pytest.mark.parametrize("fraction", [0.03, 0.05])
def test_an_unchanged_noisy_pair_keeps_the_full_contrast(ct_pair, fraction):
    fitted, noise, _, _ = _noisy_fit(ct_pair, fraction, cell=32)
    assert fitted.fit == "errors in variables"
    assert fitted.contrast == pytest.approx(1.0, abs=0.03)
    assert np.all(np.abs(fitted.local_contrast - 1.0) < 0.03)
    # least squares of G on F~ is diluted by F~'s noise: the bias this fit removes
    plain, _, _, _ = _noisy_fit(ct_pair, fraction, cell=32, fit="least squares")
    assert plain.contrast < fitted.contrast - 0.03
    # the pull-back kept about half of F's noise (fractional parts 0.4, 0.7, 0.25)
    assert noise.moved / noise.reference == pytest.approx(0.565, abs=0.03)


@pytest.mark.parametrize("fit", ["errors in variables", "deming"])
def test_an_imposed_contrast_and_offset_under_noise_is_recovered(ct_pair, fit):
    fitted, _, g, moved = _noisy_fit(ct_pair, 0.05, contrast=0.85, offset=0.07, fit=fit)
    assert fitted.contrast == pytest.approx(0.85, abs=0.03)
    # the offset: the line goes through both means
    assert fitted.offset == pytest.approx(np.nanmean(g) - 0.85 * np.nanmean(moved), abs=0.005)


def test_the_local_map_recovers_a_smooth_contrast_ramp_under_noise(ct_pair):
    reference, deformed, field = ct_pair
    x = np.arange(64, dtype=np.float32)[None, None, :]
    ramp = 0.7 + 0.3 * x / 63.0
    sigma = synthetic.ct_noise_sigma(reference, 0.05)
    g = synthetic.add_noise(ramp * reference, sigma, seed=1)
    f = synthetic.add_noise(deformed, sigma, seed=2)
    moved = warp.pull_back(f, field, cval=np.nan)
    noise = pair_noise(*scan_noises(g, f), field.displacement)
    fitted = fit_gray_levels(g, moved, cell=16, noise=noise)
    profile = fitted.local_contrast.mean(axis=(0, 1))
    truth = 0.7 + 0.3 * ((np.arange(4) + 0.5) * 16 - 0.5) / 63.0
    # smoothed over a cell and shrunk a little to the global line: within 0.06 at every cell
    assert np.all(np.abs(profile - truth) < 0.06)
    assert np.all(np.diff(profile) > 0)
    assert fitted.contrast == pytest.approx(np.mean(ramp), abs=0.03)
    # a Deming line reads the ramp's unexplained variance in G as G's noise and tilts
    deming = fit_gray_levels(g, moved, cell=0, noise=noise, fit="deming")
    assert deming.contrast > 1.0


def test_a_crack_under_noise_does_not_bend_the_map(ct_pair):
    fitted, _, g, moved = _noisy_fit(ct_pair, 0.05, crack=True, cell=32)
    assert fitted.contrast == pytest.approx(1.0, abs=0.03)
    assert np.all(np.abs(fitted.local_contrast - 1.0) < 0.05)
    residual = np.abs(fitted.apply(moved) - g)
    assert np.nanmedian(residual[30:34]) > 5.0 * np.nanmedian(residual[:28])


def test_slopes_of_the_fits_on_known_moments():
    # texture variance 4, contrast 0.5, noise variances 1 (G) and 2 (F~)
    vf, cov, vg = 4.0 + 2.0, 0.5 * 4.0, 0.25 * 4.0 + 1.0
    assert deming_slope(vf, cov, vg, 0.5) == pytest.approx(0.5, rel=1e-12)
    assert deming_slope(vf, cov, vg, np.inf) == pytest.approx(cov / vf, rel=1e-12)
    assert deming_slope(vf, cov, vg, 0.0) == pytest.approx(vg / cov, rel=1e-12)
    assert deming_slope(vf, -cov, vg, vg / vf) == pytest.approx(-np.sqrt(vg / vf), rel=1e-12)
    # a huge ratio (the stable form): least squares to 1e-6
    assert deming_slope(vf, cov, vg, 1e12) == pytest.approx(cov / vf, rel=1e-6)
    n = 1000.0
    sums = CellSums(*(np.array([[[v]]]) for v in (n, 0.0, 0.0, n * vf, n * cov, n * vg)))
    noise = PairNoise(reference=1.0, moved=2.0)
    for fit in ("errors in variables", "deming"):
        fitted = map_from_sums(sums, (8, 8, 8), 0, noise=noise, fit=fit)
        assert fitted.contrast == pytest.approx(0.5, rel=1e-12)
    assert map_from_sums(sums, (8, 8, 8), 0, noise=noise, fit="least squares").contrast == (
        pytest.approx(cov / vf)
    )
    # without the scans' noise every fit is least squares, and says so
    unknown = map_from_sums(sums, (8, 8, 8), 0)
    assert unknown.fit == "least squares" and unknown.contrast == pytest.approx(cov / vf)
    with pytest.raises(ValueError, match="fit must be one of"):
        map_from_sums(sums, (8, 8, 8), 0, noise=noise, fit="orthogonal")


def test_a_noise_estimate_the_residual_does_not_show_is_not_taken_out(texture):
    # identical clean scans: whatever a noise estimator reads in the texture, the least-squares
    # residual is zero, so no noise is taken out and the map is the identity
    for moved_noise in (0.0, 5.0, 500.0):
        noise = PairNoise(reference=moved_noise, moved=moved_noise)
        fitted = fit_gray_levels(texture, texture.copy(), cell=32, noise=noise)
        assert fitted.contrast == pytest.approx(1.0, abs=1e-6)
        assert np.max(np.abs(fitted.local_contrast - 1.0)) < 1e-6
    # noise only in the moved scan, over-estimated 4x (taken whole: 1 / (1 - 3 * 0.09) = 1.37):
    # cut to what the residual shows, which here is that noise itself
    sigma = 0.3 * float(np.std(texture))
    noisy = synthetic.add_noise(texture, sigma, seed=3)
    fitted = fit_gray_levels(texture, noisy, cell=0, noise=PairNoise(0.0, 4 * sigma**2))
    assert fitted.contrast == pytest.approx(1.0, abs=0.015)
