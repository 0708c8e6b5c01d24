"""The scans' noise correlation measured on the pair's residual, and what it does to the error
estimate (engine/evaluation/noise_correlation.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from napari_dvc_correct.engine.evaluation.accuracy_blocks import gradient_components
from napari_dvc_correct.engine.evaluation.error_moments import (
    instrument_noise_pairing,
    smoothed_gradient,
)
from napari_dvc_correct.engine.evaluation.noise_correlation import (
    MAX_LAG,
    NoiseCorrelation,
    autocovariance,
    instrument_autocorrelation,
    measure_noise_correlation,
    window_factors,
)

SHAPE = (48, 48, 48)


def _noise(smoothing, seed, shape=SHAPE):
    """Unit-variance Gaussian noise smoothed by a Gaussian of ``smoothing`` voxels (0: white):
    correlation ``exp(−k²/(4 s²))`` at lag ``k``."""
    noise = np.random.default_rng(seed).standard_normal(shape)
    if smoothing > 0:
        noise = ndimage.gaussian_filter(noise, smoothing, mode="wrap")
    return noise / noise.std()


def _pulled(noise, fraction):
    """``noise`` sampled by the cubic B-spline at ``X + fraction`` (what the pull-back does to
    the loaded scan's noise)."""
    grid = np.indices(noise.shape).astype(np.float64)
    grid += np.asarray(fraction, np.float64)[:, None, None, None]
    return ndimage.map_coordinates(noise, grid, order=3, mode="grid-wrap")


def _residual(smoothing, fraction, seeds=(1, 2), shape=SHAPE):
    """``map(F~) − G`` of two texture-free scans: the pulled-back noise of seed ``seeds[1]``
    less the reference's, of seed ``seeds[0]`` (:func:`_reference`)."""
    return _pulled(_noise(smoothing, seeds[1], shape), fraction) - _noise(
        smoothing, seeds[0], shape
    )


def _reference(smoothing, seeds=(1, 2), shape=SHAPE):
    """``G`` of :func:`_residual`: its noise alone (the residual holds its negative)."""
    return _noise(smoothing, seeds[0], shape)


@pytest.mark.parametrize("fraction", [(0.0, 0.0, 0.0), (0.3, 0.3, 0.2), (0.5, 0.5, 0.5)])
def test_white_noise_reads_white_after_the_pull_back_is_taken_out(fraction):
    residual = _residual(0.0, fraction)
    displacement = np.tile(np.asarray(fraction) + 2.0, (10, 1))
    correlation = measure_noise_correlation(residual, _reference(0.0), displacement)
    assert correlation.is_white and correlation.factor(5) == 1.0
    if fraction[0] >= 0.3:  # the residual itself is correlated by the interpolation
        covariance, _ = autocovariance(residual)
        assert covariance[MAX_LAG + 1, MAX_LAG, MAX_LAG] / covariance[(MAX_LAG,) * 3] > 0.05


@pytest.mark.parametrize("smoothing", [0.7, 1.0])
@pytest.mark.parametrize("fraction", [(0.0, 0.0, 0.0), (0.3, 0.3, 0.2)])
def test_smoothed_noise_reads_its_known_correlation(smoothing, fraction):
    """Gaussian-smoothed noise: ``ρ(k) = exp(−k²/(4 s²))`` along each axis, within 0.03 (on
    64³: read on 40 % of the voxels, :func:`.flat_voxels`, the lags of one 48³ realisation
    scatter by up to 0.04)."""
    shape = (64, 64, 64)
    residual = _residual(smoothing, fraction, shape=shape)
    displacement = np.tile(np.asarray(fraction) + 1.0, (10, 1))
    correlation = measure_noise_correlation(
        residual, _reference(smoothing, shape=shape), displacement
    )
    expected = np.exp(-(np.arange(1, MAX_LAG + 1) ** 2) / (4 * smoothing**2))
    for axis in range(3):
        np.testing.assert_allclose(correlation.along(axis), expected, atol=0.03)


def _ct_residual(error: str, smoothing: float, margin: int = 6):
    """The residual of a field wrong by ``error`` on a CT-like cylinder in air (64³, 3 % noise
    smoothed by ``smoothing`` voxels, both scans; the true field a translation of (0.3, 0.3,
    0.2) voxel, the evaluated one that plus the error, on a grid of step 5 densified by the
    cubic spline; the pull-back a cubic B-spline): ``(residual, G, node displacements)``."""
    from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
    from napari_dvc_correct.engine.fields.field_spline import densify
    from napari_dvc_correct.engine.synthetic import concrete_ct_volume, ct_noise_sigma

    shape = (64, 64, 64)
    shift = np.array([0.3, 0.3, 0.2])
    big = tuple(n + 2 * margin for n in shape)
    texture = concrete_ct_volume(big, aggregate_fraction=0.4, seed=3).astype(np.float64)
    sigma = ct_noise_sigma(texture, 0.03)
    inner = (slice(margin, margin + shape[0]),) * 3
    reference = texture[inner] + sigma * _noise(smoothing, 11, shape)
    deformed = ndimage.shift(texture, shift, order=5, mode="mirror")
    deformed += sigma * np.pad(_noise(smoothing, 12, shape), margin, mode="wrap")
    origin, step, grid = grid_for_volume(shape, 15, 5)
    base = DisplacementField.zeros(origin, step, grid, params={"subvolume": 15})
    points = base.points
    rng = np.random.default_rng(5)
    if error == "band 0.5":  # across x, as benchmarks/bench_error_estimate.py's band_error
        direction = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
        profile = np.exp(-0.5 * ((points[:, 2] - 32.0) / (12.0 / 2.355)) ** 2)
        wrong = 0.5 * profile[:, None] * direction
    else:  # "random 0.2": independent node errors of 0.2 voxel rms
        wrong = rng.normal(0.0, 0.2 / np.sqrt(3), points.shape)
    u = shift + wrong
    dense = densify(base.replace(u=u.reshape((*grid, 3))), shape=shape, dtype=float)
    where = np.indices(shape).astype(np.float64) + margin + np.moveaxis(dense, -1, 0)
    moved = ndimage.map_coordinates(deformed, where, order=3, mode="mirror")
    return moved - reference, reference, u


@pytest.mark.parametrize("error", ["band 0.5", "random 0.2"])
def test_a_field_s_own_error_does_not_read_as_correlated_noise(error, monkeypatch):
    """The evaluated field wrong by a 0.5-voxel band or by 0.2 voxel at random: its error
    ``∇G·e`` in the residual is as correlated as the texture's gradient. Read on the flattest
    40 % of the block (:func:`.flat_voxels`) white noise reads white (band; measured: all lags
    0) or nearly white (random: the resolution within 10 %; measured ρ(1) ≤ 0.03, factor 1.17)
    and smoothed noise its known correlation within 0.03. Read on every voxel (before) the
    same residuals do not read white (white noise: ρ up to 0.013 and factor 1.04 with the band;
    2.63 with the random error)."""
    from napari_dvc_correct.engine.evaluation import noise_correlation

    residual, reference, u = _ct_residual(error, 0.0)
    correlation = measure_noise_correlation(residual, reference, u)
    assert correlation.is_white if error == "band 0.5" else correlation.nearly_white
    smoothed = measure_noise_correlation(*_ct_residual(error, 0.7))
    expected = np.exp(-(np.arange(1, MAX_LAG + 1) ** 2) / (4 * 0.7**2))
    for axis in range(3):
        np.testing.assert_allclose(smoothed.along(axis), expected, atol=0.03)
    monkeypatch.setattr(noise_correlation, "FLAT_SHARE", 1.0)
    everywhere = measure_noise_correlation(residual, reference, u)
    assert not everywhere.is_white
    assert error == "band 0.5" or everywhere.spread > 1.2


def test_the_flat_voxels_are_the_share_with_the_least_texture():
    """On a half-textured block the flat voxels lie in the flat half, and they are
    :data:`.FLAT_SHARE` of the valid ones."""
    from napari_dvc_correct.engine.evaluation.noise_correlation import FLAT_SHARE, flat_voxels

    own = 100.0 * _noise(1.5, 3)
    own[:, :, :24] = 0.0
    noise = _noise(0.0, 4)
    valid = np.ones(SHAPE, bool)
    flat = flat_voxels(noise, own + 0.5 * noise, valid)
    assert flat.sum() == pytest.approx(FLAT_SHARE * valid.size, rel=0.01)
    assert flat[:, :, :20].sum() / flat.sum() > 0.99


def test_the_pairings_are_the_known_ones():
    """White noise: ``I/2`` and ``c I`` exactly. Smoothed noise: the central differences'
    ``(1 − ρ(2))/2`` per axis, and the smoothed gradient's pairing with them as a noise volume
    shows it."""
    white = NoiseCorrelation.white()
    np.testing.assert_array_equal(white.pairing("g", "g"), 0.5 * np.eye(3))
    np.testing.assert_array_equal(white.pairing("h", "g"), instrument_noise_pairing() * np.eye(3))
    s = 0.8
    lags = np.arange(-MAX_LAG, MAX_LAG + 1)
    k2 = lags[:, None, None] ** 2 + lags[None, :, None] ** 2 + lags[None, None, :] ** 2
    smooth = NoiseCorrelation(np.exp(-k2 / (4 * s * s)), {})
    expected = (1 - np.exp(-4 / (4 * s * s))) / 2
    np.testing.assert_allclose(smooth.pairing("g", "g"), expected * np.eye(3), atol=1e-12)
    noise = _noise(s, 7, (64, 64, 64))
    inner = (slice(None), *(slice(6, -6),) * 3)
    h = smoothed_gradient(noise)[inner].astype(np.float64)
    g = gradient_components(noise)[inner].astype(np.float64)
    for i in range(3):
        assert np.mean(h[i] * g[i]) == pytest.approx(smooth.pairing("h", "g")[i, i], rel=0.1)


def test_the_window_factor_is_the_variance_of_window_sums_of_correlated_noise():
    """``Σ w n`` over windows of half-size 5 (the window's mean of ``w`` out) against white
    noise's: the factor against the sums' measured variance, within 15 %; white noise gives 1."""
    s, half = 0.7, 5
    lags = np.arange(-MAX_LAG, MAX_LAG + 1)
    k2 = lags[:, None, None] ** 2 + lags[None, :, None] ** 2 + lags[None, None, :] ** 2
    rho = np.exp(-k2 / (4 * s * s))
    texture = 100.0 * _noise(2.0, 3) + 10.0 * _noise(s, 4)
    instrument = instrument_autocorrelation(texture)
    white = np.zeros_like(rho)
    white[(MAX_LAG,) * 3] = 1.0
    assert all(v == pytest.approx(1.0) for v in window_factors(white, instrument).values())
    w = 0.5 * (gradient_components(texture)[0] + smoothed_gradient(texture)[0])
    n = 2 * half + 1
    sums = []
    for seed in range(4):
        noise = _noise(s, 100 + seed)
        for z in range(6, 42 - n, n):
            for y in range(6, 42 - n, n):
                for x in range(6, 42 - n, n):
                    box = (slice(z, z + n), slice(y, y + n), slice(x, x + n))
                    weight = w[box] - w[box].mean()
                    sums.append(np.sum(weight * noise[box]) / np.sqrt(np.sum(weight**2)))
    assert np.var(sums) == pytest.approx(window_factors(rho, instrument)[half], rel=0.15)


def test_the_correlation_rides_in_the_pair_s_dictionary():
    lags = np.arange(-MAX_LAG, MAX_LAG + 1)
    rho = np.exp(-(lags[:, None, None] ** 2 + lags[None, :, None] ** 2 + lags[None, None, :] ** 2))
    correlation = NoiseCorrelation(rho, {2: 3.0, 6: 5.0})
    again = NoiseCorrelation.from_dict(correlation.to_dict())
    np.testing.assert_allclose(again.rho, rho, atol=1e-6)
    assert again.factors == {2: 3.0, 6: 5.0}
    assert again.factor(3) == 3.0 and again.factor(5) == 5.0 and again.factor(None) == 5.0
    assert NoiseCorrelation.white().factor(4) == 1.0


def _scatter_against_resolution(smoothing, half=5):
    """An exact field on CT-like texture (its two scans' noise independent, smoothed by
    ``smoothing`` voxels): ``√(mean |Δu|² / mean resolution²)`` of the step over windows of
    half-size ``half`` (the step is pure noise there), with the white-noise resolution and with
    the measured correlation."""
    from napari_dvc_correct.engine.evaluation.error_estimate import residual_error
    from napari_dvc_correct.engine.evaluation.error_moments import ErrorMoments, moment_volumes
    from napari_dvc_correct.engine.synthetic import concrete_ct_volume, ct_noise_sigma

    shape = (64, 64, 64)
    texture = concrete_ct_volume(shape, aggregate_fraction=0.4, radius_fraction=0.7, seed=3)
    sigma = ct_noise_sigma(texture, 0.03)
    own = texture + sigma * _noise(smoothing, 11, shape)
    signed = sigma * (_noise(smoothing, 12, shape) - _noise(smoothing, 11, shape))
    r0 = float(np.mean(np.abs(signed)))
    correlation = measure_noise_correlation(signed, own, np.zeros((1, 3)))
    gradient = np.concatenate([gradient_components(own), smoothed_gradient(own)])
    n = 2 * half + 1
    centres = np.arange(4 + half, 60 - half, 3)
    index = np.ix_(centres, centres, centres)
    means = np.stack(
        [
            ndimage.uniform_filter(v.astype(np.float64), n)[index]
            for v in moment_volumes(signed, own, gradient)
        ]
    )
    moments = ErrorMoments(np.full(means.shape[1:], n**3), means, half)
    ratios = []
    for given in (None, correlation):
        step = residual_error(moments, r0, 0.5, given)
        ratios.append(np.sqrt(np.mean(np.sum(step.shift**2, -1)) / np.mean(step.resolution**2)))
    return correlation, ratios


def test_the_resolution_follows_the_step_s_scatter_under_correlated_noise():
    """White noise: the scatter is the resolution (within 20 %; measured 1.01) and the measured
    correlation is white. Noise smoothed by 0.7 voxel: the white-noise resolution understates
    the step's scatter (measured 2.8×); with the measured correlation they agree (measured
    1.05; 1.08 at 1.0 voxel, where white reads 4.0×)."""
    correlation, (plain, _) = _scatter_against_resolution(0.0)
    assert correlation.is_white and 0.8 < plain < 1.2
    correlation, (plain, measured) = _scatter_against_resolution(0.7)
    assert correlation.along(0)[0] == pytest.approx(0.6, abs=0.03)
    assert plain > 2.0 and 0.85 < measured < 1.25


def test_the_correlation_in_words_gives_one_voxel_lags_and_the_resolution_s_shortfall():
    assert NoiseCorrelation.white().describe() == (
        "scan noise white in space (no correlation 1–3 voxels apart)"
    )
    lags = np.arange(-MAX_LAG, MAX_LAG + 1)
    rho = np.exp(
        -(lags[:, None, None] ** 2 + 2 * lags[None, :, None] ** 2 + lags[None, None, :] ** 2)
    )
    text = NoiseCorrelation(rho, {2: 3.0, 6: 6.25}).describe(applied=False)
    one = np.exp(-1.0), np.exp(-2.0), np.exp(-1.0)  # z, y, x
    assert f"z/y/x: {one[0]:.2f}/{one[1]:.2f}/{one[2]:.2f}" in text
    assert "up to 2.5× small" in text  # √6.25: the largest variance factor as a spread
    # a correlation that changes the resolution by less than 10 % says so
    nearly = NoiseCorrelation(rho, {2: 1.05, 6: 1.1})
    assert nearly.describe().startswith("scan noise nearly white in space (ρ one voxel apart")
    assert nearly.describe().endswith("white-noise resolution holds within 10 %")
    # a negative one (anti-correlated noise) makes the resolution read large
    negative = NoiseCorrelation(rho, {2: 0.5, 6: 0.64})
    assert negative.describe(applied=False).endswith("may read up to 1.2× large")  # 1/√0.64
    # applied: the estimate's resolution carries it, by the factor given
    applied = NoiseCorrelation(rho, {2: 3.0, 6: 6.25}).describe(applied=True)
    assert applied.endswith(
        "the error estimate takes it into account (its resolution up to 2.5× the white-noise one)"
    )
    assert negative.describe(applied=True).endswith("down to 0.8× the white-noise one)")
    assert nearly.describe(applied=True) == nearly.describe(applied=False)
