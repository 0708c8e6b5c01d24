"""The checked EvaluationOptions record (engine/evaluation/options.py)."""

import subprocess
import sys

import pytest

from napari_dvc_correct.engine.evaluation.options import MAX_PHASES, EvaluationOptions


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"mode": "deformed"}, "mode must be 'reference' or 'loaded'"),
        ({"strain_measure": "true"}, "unknown strain measure"),
        ({"strain_method": "spline"}, "unknown gradient method"),
        ({"strain_method": "least-squares", "strain_window": 4}, "odd number of nodes >= 3"),
        ({"n_bins": 0}, "n_bins must be >= 1"),
        ({"n_phases": 1}, "number of phases must be an integer in 2"),
        ({"n_phases": MAX_PHASES + 1}, "number of phases must be an integer in 2"),
        ({"phases": "otsu"}, "phases must be 'auto'"),
        ({"phases": [120.0, float("nan")]}, "finite gray thresholds"),
        ({"phase_pair": (0,)}, "phase_pair must be two phase numbers"),
    ],
)
def test_a_bad_option_is_refused_with_what_to_change(changes, message):
    with pytest.raises(ValueError, match=message):
        EvaluationOptions(**changes)


def test_the_record_round_trips_and_gives_evaluate_iter_s_keywords():
    options = EvaluationOptions(phases=[100, 170.5], phase_pair=[0, 1], mode="loaded")
    assert options.phases == (100.0, 170.5) and options.phase_pair == (0, 1)
    assert EvaluationOptions.from_dict(options.as_dict()) == options
    keywords = options.keywords()
    assert keywords["mode"] == "loaded" and keywords["n_bins"] == 10


def test_the_evaluation_refuses_what_the_record_refuses():
    import numpy as np

    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_iter
    from napari_dvc_correct.engine.fields.field import DisplacementField

    volume = np.random.default_rng(0).random((16, 16, 16)).astype(np.float32)
    field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (2, 2, 2))
    with pytest.raises(ValueError, match="unknown strain measure"):
        next(evaluate_iter(volume, volume, field, strain_measure="true"))


def test_the_record_loads_neither_numba_nor_scipy():
    code = (
        "import sys; import napari_dvc_correct.engine.evaluation.options, "
        "napari_dvc_correct.engine.run_options; "
        "print(sorted({'numba', 'scipy'} & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
