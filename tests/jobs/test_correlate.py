"""The correlation jobs: one place that chooses in memory or out of core."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.progress import Progress, run_to_completion
from napari_dvc_correct.engine.run_options import RunOptions
from napari_dvc_correct.jobs.correlate import correlate_job, points_job

SHIFT = (0.6, -1.3, 2.2)
PARAMS = CorrelationParams(subvolume=15, step=8)


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=4)
    return reference, synthetic.deform_volume(reference, synthetic.translation(SHIFT))


def test_in_memory_the_job_is_the_engine_s_correlation(pair):
    reference, deformed = pair
    field = run_to_completion(
        correlate_job(reference, deformed, PARAMS, run=RunOptions(device="cpu"))
    )
    assert field.metadata["device"].startswith("CPU")
    np.testing.assert_array_equal(field.u, correlate(reference, deformed, PARAMS).u)
    good = field.status == Status.CONVERGED
    assert good.mean() > 0.9
    assert np.abs(field.u[good] - SHIFT).max() < 0.01  # the known translation, in voxels


def test_at_points_the_job_matches_the_known_translation(pair):
    reference, deformed = pair
    points = np.array([[20.0, 20.0, 20.0], [14.5, 22.0, 25.25]])
    result = run_to_completion(points_job(reference, deformed, points, PARAMS))
    assert result.valid.all()
    assert np.abs(result.u - SHIFT).max() < 0.01


def test_out_of_core_the_jobs_hand_the_run_to_the_tiled_engine(pair, monkeypatch):
    import napari_dvc_correct.tiled.correlate as tiled_correlate
    import napari_dvc_correct.tiled.points as tiled_points

    reference, deformed = pair
    seen = {}

    def tiled(*args, **keywords):
        seen.update(keywords, n_args=len(args))
        yield Progress("plan", 1, 1, "planned")
        return "tiled"

    monkeypatch.setattr(tiled_correlate, "correlate_tiled_iter", tiled)
    monkeypatch.setattr(tiled_points, "correlate_points_tiled_iter", tiled)
    run = RunOptions(workers=3, batch_shape=(2, 2, 2), device="cpu")
    assert run_to_completion(correlate_job(reference, deformed, PARAMS, run=run)) == "tiled"
    assert seen == {
        "mask": None,
        "batch_shape": (2, 2, 2),
        "max_memory": None,
        "workers": 3,
        "scheduler": None,
        "device": "cpu",
        "n_args": 3,
    }
    seen.clear()
    points = np.zeros((1, 3))
    assert run_to_completion(points_job(reference, deformed, points, PARAMS, run=run)) == "tiled"
    assert seen["workers"] == 3 and seen["n_args"] == 4
    with pytest.raises(ValueError, match="does not apply to a run out of core"):
        next(
            correlate_job(
                reference, deformed, PARAMS, grid=((8, 8, 8), (8, 8, 8), (2, 2, 2)), run=run
            )
        )
