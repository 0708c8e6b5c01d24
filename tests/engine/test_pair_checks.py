"""One check of (pair, field, mask) before any work (issue 12, items 1 and 4)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import validate_pair
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.pair_checks import (
    check_field_on_volume,
    check_pair,
    check_pair_and_fields,
    largest_subvolume_advice,
)

SHAPE = (24, 24, 24)


def field_on(shape=SHAPE, u=(0.0, 0.0, 0.0), **metadata) -> DisplacementField:
    origin, step, grid = grid_for_volume(shape, 9, 6)
    field = DisplacementField.zeros(origin, step, grid, metadata=dict(metadata))
    field.u[...] = u
    return field


@pytest.fixture(scope="module")
def pair():
    volume = synthetic.textured_volume(SHAPE, 2.0, seed=3).astype(np.float32)
    return volume, volume.copy()


def test_a_good_pair_and_field_pass(pair):
    check_pair_and_fields(*pair, {"a": field_on(u=(0.5, -1.0, 2.0))}, mask=np.ones(SHAPE))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("shape", "must have the same shape"),
        ("nan", "deformed volume contains NaN"),
        ("inf", "deformed volume contains NaN"),
        ("flat", "3-D volume"),
    ],
)
def test_bad_pairs_are_refused(pair, change, message):
    reference, deformed = pair
    if change == "shape":
        deformed = deformed[:20]
    elif change in ("nan", "inf"):
        deformed = deformed.copy()
        deformed[3, 4, 5] = np.nan if change == "nan" else np.inf
    else:
        deformed = deformed[0]
    with pytest.raises(ValueError, match=message):
        check_pair(reference, deformed)


@pytest.mark.parametrize(
    ("mask", "message"),
    [
        (np.zeros(SHAPE), "the mask is empty"),
        (np.full(SHAPE, np.nan), "NaN"),
        (np.ones((24, 24, 20)), "mask shape"),
    ],
)
def test_bad_masks_are_refused(pair, mask, message):
    with pytest.raises(ValueError, match=message):
        check_pair(*pair, mask=mask)


@pytest.mark.parametrize(
    ("field", "message"),
    [
        (field_on(volume_shape=[48, 48, 48]), r"measured on volumes of shape \(48, 48, 48\)"),
        (field_on(shape=(48, 48, 48)), "grid does not fit the volume"),
        (field_on(u=(0.0, 1e6, 0.0)), "displacements up to 1e\\+06 voxels along y"),
    ],
)
def test_fields_not_of_the_pair_are_refused(field, message):
    with pytest.raises(ValueError, match=message):
        check_field_on_volume(field, SHAPE)


def test_failed_nodes_do_not_count_for_the_plausibility_check():
    field = field_on(u=(0.0, 0.0, 0.0))
    field.u[0, 0, 0] = (0.0, 5e5, 0.0)
    field.status[0, 0, 0] = 3  # a failed match holds whatever the solver left; cleaning replaces it
    assert not field.valid[0, 0, 0]
    check_field_on_volume(field, SHAPE)


def test_python_evaluate_refuses_nan_volumes_and_other_volumes(pair):
    reference, deformed = pair
    broken = deformed.copy()
    broken[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="contains NaN"):
        evaluate_fields(reference, broken, {"a": field_on()}, phases=[0.5])
    with pytest.raises(ValueError, match="measured on volumes of shape"):
        evaluate_fields(reference, deformed, {"a": field_on(volume_shape=[30, 30, 30])})


def test_correlate_refuses_a_nan_mask(pair):
    with pytest.raises(ValueError, match="mask contains NaN"):
        validate_pair(*pair, CorrelationParams(subvolume=9), mask=np.full(SHAPE, np.nan))


@pytest.mark.parametrize(("shape", "text"), [((24, 24, 3), "at least 5 voxels"),
                                             ((24, 24, 12), "at most 11")])  # fmt: skip
def test_subvolume_advice(shape, text):
    assert text in largest_subvolume_advice(shape)
    with pytest.raises(ValueError, match=text):
        grid_for_volume(shape, 15, 4)


@pytest.mark.parametrize("frame", ["loaded", "reference"])
def test_correct_iter_refuses_an_empty_mask_and_a_field_outside_in_both_frames(pair, frame):
    from napari_dvc_correct.engine.correction.self_correction import correct_iter

    with pytest.raises(ValueError, match="the mask is empty"):
        next(correct_iter(*pair, field_on(), frame=frame, mask=np.zeros(SHAPE, bool)))
    with pytest.raises(ValueError, match="grid does not fit the volume"):
        next(correct_iter(*pair, field_on(shape=(48, 48, 48)), frame=frame))


def test_a_named_field_outside_the_volume_reads_without_a_doubled_quote():
    # "field 'foam''s grid does not fit" (a quoted name then 's) read badly in the panels
    from napari_dvc_correct.engine.pair_checks import check_field_on_volume

    with pytest.raises(ValueError, match=r"^field 'foam': its grid does not fit the volume"):
        check_field_on_volume(field_on(shape=(48, 48, 48)), SHAPE, name="field 'foam'")
