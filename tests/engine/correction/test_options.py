"""The checked option records of the cleaning and the correction (engine/correction/options.py)."""

import subprocess
import sys

import pytest

from napari_dvc_correct.engine.correction.options import (
    CleaningOptions,
    CorrectionOptions,
    defaults,
)


@pytest.mark.parametrize(
    "changes",
    [
        {"frame": "deformed"},
        {"update": "add"},
        {"max_passes": 0},
        {"min_improvement": 1.0},
        {"min_improvement": -0.1},
        {"min_improvement": float("nan")},
    ],
)
def test_a_correction_option_out_of_range_is_refused(changes):
    with pytest.raises(ValueError, match=next(iter(changes))):
        CorrectionOptions(**changes)


@pytest.mark.parametrize(
    "changes", [{"threshold": 0}, {"radius": 0}, {"epsilon": -1}, {"passes": 0}, {"smoothing": -1}]
)
def test_a_cleaning_option_out_of_range_is_refused(changes):
    with pytest.raises(ValueError, match=next(iter(changes))):
        CleaningOptions(**changes)


def test_the_correction_refuses_what_the_record_refuses():
    import numpy as np

    from napari_dvc_correct.engine.correction.self_correction import correct_iter

    volume = np.zeros((8, 8, 8), np.float32)
    with pytest.raises(ValueError, match="max_passes"):
        next(correct_iter(volume, volume, max_passes=0))


def test_defaults_hold_both_records_and_load_no_numba():
    values = defaults()
    assert values["frame"] == "loaded" and values["max_passes"] == CorrectionOptions().max_passes
    assert values["threshold"] == CleaningOptions().threshold
    code = (
        "import sys; from napari_dvc_correct.engine.correction.options import defaults; defaults(); "
        "print(any(m in sys.modules for m in ('numba', 'scipy')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("floor", [1.5, -2.0, float("nan")])
def test_the_cleaning_s_absolute_zncc_floor_is_a_zncc(floor):
    with pytest.raises(ValueError, match="zncc_floor must be a ZNCC"):
        CleaningOptions(zncc_floor=floor)


def test_the_zncc_floor_is_absolute_and_keeps_clean_s_older_keyword():
    import numpy as np

    from napari_dvc_correct.engine.correction.cleaning import detect_outliers
    from napari_dvc_correct.engine.fields.field import DisplacementField, Status

    field = DisplacementField.zeros((8.0, 8.0, 8.0), (4.0, 4.0, 4.0), (5, 5, 5))
    field.status[:] = Status.CONVERGED
    field.zncc[:] = 0.9
    field.zncc[2, 2, 2] = 0.55  # above the floor 0.5 (a relative 0.5 x 0.9 = 0.45 too)
    field.zncc[1, 1, 1] = 0.45
    report = detect_outliers(field, CleaningOptions(zncc_floor=0.5))
    assert np.argwhere(report.low_zncc).tolist() == [[1, 1, 1]]  # the value itself, not a share
    older = detect_outliers(field, min_zncc=0.5)
    assert np.array_equal(older.low_zncc, report.low_zncc)
    assert CleaningOptions(zncc_floor=0.5).as_dict()["zncc_floor"] == 0.5
    assert not detect_outliers(field).low_zncc.any()  # None: no such test
