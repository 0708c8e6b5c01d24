import numpy as np
import pytest
from scipy import ndimage

from napari_dvc_correct.engine.correlation.interpolation import (
    prefilter,
    sample,
    sample_with_gradient,
)
from napari_dvc_correct.engine.synthetic import textured_volume


@pytest.fixture(scope="module")
def volume():
    return textured_volume((20, 23, 26), feature_size=1.5, seed=3)


def test_sample_matches_scipy_cubic_spline_everywhere_including_borders(volume):
    coefficients = prefilter(volume)
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 1, (4000, 3)) * (np.array(volume.shape) - 1)
    expected = ndimage.map_coordinates(volume.astype(np.float64), points.T, order=3, mode="mirror")
    assert np.max(np.abs(sample(coefficients, points) - expected)) < 1e-5


def test_sample_reproduces_voxel_values_at_integer_positions(volume):
    coefficients = prefilter(volume)
    points = np.indices(volume.shape).reshape(3, -1).T.astype(float)
    assert np.max(np.abs(sample(coefficients, points) - volume.reshape(-1))) < 1e-5


@pytest.mark.parametrize(
    "shape, dtype",
    [((1, 5, 7), np.float32), ((2, 3, 40), np.uint16), ((31, 17, 9), np.float64),
     ((40, 90, 3), np.uint8), ((3, 2, 200), np.int16)],
)  # fmt: skip
def test_prefilter_equals_scipys_spline_filter_on_any_shape_and_dtype(shape, dtype):
    rng = np.random.default_rng(5)
    volume = (rng.random(shape) * 200).astype(dtype)
    coefficients = prefilter(volume)
    assert coefficients.dtype == np.float32 and coefficients.flags.c_contiguous
    expected = ndimage.spline_filter(volume.astype(np.float64), order=3, mode="mirror")
    np.testing.assert_allclose(coefficients, expected, rtol=0, atol=3e-7 * np.abs(expected).max())


def test_prefilter_of_a_boolean_mask_and_a_bad_shape():
    mask = np.zeros((6, 7, 8), bool)
    mask[2:4, 3:6, 1:7] = True
    expected = ndimage.spline_filter(mask.astype(np.float64), order=3, mode="mirror")
    np.testing.assert_allclose(prefilter(mask), expected, atol=1e-6)
    with pytest.raises(ValueError, match="3-D"):
        prefilter(np.zeros((4, 4)))


def test_points_outside_get_cval(volume):
    coefficients = prefilter(volume)
    points = np.array([[-0.01, 5, 5], [5, 5, volume.shape[2] - 1 + 1e-3], [5, 5, 5]])
    values = sample(coefficients, points, cval=-7.0)
    assert values[0] == -7.0 and values[1] == -7.0 and values[2] != -7.0


def test_gradient_matches_finite_differences(volume):
    coefficients = prefilter(volume)
    rng = np.random.default_rng(1)
    points = rng.uniform(0.5, 1, (500, 3)) * (np.array(volume.shape) - 2)
    values = sample_with_gradient(coefficients, points)
    h = 1e-4
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        numeric = sample(coefficients, points + step).astype(np.float64) - sample(
            coefficients, points - step
        )
        exact = ndimage.map_coordinates(
            volume.astype(np.float64), (points + step).T, order=3, mode="mirror"
        ) - ndimage.map_coordinates(
            volume.astype(np.float64), (points - step).T, order=3, mode="mirror"
        )
        assert np.max(np.abs(values[:, 1 + axis] - exact / (2 * h))) < 1e-4
        assert numeric.shape == (500,)


def test_bad_points_shape_is_a_clear_error(volume):
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        sample(prefilter(volume), np.zeros((4, 2)))
