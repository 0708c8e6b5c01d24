"""Warping volumes by a field (engine/fields/warp.py): pull-back and forward warp undo a known deformation."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.evaluation import residual
from napari_dvc_correct.engine.fields import warp
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume

GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


def test_pull_back_and_forward_warp_undo_a_known_deformation(sheared_pair):
    reference, deformed, field = sheared_pair
    contrast = float(reference.std())
    core = (slice(8, 32),) * 3
    pulled = warp.pull_back(deformed, field)
    assert np.mean(np.abs(pulled - reference)[core]) < 0.01 * contrast
    assert np.mean(np.abs(deformed - reference)[core]) > 0.5 * contrast  # not vacuous
    moved = warp.warp_forward(reference, field, chunk_voxels=5000)
    assert np.mean(np.abs(moved - deformed)[core]) < 0.01 * contrast
    # chunking does not change the result
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)


def test_forward_warp_with_residual_matches_the_separate_calls(sheared_pair):
    reference, deformed, field = sheared_pair
    moved, mean = warp.warp_forward_with_residual(reference, deformed, field, chunk_voxels=4000)
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)
    expected = residual.mean_gray_residual(reference, deformed, field, "loaded")
    assert mean == pytest.approx(expected, rel=1e-6)


def test_forward_warp_with_the_lattice_inverse_equals_newton_at_every_voxel(sheared_pair):
    reference = sheared_pair[0]
    band = synthetic.shear_band((20.0, 20.0, 20.0), width=8.0, slip=4.0, shift=(1.5, -2.0, 2.5))
    origin, step, shape = grid_for_volume(reference.shape, 9, 8)  # node step 8: stride 4
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(*shape, 3))
    fast = warp.warp_forward(reference, field)
    exact = warp.warp_forward(reference, field, accuracy=None)
    # X within the inverse's error of the volume's faces may fall on either side of them
    assert np.mean(np.isnan(fast) != np.isnan(exact)) < 1e-3
    difference = np.abs(fast - exact)[np.isfinite(exact) & np.isfinite(fast)]
    # positions within 1e-3 voxel (1e-2 beyond the hull) of Newton's, gray gradients below 1 / voxel
    assert difference.max() < 1e-2 * np.ptp(reference)
    assert difference.mean() < 1e-4 * np.ptp(reference)
    assert difference.max() > 0  # two different computations


def _forward_with_residual_whole_box(reference, deformed, field, gray_levels, chunk_voxels):
    """warp_forward_with_residual as it was written before it sampled slab by slab: the whole
    box's warp and hull mask, then the residual slab by slab."""
    from napari_dvc_correct.engine.fields.field_spline import FieldSpline
    from napari_dvc_correct.engine.slabs import iter_slabs

    shape = reference.shape
    spline = FieldSpline.from_field(field)
    sampler = warp.spline_sampler(warp.coefficients_of(reference, None, "reference"))
    result, in_hull = warp.warp_forward_block(
        sampler, spline, warp.whole_box(shape), chunk_voxels=chunk_voxels
    )
    total, count = 0.0, 0
    for z in iter_slabs(shape, chunk_voxels):
        values = result[z]
        defined = np.isfinite(values)
        own = deformed[z].astype(np.float32)
        if gray_levels is not None:
            own = gray_levels.apply(own, (z, slice(0, shape[1]), slice(0, shape[2])))
        difference = np.abs(own - values)[defined & in_hull[z]]
        total += float(np.sum(difference, dtype=np.float64))
        count += int(difference.size)
    return result, total / count


@pytest.mark.parametrize("chunk_voxels", [4000, 1 << 21])
def test_forward_warp_with_residual_sampled_slab_by_slab_equals_the_whole_box(
    sheared_pair, chunk_voxels
):
    """G' made slab by slab (no whole-volume hull mask) is the whole box's to the bit, and so is
    the mean residual; with a gray-level map and with a coarse stage built beforehand too."""
    from napari_dvc_correct.engine.evaluation.gray_levels import GrayLevelMap

    reference, deformed, field = sheared_pair
    gray = GrayLevelMap(contrast=0.93, offset=4.5, volume_shape=reference.shape)
    for gray_levels in (None, gray):
        before, mean_before = _forward_with_residual_whole_box(
            reference, deformed, field, gray_levels, chunk_voxels
        )
        moved, mean = warp.warp_forward_with_residual(
            reference, deformed, field, chunk_voxels=chunk_voxels, gray_levels=gray_levels
        )
        assert np.array_equal(moved, before, equal_nan=True) and mean == mean_before
        inverter = warp.forward_inverter(warp.as_field_spline(field), reference.shape)
        shared, mean_shared = warp.warp_forward_with_residual(
            reference, deformed, field, chunk_voxels=chunk_voxels, gray_levels=gray_levels,
            inverter=inverter,
        )  # fmt: skip
        assert np.array_equal(shared, before, equal_nan=True) and mean_shared == mean_before
