"""The fused residual and same-phase sums against label_phases, np.abs and background_residual."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.accuracy_blocks import background_residual
from napari_dvc_correct.engine.evaluation.phase_sums import residual_phase_sums
from napari_dvc_correct.engine.evaluation.phases import NO_PHASE, label_phases


def _pair(dtype, seed=0):
    rng = np.random.default_rng(seed)
    own = rng.integers(0, 1000, (9, 11, 13)).astype(dtype)
    moved = (own + rng.normal(0.0, 60.0, own.shape)).astype(np.float32)
    moved[rng.random(own.shape) < 0.1] = np.nan  # outside the hull / the volume
    labels = label_phases(own, [300.0, 650.0])
    labels[0, :3] = NO_PHASE  # undefined own phases (e.g. masked)
    return own, moved, labels


@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.float64])
def test_equals_the_separate_steps(dtype):
    own, moved, labels = _pair(dtype)
    thresholds = [310.0, 640.0]  # the other state's, slightly different
    sums = residual_phase_sums(own, moved, labels, thresholds)
    expected = np.abs(moved - own.astype(np.float32))
    np.testing.assert_array_equal(sums.residual, expected)  # NaN at the same voxels
    mapped = label_phases(moved, thresholds)
    np.testing.assert_array_equal(sums.mapped, mapped)
    background = background_residual(expected, labels, mapped)
    assert sums.same_phase_mean == pytest.approx(background.mean, rel=1e-12)
    assert int(sums.same_counts.sum()) == background.voxels
    for phase, mean, voxels in background.per_phase:
        assert sums.same_counts[phase] == voxels
        assert sums.same_sums[phase] / voxels == pytest.approx(mean, rel=1e-12)
    finite = np.isfinite(expected)
    assert sums.residual_count == int(finite.sum())
    assert sums.residual_sum == pytest.approx(float(expected[finite].astype(np.float64).sum()))
    assert sums.max_label == 2


def test_no_agreeing_voxel_gives_nan_and_no_label_gives_minus_one():
    own = np.full((3, 4, 5), 10.0, np.float32)
    moved = np.full(own.shape, np.nan, np.float32)
    sums = residual_phase_sums(own, moved, np.full(own.shape, NO_PHASE, np.uint8), [5.0])
    assert np.isnan(sums.same_phase_mean) and sums.residual_count == 0
    assert sums.max_label == -1
    assert np.all(sums.mapped == NO_PHASE)


def test_shapes_must_agree():
    with pytest.raises(ValueError, match="same 3-D shape"):
        residual_phase_sums(np.zeros((2, 2, 2)), np.zeros((2, 2, 3), np.float32),
                            np.zeros((2, 2, 2), np.uint8), [1.0])  # fmt: skip


def _whole_volume_sums(own, moved, labels, thresholds):
    """residual_phase_sums as it was written before PhaseRows: one kernel call on the whole
    volume, the rows added up."""
    from napari_dvc_correct.engine.evaluation import phase_sums

    nz = own.shape[0]
    residual = np.empty(own.shape, np.float32)
    mapped = np.empty(own.shape, np.uint8)
    sums = np.zeros((nz, NO_PHASE + 1))
    counts = np.zeros((nz, NO_PHASE + 2), np.int64)
    phase_sums._residual_phase_planes(
        own, moved, labels, np.asarray(thresholds, np.float64), residual, mapped, sums, counts
    )
    return residual, mapped, sums[:, :NO_PHASE].sum(axis=0), counts[:, :NO_PHASE].sum(axis=0), (
        float(sums[:, NO_PHASE].sum()), int(counts[:, NO_PHASE].sum()),
        int(counts[:, NO_PHASE + 1].max()),
    )  # fmt: skip


@pytest.mark.parametrize("planes", [1, 2, 4, 9])
def test_rows_added_slab_by_slab_give_the_whole_volume_s_numbers_to_the_bit(planes):
    from napari_dvc_correct.engine.evaluation.phase_sums import PhaseRows

    own, moved, labels = _pair(np.float32, seed=3)
    moved = moved * np.float32(1.7)  # sums that float64 rounds
    thresholds = [310.0, 640.0]
    residual, mapped, same_sums, same_counts, totals = _whole_volume_sums(
        own, moved, labels, thresholds
    )
    whole = residual_phase_sums(own, moved, labels, thresholds)
    rows = PhaseRows(own.shape[0])
    parts = []
    for start in range(0, own.shape[0], planes):
        zs = slice(start, min(start + planes, own.shape[0]))
        parts.append(rows.add(zs, own[zs], moved[zs], labels[zs], thresholds))
    slabbed = rows.total()
    for sums in (whole, slabbed):
        np.testing.assert_array_equal(sums.same_sums, same_sums)
        np.testing.assert_array_equal(sums.same_counts, same_counts)
        assert (sums.residual_sum, sums.residual_count, sums.max_label) == totals
        assert sums.same_phase_mean == whole.same_phase_mean
    np.testing.assert_array_equal(whole.residual, residual)
    np.testing.assert_array_equal(whole.mapped, mapped)
    np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), residual)
    np.testing.assert_array_equal(np.concatenate([p[1] for p in parts]), mapped)
    assert slabbed.residual is None and slabbed.mapped is None
    with pytest.raises(ValueError, match="planes"):
        rows.add(slice(0, 2), own[:3], moved[:3], labels[:3], thresholds)
