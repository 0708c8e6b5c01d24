"""Every default lives in its record: the command line's parsers, the panels' controls and the
engine's keyword defaults all read it from there, so a default written twice fails here."""

from __future__ import annotations

import inspect

import pytest

from napari_dvc_correct.cli import build_parser
from napari_dvc_correct.engine.correction.options import CleaningOptions, CorrectionOptions
from napari_dvc_correct.engine.correlation.params import MIN_SUBVOLUME, CorrelationParams
from napari_dvc_correct.engine.evaluation.options import MAX_PHASES, EvaluationOptions
from napari_dvc_correct.engine.run_options import RunOptions

#: Command-line destination -> (record, field) for the options a record holds.
CORRELATION = {
    "subvolume": "subvolume",
    "step": "step",
    "order": "order",
    "search": "search_radius",
    "max_iterations": "max_iterations",
    "tolerance": "tolerance",
    "min_zncc": "min_zncc",
}
CORRECTION = {
    name: name for name in ("frame", "update", "max_passes", "min_improvement", "noise_fit")
}
CLEANING = {"outlier_threshold": "threshold", "smoothing": "smoothing"}
EVALUATION = {
    "phases": "phases",
    "phases_deformed": "phases_deformed",
    "n_phases": "n_phases",
    "phase_pair": "phase_pair",
    "mode": "mode",
    "strain": "strain_measure",
    "gradient": "strain_method",
    "strain_window": "strain_window",
    "bins": "n_bins",
    "bin_by": "bin_by",
}
RUN = {
    "tiled": "tiled",
    "max_memory": "max_memory",
    "workers": "workers",
    "scheduler": "scheduler",
    "batch": "batch_shape",
    "temp_dir": "temp_dir",
}


def _actions(command: str) -> dict:
    parser = build_parser((command,))
    sub = parser._subparsers._group_actions[0].choices[command]
    return {action.dest: action for action in sub._actions}


def _check(actions, record, names, shown=True):
    for dest, field in names.items():
        action = actions[dest]
        assert action.default == getattr(record, field), (dest, action.default)
        if shown and getattr(record, field) is not None and action.help:
            assert "%(default)s" in action.help, f"--{dest} does not show its default"


def test_correlate_s_options_are_the_records_defaults():
    actions = _actions("correlate")
    _check(actions, CorrelationParams(), CORRELATION)
    _check(actions, CorrectionOptions(), CORRECTION)
    _check(actions, CleaningOptions(), CLEANING)
    _check(actions, RunOptions(), RUN, shown=False)
    assert actions["device"].default == RunOptions().device
    assert "%(default)s" in actions["device"].help


@pytest.mark.parametrize("command", ["correct", "clean", "series"])
def test_correcting_commands_take_the_correction_records_defaults(command):
    actions = _actions(command)
    _check(actions, CleaningOptions(), CLEANING)
    if command != "clean":
        _check(actions, CorrectionOptions(), CORRECTION)
        _check(actions, RunOptions(), RUN, shown=False)


def test_evaluate_s_options_are_the_record_s_defaults():
    actions = _actions("evaluate")
    record = EvaluationOptions()
    _check(actions, record, EVALUATION)
    # switches that turn a default off
    assert actions["own_background"].default is (not record.shared_background)
    assert actions["raw_gray_levels"].default is (not record.gray_levels)
    assert actions["block"].default == RunOptions().block_shape
    evaluation_run = {k: v for k, v in RUN.items() if k not in ("batch", "temp_dir")}
    _check(actions, RunOptions(), evaluation_run, shown=False)


def test_help_prints_the_defaults():
    text = (
        build_parser(("correlate",))
        ._subparsers._group_actions[0]
        .choices["correlate"]
        .format_help()
    )
    params = CorrelationParams()
    for shown in (
        f"default {params.subvolume}",
        f"default {params.step}",
        f"default {params.max_iterations}",
        f"default {params.min_zncc}",
        f"default {CorrectionOptions().max_passes}",
        f">= {MIN_SUBVOLUME}",
    ):
        assert shown in " ".join(text.split()), shown


def _keyword_defaults(function) -> dict:
    return {
        name: p.default
        for name, p in inspect.signature(function).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def test_the_engine_s_keyword_defaults_are_the_records():
    from napari_dvc_correct.engine.correction.self_correction import correct_iter
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_iter, plan_evaluation
    from napari_dvc_correct.tiled.correction import correct_tiled_iter
    from napari_dvc_correct.tiled.evaluation import evaluate_tiled_iter

    correction = CorrectionOptions().as_dict()
    for function in (correct_iter, correct_tiled_iter):
        defaults = _keyword_defaults(function)
        assert {k: defaults[k] for k in correction} == correction, function.__name__
    evaluation = EvaluationOptions().keywords()
    for function in (evaluate_iter, evaluate_tiled_iter, plan_evaluation):
        defaults = _keyword_defaults(function)
        shared = set(defaults) & set(evaluation)
        assert len(shared) >= 7, function.__name__
        assert {k: defaults[k] for k in shared} == {k: evaluation[k] for k in shared}
    run = RunOptions()
    for function in (correct_tiled_iter, evaluate_tiled_iter):
        defaults = _keyword_defaults(function)
        for name in ("max_memory", "workers", "scheduler"):
            assert defaults[name] == getattr(run, name), (function.__name__, name)


def test_the_panels_start_from_the_records(make_napari_viewer):
    from napari_dvc_correct.widgets import CorrectWidget, CorrelateWidget, EvaluateWidget

    viewer = make_napari_viewer()
    params, run = CorrelationParams(), RunOptions()
    correlate = CorrelateWidget(viewer)
    viewer.window.add_dock_widget(correlate)
    assert correlate.subvolume.value() == params.subvolume
    assert correlate.subvolume.minimum() == MIN_SUBVOLUME
    assert correlate.step.value() == params.step
    assert correlate.order.currentData() == params.order
    assert (correlate.search_radius.value() or None) == params.search_radius
    assert correlate.device.currentData() == run.device
    assert correlate.tiled.isChecked() == run.tiled
    assert correlate.params() == params

    correct = CorrectWidget(viewer)
    viewer.window.add_dock_widget(correct)
    options = CorrectionOptions()
    assert correct.frame.currentData() == options.frame
    assert correct.update_rule.currentData() == options.update
    assert correct.max_passes.value() == options.max_passes
    assert correct.noise_fit.isChecked() == options.noise_fit
    assert correct._options() == options
    settings = correct.settings()  # a session saves the record whole
    assert {k: settings[k] for k in options.as_dict()} == options.as_dict()

    evaluate = EvaluateWidget(viewer)
    viewer.window.add_dock_widget(evaluate)
    evaluation = EvaluationOptions()
    assert evaluate.n_phases.value() == evaluation.n_phases
    assert evaluate.n_phases.maximum() == MAX_PHASES
    assert evaluate.mode.currentData() == evaluation.mode
