"""Phase segmentation by gray thresholds and the paper's Table 1 statistics."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.phases import (
    NO_PHASE,
    auto_thresholds,
    label_phases,
    phase_table,
    phase_thresholds,
    segment_phases,
    validate_thresholds,
)
from napari_dvc_correct.engine.synthetic import add_noise, two_phase_volume


@pytest.fixture(scope="module")
def clean():
    return two_phase_volume((48, 48, 48), phase_grays=(100.0, 170.0), texture=4.0, seed=2)


def blocks(grays=(40.0, 120.0, 220.0), shape=(12, 16, 20)):
    """Three slabs along x with exact grays: phases with a known answer."""
    volume = np.empty(shape, np.float32)
    thirds = np.array_split(np.arange(shape[2]), len(grays))
    for gray, columns in zip(grays, thirds):
        volume[:, :, columns] = gray
    return volume


# --- phases ---------------------------------------------------------------------------------------
def test_auto_thresholds_split_known_phases_and_table():
    volume = blocks()
    thresholds = auto_thresholds(volume, n_phases=3)
    assert 40 <= thresholds[0] < 120 <= thresholds[1] < 220
    labels = segment_phases(volume, thresholds)
    assert labels.dtype == np.uint8
    assert np.array_equal(np.unique(labels[:, :, 0]), [0])
    assert np.array_equal(np.unique(labels[:, :, -1]), [2])
    table = phase_table(volume, labels, thresholds)
    assert [s.mean_gray for s in table] == pytest.approx([40.0, 120.0, 220.0])
    assert table[0].lower == 40.0 and table[-1].upper == 220.0
    assert table[1].lower == thresholds[0] and table[1].upper == thresholds[1]
    assert sum(s.voxels for s in table) == volume.size
    assert sum(s.fraction for s in table) == pytest.approx(1.0)


def test_auto_thresholds_on_noisy_two_phase_volume(clean):
    noisy = add_noise(clean, 5.0, seed=3)
    (threshold,) = phase_thresholds(noisy, "auto", n_phases=2)
    assert 120 < threshold < 150  # between the phase grays 100 and 170
    labels = segment_phases(noisy, [threshold])
    table = phase_table(noisy, labels, [threshold])
    # the noise averages out: the phase means are those of the clean volume on the same voxels
    for phase in (0, 1):
        assert table[phase].mean_gray == pytest.approx(clean[labels == phase].mean(), abs=0.3)
    assert 0.25 < table[1].fraction < 0.45  # grain fraction 0.35


def test_user_thresholds_are_used_as_given():
    volume = blocks()
    thresholds = phase_thresholds(volume, [100.0, 150.0])
    assert np.array_equal(thresholds, [100.0, 150.0])
    labels = segment_phases(volume, thresholds)
    assert np.array_equal(np.bincount(labels.ravel()), [12 * 16 * 7, 12 * 16 * 7, 12 * 16 * 6])


@pytest.mark.parametrize(
    ("thresholds", "message"),
    [
        ([10.0], "outside the gray range"),
        ([100.0, 300.0], "outside the gray range"),
        ([150.0, 100.0], "strictly increasing"),
        ([100.0, 100.0], "strictly increasing"),
        ([np.nan], "finite"),
        ([], "1 to 7"),
    ],
)
def test_bad_thresholds_are_clear_errors(thresholds, message):
    with pytest.raises(ValueError, match=message):
        phase_thresholds(blocks(), thresholds, name="reference")


def test_phase_with_no_voxels_is_a_clear_error():
    # thresholds inside the range but nothing between 130 and 200
    with pytest.raises(
        ValueError, match=r"phase 2 \(gray 130 .. 200\) has no voxel in the deformed"
    ):
        segment_phases(blocks(), [100.0, 130.0, 200.0], name="deformed")
    validate_thresholds([100.0, 130.0, 200.0], (40.0, 220.0))  # valid as numbers
    with pytest.raises(ValueError, match="single gray value"):
        auto_thresholds(np.full((4, 4, 4), 7.0))
    with pytest.raises(ValueError, match="number of phases"):
        auto_thresholds(blocks(), n_phases=1)


def test_auto_thresholds_on_integer_volumes_keep_each_gray_in_one_phase():
    volume = blocks(grays=(0.0, 1.0, 2.0, 3.0), shape=(4, 4, 40)).astype(np.uint8)
    (threshold,) = auto_thresholds(volume, 2)
    labels = segment_phases(volume, [threshold])
    for gray in range(4):  # every gray value lies wholly in one phase
        assert np.unique(labels[volume == gray]).size == 1
    assert 0 < threshold <= 3


def test_label_phases_marks_undefined_voxels():
    volume = np.array([[[10.0, 50.0, np.nan, 90.0]]])
    assert label_phases(volume, [40.0, 80.0]).tolist() == [[[0, 1, NO_PHASE, 2]]]
