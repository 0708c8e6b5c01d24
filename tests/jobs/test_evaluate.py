"""The evaluation job: one place that chooses in memory or out of core."""

from __future__ import annotations

import pytest

from napari_dvc_correct.engine.evaluation.options import EvaluationOptions
from napari_dvc_correct.engine.progress import Progress, run_to_completion
from napari_dvc_correct.engine.run_options import RunOptions
from napari_dvc_correct.jobs.evaluate import evaluate_job


@pytest.mark.parametrize("out_of_core", [False, True])
def test_the_job_hands_the_records_to_the_chosen_back_end(monkeypatch, out_of_core):
    import napari_dvc_correct.engine.evaluation.accuracy as accuracy
    import napari_dvc_correct.tiled.evaluation as tiled_evaluation

    seen = {}

    def back_end(name):
        def run(reference, deformed, fields, **keywords):
            seen.update(keywords, back_end=name)
            yield Progress("evaluate", 1, 1, "done")
            return name

        return run

    monkeypatch.setattr(accuracy, "evaluate_iter", back_end("memory"))
    monkeypatch.setattr(tiled_evaluation, "evaluate_tiled_iter", back_end("tiled"))
    options = EvaluationOptions(phases=[120.0], mode="loaded", n_bins=4)
    run = RunOptions(block_shape=(32, 32, 32), workers=2) if out_of_core else RunOptions()
    outputs = {("residual", "a"): "a.zarr"}
    result = run_to_completion(
        evaluate_job(None, None, {"a": None}, options, outputs=outputs, run=run)
    )
    assert result == seen["back_end"] == ("tiled" if out_of_core else "memory")
    assert seen["phases"] == (120.0,) and seen["mode"] == "loaded" and seen["n_bins"] == 4
    assert seen["strain_window"] == EvaluationOptions().strain_window
    if out_of_core:
        assert seen["block_shape"] == (32, 32, 32) and seen["workers"] == 2
        assert seen["outputs"] == outputs
    else:
        assert seen["keep_volumes"] and "outputs" not in seen
