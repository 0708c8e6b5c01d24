"""The correction job: one place that chooses in memory or out of core."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction.options import CleaningOptions, CorrectionOptions
from napari_dvc_correct.engine.correction.self_correction import correct_iter
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.progress import Progress, run_to_completion
from napari_dvc_correct.engine.run_options import RunOptions
from napari_dvc_correct.jobs.correct import correct_job


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=3)
    band = synthetic.shear_band((20.0, 20.0, 20.0), width=7.0, slip=3.0)
    deformed = synthetic.deform_volume(reference, band)
    field = correlate(reference, deformed, CorrelationParams(subvolume=15, step=6))
    return reference, deformed, field


def test_in_memory_the_job_is_the_engine_s_correction(pair):
    reference, deformed, field = pair
    options = CorrectionOptions(max_passes=1)
    cleaning = CleaningOptions(threshold=3.0)
    by_job = run_to_completion(
        correct_job(reference, deformed, field, options=options, cleaning=cleaning)
    )
    by_engine = run_to_completion(
        correct_iter(reference, deformed, field, max_passes=1, clean_options={"threshold": 3.0})
    )
    np.testing.assert_array_equal(by_job.u, by_engine.u)
    np.testing.assert_array_equal(by_job.status, by_engine.status)
    assert by_job.metadata["correction"]["passes_applied"] == 1


def test_out_of_core_the_job_hands_the_run_to_the_tiled_correction(pair, monkeypatch, tmp_path):
    reference, deformed, field = pair
    seen = {}

    def tiled(reference, deformed, field, params, **keywords):
        seen.update(keywords, params=params)
        yield Progress("plan", 1, 1, "planned")
        return "tiled result"

    import napari_dvc_correct.tiled.correction as tiled_correction

    monkeypatch.setattr(tiled_correction, "correct_tiled_iter", tiled)
    run = RunOptions(max_memory=2**30, workers=2, temp_dir=str(tmp_path), device="cpu")
    options = CorrectionOptions(frame="reference", max_passes=2)
    result = run_to_completion(
        correct_job(reference, deformed, field, options=options, run=run, mask=None)
    )
    assert result == "tiled result"
    assert seen["max_memory"] == 2**30 and seen["workers"] == 2
    assert seen["temp_dir"] == str(tmp_path) and seen["device"] == "cpu"
    assert seen["frame"] == "reference" and seen["max_passes"] == 2
    assert seen["min_improvement"] == CorrectionOptions().min_improvement
    assert seen["clean_options"] is None and seen["params"] is None
