"""The Correlate panel's Qt-free model: checks, preview, estimates, POI read-out."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import (
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)
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
    # a node the self-correction measured again is not shown as plainly "diverged"
    field.status[0, 0, 0] = Status.DIVERGED
    field.provenance[0, 0, 0] = Provenance.CORRECTED
    field.zncc[0, 0, 0] = 0.99998
    values = model.describe_poi(field, (0, 0, 0))
    assert values["status"] == "diverged in the first match, corrected since"


def test_pair_job_runs_on_the_chosen_device_and_records_it():
    import numpy as np

    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation.params import CorrelationParams
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


def test_run_points_job_equals_the_engine_and_finds_a_translation():
    from napari_dvc_correct.engine.correlation.correlate_points import correlate_points
    from napari_dvc_correct.engine.progress import Progress, run_to_completion
    from napari_dvc_correct.engine.synthetic import make_pair, textured_volume, translation

    shift = (1.25, -0.5, 0.75)
    pattern = lambda s: textured_volume(s, 2.0, seed=3)  # noqa: E731
    reference, deformed = make_pair(pattern, (40, 40, 40), translation(shift))
    params = CorrelationParams(subvolume=15, step=8)
    points = np.array([[12.0, 14.0, 20.0], [20.3, 20.0, 19.6], [27.0, 25.0, 13.0]])
    job = model.CorrelationJob(
        volumes=[reference, deformed],
        params=params,
        voxel_size=(2.0, 2.0, 2.0),
        offset=(1.0, 0.0, 0.0),
        names=["ref", "def"],
        device="cpu",
        unit="µm",
        points=points,
        points_layer="pois",
    )
    stages = []

    def collect():
        result = yield from model.run_job(job)
        return result

    generator = collect()
    while True:
        try:
            item = next(generator)
            stages.append(item.stage if isinstance(item, Progress) else None)
        except StopIteration as stop:
            result = stop.value
            break
    assert "IC-GN at the points" in stages and len(stages) > 2  # the guide's progress too
    ((source, field),) = result.fields
    assert source == "points"
    direct = correlate_points(reference, deformed, points, params, device="cpu")
    np.testing.assert_allclose(field.u, direct.u, atol=1e-9)
    np.testing.assert_array_equal(field.status, direct.status)
    np.testing.assert_allclose(field.u, np.broadcast_to(shift, (3, 3)), atol=0.02)
    assert field.metadata["points_layer"] == "pois" and field.metadata["unit"] == "µm"
    assert field.metadata["voxel_size"] == [2.0, 2.0, 2.0]
    assert run_to_completion(model.run_job(job)).fields[0][0] == "points"


def test_suggest_and_check_tiled(tmp_path):
    import dask.array as da

    small = np.zeros((8, 8, 8), np.float32)
    assert not model.suggest_tiled([small], memory=1 << 30)
    assert model.suggest_tiled([da.from_array(small, chunks=4)], memory=1 << 30)  # lazy
    assert model.suggest_tiled([small], memory=8 * 8 * 8 * 4 * 6)  # larger than half of it
    mapped = np.lib.format.open_memmap(tmp_path / "small.npy", "w+", np.float32, small.shape)
    assert model.is_lazy(mapped)  # read lazily by napari, yet small: no need to go out of core
    assert not model.suggest_tiled([mapped], memory=1 << 30)
    assert model.suggest_tiled([mapped], memory=8 * 8 * 8 * 4 * 6)
    assert model.check_tiled("pair", None, " auto ") is None
    assert model.check_tiled("pair", None, "2GB") == "2GB"
    with pytest.raises(ValueError):
        model.check_tiled("pair", None, "lots")
    assert model.check_tiled("total", None, "") is None  # a series on the grid: out of core
    with pytest.raises(ValueError, match="series at points of interest runs in memory"):
        model.check_tiled("incremental", np.zeros((1, 3)), "")
    assert model.check_tiled("pair", np.zeros((1, 3)), "1GB") == "1GB"  # points out of core


def test_automatic_thresholds_of_a_lazy_volume_read_only_the_lattice():
    import dask.array as da

    from napari_dvc_correct.engine.synthetic import two_phase_volume
    from napari_dvc_correct.widgets.evaluate_model import automatic_thresholds

    volume = two_phase_volume((40, 40, 40), seed=2)
    lazy = da.from_array(volume, chunks=20)
    np.testing.assert_array_equal(automatic_thresholds(lazy, 3), automatic_thresholds(volume, 3))


def test_a_series_result_carries_its_fields_as_shown_with_state_0():
    """The worker makes the series as its 4-D layers show it (state 0 without displacement
    first), so the panel's slot has nothing to compute; a pair has no series."""
    from napari_dvc_correct._sample_data import scan_series
    from napari_dvc_correct.engine.progress import run_to_completion
    from napari_dvc_correct.widgets._base import _result_fields

    volumes, _ = scan_series((40, 40, 40), slips=(0.0, 1.0, 2.0))
    job = model.CorrelationJob(
        volumes=list(volumes),
        params=CorrelationParams(subvolume=11, step=8),
        strategy="total",
        names=["s0", "s1", "s2"],
    )
    result = run_to_completion(model.run_job(job))
    states = [field for _, field in result.fields]
    assert len(result.series) == 3
    assert all(a is b for a, b in zip(result.series[1:], states))  # the same fields
    zero = result.series[0]
    assert zero.same_grid(states[0]) and not zero.u.any()
    assert (zero.status == 0).all() and zero.metadata["voxel_size"] == [1.0, 1.0, 1.0]
    ahead = _result_fields(result)  # what the worker computes the quantity on view of
    assert len(ahead) == 3 and all(a is b for a, b in zip(ahead, [*states, zero]))
    pair = model.CorrelationJob(volumes=list(volumes[:2]), params=job.params, names=["a", "b"])
    assert run_to_completion(model.run_job(pair)).series is None


def test_the_done_message_counts_each_state_and_hints_at_a_region_only_without_one():
    air = DisplacementField.zeros((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (4, 5, 5))
    air.status.reshape(-1)[:20] = Status.LOW_TEXTURE  # 20 of 100 nodes
    result = model.CorrelationResult(fields=[("rock", air)])
    message = model.done_message(result, region_given=False)
    assert message.startswith("Done: usable 80 of 100 nodes")
    assert "20 of 100 nodes (20 %) found no texture" in message and message.endswith("(Region).")
    assert "found no texture" not in model.done_message(result, region_given=True)
    series = model.CorrelationResult(fields=[("state 1", air), ("state 2", air)])
    assert "state 1: usable" in model.done_message(series, True)
