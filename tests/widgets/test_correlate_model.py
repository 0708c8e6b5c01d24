"""The Correlate panel's Qt-free model: checks, preview, estimates, POI read-out."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.field import DisplacementField, Status, grid_for_volume
from napari_dvc_correct.engine.params import CorrelationParams
from napari_dvc_correct.widgets import correlate_model as model


@pytest.mark.parametrize(
    "args, message",
    [
        (("a", (40, 40, 40), "a", (40, 40, 40)), "same layer"),
        (("a", (40, 40), "b", (40, 40, 40)), "2-D image"),
        (("a", (4, 40, 40, 40), "b", (40, 40, 40)), "4-D mode"),
        (("a", (40, 40, 40), "b", (40, 40, 41)), "differ in shape"),
        ((None, (40, 40, 40), "b", (40, 40, 40)), "choose a reference"),
    ],
)
def test_check_pair_messages(args, message):
    with pytest.raises(ValueError, match=message):
        model.check_pair(*args)


def test_check_mask():
    with pytest.raises(ValueError, match="empty"):
        model.check_mask(np.zeros((5, 5, 5)), (5, 5, 5))
    with pytest.raises(ValueError, match="shape"):
        model.check_mask(np.ones((5, 5, 4)), (5, 5, 5))
    assert model.check_mask(np.full((5, 5, 5), 3), (5, 5, 5)).dtype == bool


def test_make_params_auto_search_radius():
    params = model.make_params(21, 6, 2, 0)
    assert params.search_radius is None and params.order == 2
    with pytest.raises(ValueError, match="odd"):
        model.make_params(20, 6, 1, 0)


def test_grid_preview_matches_the_engine_grid():
    params = CorrelationParams(subvolume=15, step=8)
    points, box, n = model.grid_preview((64, 64, 64), params)
    origin, step, shape = grid_for_volume((64, 64, 64), 15, 8)
    assert n == np.prod(shape) == len(points)
    np.testing.assert_allclose(points[0], origin)
    corners = np.concatenate(box)
    assert np.ptp(corners, axis=0).tolist() == [14.0, 14.0, 14.0]
    # one rectangle per slice of the subvolume along each axis, each flat along its axis
    assert len(box) == 3 * 15
    flat_axes = [int(np.flatnonzero(np.ptp(rect, axis=0) == 0)[0]) for rect in box]
    assert [flat_axes.count(a) for a in range(3)] == [15, 15, 15]
    many, _, n_many = model.grid_preview(
        (200, 200, 200), CorrelationParams(subvolume=5, step=1), max_points=1000
    )
    assert len(many) <= 1000 < n_many


def test_estimates_grow_with_the_work_and_learn_from_runs(monkeypatch):
    monkeypatch.setitem(model._calibration, "seconds_per_voxel_iteration", 1e-7)
    small = model.estimate_run((64, 64, 64), CorrelationParams(subvolume=15, step=8), threads=2)
    large = model.estimate_run((64, 64, 64), CorrelationParams(subvolume=15, step=4), threads=2)
    assert large.n_points > small.n_points and large.seconds > small.seconds
    assert small.memory_bytes > 64**3 * 4 * 2  # at least the two float32 volumes
    assert "POIs" in small.text() and "memory" in small.text()
    # a run that took 10 times the estimate pulls the next estimate up
    model.record_timing(
        10 * small.seconds, (64, 64, 64), CorrelationParams(subvolume=15, step=8), threads=2
    )
    again = model.estimate_run((64, 64, 64), CorrelationParams(subvolume=15, step=8), threads=2)
    assert again.seconds > 2 * small.seconds


def test_poi_read_out():
    field = DisplacementField.zeros((7, 7, 7), (4, 4, 4), (3, 3, 3))
    field.u[1, 2, 0] = (0.5, -0.25, 1.0)
    field.status[1, 2, 0] = Status.MAX_ITERATIONS
    field.iterations[1, 2, 0] = 50
    assert model.nearest_node(field, (11.4, 15.3, 6.6)) == (1, 2, 0)
    assert model.nearest_node(field, (100, 7, 7)) is None
    values = model.describe_poi(field, (1, 2, 0))
    assert values["status"] == "max iterations" and values["iterations"] == 50
    assert values["magnitude"] == pytest.approx(np.sqrt(0.25 + 0.0625 + 1.0))
    text = model.poi_text(values, "uncorrected")
    assert "+0.500" in text and "max iterations" in text and "uncorrected" in text


def test_pair_job_runs_on_the_chosen_device_and_records_it():
    import numpy as np

    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.params import CorrelationParams
    from napari_dvc_correct.engine.progress import run_to_completion
    from napari_dvc_correct.widgets import correlate_model as model

    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=4),
        (32, 32, 32),
        synthetic.translation((0.5, 0.0, -0.5)),
    )
    job = model.CorrelationJob(
        volumes=[reference, deformed],
        params=CorrelationParams(subvolume=11, step=8),
        names=["g", "f"],
        device="cpu",
    )
    result = run_to_completion(model.run_job(job))
    field = result.fields[0][1]
    assert "CPU" in str(field.metadata["device"])
    assert np.nanmax(np.abs(field.u - [0.5, 0.0, -0.5])) < 0.05
