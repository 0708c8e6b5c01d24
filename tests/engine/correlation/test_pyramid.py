"""The arrays of one pyramid level (engine/correlation/pyramid.py), against known answers."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.initial_guess import bin_volume
from napari_dvc_correct.engine.correlation.interpolation import prefilter
from napari_dvc_correct.engine.correlation.pyramid import Prefiltered, PyramidLevel


@pytest.fixture(scope="module")
def volume():
    return synthetic.textured_volume((24, 24, 24), 2.0, seed=4).astype(np.float32)


def test_a_coarse_level_holds_the_binned_volumes_and_their_std(volume):
    level = PyramidLevel.build(2, volume, volume, None, 5, 0.0)
    binned = bin_volume(volume, 2)
    assert level.factor == 2 and level.half == 5
    np.testing.assert_allclose(level.reference, binned)
    np.testing.assert_allclose(level.coef_deformed, prefilter(binned), rtol=1e-5, atol=1e-4)
    assert level.gradient.shape == (3, *binned.shape)
    assert not level.reference.flags.writeable  # one array type for the kernels
    assert level.min_std == pytest.approx(0.0)


def test_prefiltered_arrays_are_used_as_given_and_checked_against_the_volumes(volume):
    coefficients = prefilter(volume)
    level = PyramidLevel.build(1, volume, volume, None, 5, 0.0,
                               prefiltered=Prefiltered(coef_deformed=coefficients))  # fmt: skip
    assert level.coef_deformed is coefficients
    with pytest.raises(ValueError, match="do not fit"):
        Prefiltered(coef_deformed=coefficients[:-1]).check(volume.shape)


def test_a_large_cpu_level_holds_gs_coefficients_and_a_gpu_level_its_gradient(volume, monkeypatch):
    """From ``GRADIENT_ON_DEMAND_FROM`` voxels a CPU level keeps ``G``'s coefficients (1, …)
    in place of ``∇G`` (3, …); the GPU's kernels read ``∇G``, so a CUDA level keeps it."""
    from napari_dvc_correct.engine.correlation import icgn_reference, pyramid

    coefficients = prefilter(volume)
    small = PyramidLevel.build(1, volume, volume, None, 5, 0.0)
    np.testing.assert_array_equal(small.gradient, icgn_reference.gradient_volume(coefficients))
    monkeypatch.setattr(pyramid, "GRADIENT_ON_DEMAND_FROM", volume.size)
    large = PyramidLevel.build(1, volume, volume, None, 5, 0.0)
    assert large.gradient.shape == (1, *volume.shape)
    np.testing.assert_array_equal(large.gradient[0], coefficients)
    on_gpu = PyramidLevel.build(1, volume, volume, None, 5, 0.0, device="cuda")
    np.testing.assert_array_equal(on_gpu.gradient, small.gradient)
