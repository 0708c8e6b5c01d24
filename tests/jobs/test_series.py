"""The series job: one place that chooses in memory or out of core."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.progress import Progress, run_to_completion
from napari_dvc_correct.engine.run_options import RunOptions
from napari_dvc_correct.jobs.series import series_job

PARAMS = CorrelationParams(subvolume=15, step=10)


@pytest.fixture(scope="module")
def states():
    first = synthetic.textured_volume((36, 36, 36), 2.0, seed=6)
    return [first] + [
        synthetic.deform_volume(first, synthetic.translation((0.0, 0.5 * k, -0.75 * k)))
        for k in (1, 2)
    ]


def test_in_memory_the_job_gives_the_known_total_displacements(states):
    result = run_to_completion(series_job(states, PARAMS, strategy="total"))
    assert len(result.totals) == 2
    for k, total in enumerate(result.totals, start=1):
        good = total.status == Status.CONVERGED
        assert good.mean() > 0.9
        assert np.abs(total.u[good] - (0.0, 0.5 * k, -0.75 * k)).max() < 0.01


def test_out_of_core_the_job_hands_the_series_to_the_tiled_engine(states, monkeypatch, tmp_path):
    import napari_dvc_correct.tiled.series as tiled_series

    seen = {}

    def tiled(volumes, params, **keywords):
        seen.update(keywords, n_volumes=len(volumes))
        yield Progress("plan", 1, 1, "planned")
        return "tiled"

    monkeypatch.setattr(tiled_series, "series_tiled_iter", tiled)
    run = RunOptions(max_memory=2**31, temp_dir=str(tmp_path), device="cpu")
    job = series_job(states, PARAMS, strategy="total", correct_total=True, run=run)
    assert run_to_completion(job) == "tiled"
    assert seen["n_volumes"] == 3 and seen["strategy"] == "total" and seen["correct_total"]
    assert seen["max_memory"] == 2**31 and seen["temp_dir"] == str(tmp_path)
    with pytest.raises(ValueError, match="runs in memory only"):
        next(series_job(states, PARAMS, points=np.zeros((1, 3)), run=run))
