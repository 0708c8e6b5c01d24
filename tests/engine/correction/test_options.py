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
