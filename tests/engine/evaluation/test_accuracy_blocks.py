"""Block-wise sums of the evaluation: any tiling of the volume gives the whole-volume numbers."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.binning import (
    cell_sums,
    cell_sums_block,
    node_box_sums,
    node_box_sums_nested,
    node_voxels,
)
from napari_dvc_correct.engine.evaluation.local_accuracy import local_mean_residual
from napari_dvc_correct.engine.evaluation.phases import (
    PhaseTotals,
    label_phases,
    lattice_sample,
    phase_table,
)
from napari_dvc_correct.engine.fields.field import DisplacementField

SHAPE = (23, 19, 29)


def tiles(shape, block):
    for z in range(0, shape[0], block[0]):
        for y in range(0, shape[1], block[1]):
            for x in range(0, shape[2], block[2]):
                yield tuple(slice(a, min(n, a + b)) for a, n, b in zip((z, y, x), shape, block))


@pytest.fixture(scope="module")
def residual():
    rng = np.random.default_rng(3)
    values = rng.random(SHAPE).astype(np.float32) * 10
    values[rng.random(SHAPE) < 0.1] = np.nan
    values[:8] = np.nan  # a slab with no defined voxel: the first layer of nodes sees none
    return values


def field():
    return DisplacementField.zeros((2.0, 3.4, 1.0), (4.0, 3.0, 5.5), (6, 6, 6))


def test_node_box_sums_are_the_brute_force_box_means_in_any_tiling(residual):
    item = field()
    centers = node_voxels(item, SHAPE)
    half = 3
    expected = np.full(item.shape, np.nan)
    for index in np.ndindex(item.shape):
        box = tuple(slice(max(0, c[i] - half), c[i] + half + 1) for c, i in zip(centers, index))
        values = residual[box][np.isfinite(residual[box])]
        expected[index] = values.astype(np.float64).mean() if values.size else np.nan
    np.testing.assert_allclose(local_mean_residual(residual, item, half), expected, rtol=1e-12)
    sums, counts = np.zeros(item.shape), np.zeros(item.shape, np.int64)
    for box in tiles(SHAPE, (5, 7, 4)):
        node_box_sums(residual[box], box, centers, half).add_to(sums, counts)
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose(sums / counts, expected, rtol=1e-12)
    assert np.isnan(expected).any() and np.isfinite(expected).any()


def test_nested_node_box_sums_are_one_call_per_half_size_in_any_tiling(residual):
    """Several half-sizes in one pass: the very numbers of one :func:`node_box_sums` per
    half-size, block by block (nodes whose smaller boxes miss a block add 0)."""
    item = field()
    centers = node_voxels(item, SHAPE)
    halves = (4, 1, 2)
    for box in tiles(SHAPE, (5, 7, 4)):
        parts = node_box_sums_nested(residual[box], box, centers, halves)
        for half, part in zip(halves, parts):
            one = node_box_sums(residual[box], box, centers, half)
            sums, counts = np.zeros(item.shape), np.zeros(item.shape, np.int64)
            expected_sums, expected_counts = np.zeros(item.shape), np.zeros(item.shape, np.int64)
            part.add_to(sums, counts)
            one.add_to(expected_sums, expected_counts)
            np.testing.assert_array_equal(counts, expected_counts)
            np.testing.assert_array_equal(sums, expected_sums)
    outside = (slice(0, 2), slice(0, 2), slice(0, 2))
    far = tuple(c[-1:] + 100 for c in centers)
    assert all(
        p.sums.size == 0 for p in node_box_sums_nested(residual[outside], outside, far, halves)
    )


def test_cell_sums_of_blocks_add_up_to_the_whole_volume(residual):
    item = field()
    whole_sums, whole_counts = cell_sums(residual, item)
    sums, counts = np.zeros(item.shape), np.zeros(item.shape, np.int64)
    for box in tiles(SHAPE, (6, 5, 8)):
        cell_sums_block(residual[box], box, item).add_to(sums, counts)
    np.testing.assert_array_equal(counts, whole_counts)
    np.testing.assert_allclose(sums, whole_sums, rtol=1e-12)
    # every finite voxel inside the cells counts once
    assert whole_counts.sum() <= np.isfinite(residual).sum() and whole_counts.sum() > 0


def test_lattice_samples_and_phase_totals_of_blocks_are_the_whole_volumes():
    rng = np.random.default_rng(4)
    volume = rng.normal(100, 20, SHAPE).astype(np.float32)
    stride = 3
    parts = [lattice_sample(volume[box], box, stride) for box in tiles(SHAPE, (4, 5, 7))]
    np.testing.assert_array_equal(
        np.sort(np.concatenate(parts)), np.sort(volume[::stride, ::stride, ::stride].ravel())
    )
    thresholds = np.array([90.0, 115.0])
    totals = PhaseTotals(3)
    for box in tiles(SHAPE, (4, 5, 7)):
        totals.add(volume[box], label_phases(volume[box], thresholds))
    whole = phase_table(volume, label_phases(volume, thresholds), thresholds)
    for ours, theirs in zip(totals.table(thresholds), whole):
        assert (ours.voxels, ours.lower, ours.upper) == (theirs.voxels, theirs.lower, theirs.upper)
        assert ours.mean_gray == pytest.approx(theirs.mean_gray, rel=1e-12)
    with pytest.raises(ValueError, match="phase 1 .* has no voxel"):
        PhaseTotals(3).add(volume, label_phases(volume, [300.0, 400.0])).check_nonempty(
            [300.0, 400.0]
        )


# --- eq. 1 and the gradients, whole or by block ---------------------------------------------------
def test_background_residual_is_eq_1_over_the_voxels_of_one_phase_in_both_states():
    from napari_dvc_correct.engine.evaluation import accuracy_blocks

    residual = np.array([1.0, 2.0, 3.0, 4.0, np.nan, 6.0]).reshape(1, 2, 3)
    reference = np.array([0, 0, 1, 1, 1, 1], np.uint8).reshape(1, 2, 3)
    mapped = np.array([0, 1, 1, 1, 1, 0], np.uint8).reshape(1, 2, 3)  # voxels 1 and 5 disagree
    background = accuracy_blocks.background_residual(residual, reference, mapped)
    # agreeing and finite: voxel 0 (phase 0, r = 1), voxels 2, 3 (phase 1, r = 3, 4)
    assert background.mean == pytest.approx(8.0 / 3) and background.voxels == 3
    assert background.per_phase == ((0, 1.0, 1), (1, 3.5, 2))
    corrected = accuracy_blocks.corrected_residual(residual, background)
    assert corrected.dtype == np.float32
    np.testing.assert_allclose(corrected[0, 0], [1 - 8 / 3, 2 - 8 / 3, 3 - 8 / 3], rtol=1e-6)
    with pytest.raises(ValueError, match="background residual is undefined"):
        accuracy_blocks.background_residual(residual, reference, 1 - reference)
    with pytest.raises(ValueError, match="must have the same shape"):
        accuracy_blocks.background_residual(residual, reference[..., :2], mapped)


def test_the_gradient_of_a_block_with_its_halo_is_the_whole_volume_s():
    from napari_dvc_correct.engine.evaluation import accuracy_blocks

    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float32) for n in (6, 7, 8)), indexing="ij")
    volume = 2.0 * z - 3.0 * y + 0.5 * x  # grad = (2, -3, 0.5) everywhere, faces included
    components = accuracy_blocks.gradient_components(volume)
    assert components.shape == (3, 6, 7, 8)
    for axis, slope in enumerate((2.0, -3.0, 0.5)):
        np.testing.assert_allclose(components[axis], slope, rtol=1e-6)
    ramp = (x**2).astype(np.float32)  # central differences: 2x, one-sided at the faces
    whole = accuracy_blocks.gradient_components(ramp)
    np.testing.assert_allclose(whole[2][:, :, 1:-1], 2.0 * x[:, :, 1:-1], rtol=1e-6)
    box = (slice(2, 4), slice(0, 7), slice(3, 6))
    block = accuracy_blocks.halo_gradient(lambda s: ramp[s], box, ramp.shape)
    np.testing.assert_array_equal(block, whole[(slice(None), *box)])


def test_the_smoothed_gradient_of_a_block_with_its_halo_is_the_whole_volume_s():
    """The error estimate's instrument (a Gaussian derivative): a block read with its halo gives
    the whole volume's values, at inner faces and at the volume's faces; on a linear ramp it is
    the slope away from the faces."""
    from napari_dvc_correct.engine.evaluation import accuracy_blocks
    from napari_dvc_correct.engine.evaluation.error_moments import (
        INSTRUMENT_RADIUS,
        smoothed_gradient,
    )

    rng = np.random.default_rng(3)
    volume = rng.normal(0.0, 10.0, (14, 15, 16)).astype(np.float32)
    whole = smoothed_gradient(volume)
    for box in (
        (slice(5, 9), slice(4, 11), slice(6, 10)),  # inner faces only
        (slice(0, 3), slice(12, 15), slice(0, 16)),  # the volume's faces
    ):
        block = accuracy_blocks.halo_gradient(lambda s: volume[s], box, volume.shape, None, True)
        assert block.shape == (6, *(s.stop - s.start for s in box))
        np.testing.assert_array_equal(
            block[:3], accuracy_blocks.gradient_components(volume)[(slice(None), *box)]
        )
        np.testing.assert_allclose(block[3:], whole[(slice(None), *box)], rtol=1e-6, atol=1e-5)
    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float64) for n in (14, 15, 16)), indexing="ij")
    ramp = smoothed_gradient(2.0 * z - 3.0 * y + 0.5 * x)
    inner = tuple(slice(INSTRUMENT_RADIUS, n - INSTRUMENT_RADIUS) for n in (14, 15, 16))
    for axis, slope in enumerate((2.0, -3.0, 0.5)):
        # the truncated kernel reads a slope 0.4 % low (the step does not depend on its scale)
        np.testing.assert_allclose(ramp[(axis, *inner)], slope, rtol=1e-2)
