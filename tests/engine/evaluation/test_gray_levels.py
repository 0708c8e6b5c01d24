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
    fit_gray_levels,
    map_from_sums,
)


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


def test_no_change_gives_the_identity_and_noise_only_attenuates(texture):
    fitted = fit_gray_levels(texture, texture.copy())
    assert fitted.contrast == pytest.approx(1.0, abs=1e-6)
    assert fitted.offset == pytest.approx(0.0, abs=1e-3)
    # independent noise in the moved scan: least squares attenuates the slope by
    # var(G) / (var(G) + sigma^2), as it should for the best prediction of G
    sigma = 0.3 * float(np.std(texture))
    noisy = synthetic.add_noise(texture, sigma, seed=3)
    fitted = fit_gray_levels(texture, noisy, cell=0)
    expected = np.var(texture) / (np.var(texture) + sigma**2)
    assert fitted.contrast == pytest.approx(expected, rel=0.05)


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
    a, b = map_from_sums(whole, shape, cell), map_from_sums(parts, shape, cell)
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


def test_bad_input_is_refused(texture):
    with pytest.raises(ValueError, match="same shape|one shape"):
        fit_gray_levels(texture, texture[:10])
    with pytest.raises(ValueError, match="cell"):
        fit_gray_levels(texture, texture, cell=-1)
    # nothing defined: the identity, not an exception
    assert fit_gray_levels(texture, np.full_like(texture, np.nan)).is_identity
