"""Points of interest out of core: the in-memory points result, reading only the regions the
points need (groups of points, each region read once), with the memory refused up front."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate_points import correlate_points
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.io.lazy import ArrayVolume
from napari_dvc_correct.tiled.memory import MemoryBudgetError
from napari_dvc_correct.tiled.points import correlate_points_tiled, correlate_points_tiled_iter

GRADIENT = np.array([[0.02, 0.0, 0.01], [0.0, -0.01, 0.0], [0.0, 0.0, 0.015]])
# fine enough that a converged answer does not depend on IC-GN's starting guess
PARAMS = CorrelationParams(subvolume=15, step=6, tolerance=1e-5)


class CountingVolume(ArrayVolume):
    """A lazy volume that records the regions read."""

    def __init__(self, array) -> None:
        super().__init__(array)
        self.regions = []

    def read_region(self, slices):
        self.regions.append(slices)
        return super().read_region(slices)


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume((46, 46, 150), 2.0, seed=5)
    truth = synthetic.affine(GRADIENT, np.array(reference.shape) / 2, shift=(1.5, -2.2, 0.8))
    deformed = synthetic.deform_volume(reference, truth)
    rng = np.random.default_rng(2)
    points = np.column_stack(
        [rng.uniform(9, 37, 60), rng.uniform(9, 37, 60), rng.uniform(9, 141, 60)]
    )
    points[0] = (2.0, 20.0, 20.0)  # too near the border: OUT_OF_BOUNDS in both
    return reference, deformed, truth, points


def test_points_out_of_core_give_the_in_memory_result(pair):
    reference, deformed, truth, points = pair
    memory = correlate_points(reference, deformed, points, PARAMS)
    lazy_f = CountingVolume(deformed)
    tiled = correlate_points_tiled(
        ArrayVolume(reference), lazy_f, points, PARAMS, group_voxels=32, batch_shape=4
    )
    np.testing.assert_array_equal(tiled.status, memory.status)
    assert tiled.status[0] == Status.OUT_OF_BOUNDS
    good = memory.valid
    assert good.sum() > 50
    assert np.max(np.abs(tiled.u[good] - memory.u[good])) < 1e-4
    assert np.max(np.abs(tiled.zncc[good] - memory.zncc[good])) < 1e-5
    expected = synthetic.sample_displacement(truth, points[good])
    assert np.max(np.abs(tiled.u[good] - expected)) < 0.02
    assert tiled.metadata["noise"]["source"] == memory.metadata["noise"]["source"] == "points"
    info = tiled.metadata["tiled"]
    assert info["groups"] > 1
    # the groups read regions, not the volume: none of them is the whole scan
    assert info["largest_region_voxels"] < reference.size
    group_reads = lazy_f.regions[-info["groups"] :]
    assert all(
        np.prod([s.stop - s.start for s in region]) < reference.size for region in group_reads
    )


def test_masked_points_out_of_core_as_in_memory(pair):
    reference, deformed, _, points = pair
    mask = np.zeros(reference.shape, bool)
    mask[:, :, :80] = True  # the points beyond x ~ 80 lie outside the material
    memory = correlate_points(reference, deformed, points, PARAMS, mask=mask)
    tiled = correlate_points_tiled(reference, deformed, points, PARAMS, mask=mask, group_voxels=32)
    np.testing.assert_array_equal(tiled.status, memory.status)
    assert (memory.status == Status.MASKED).sum() > 10
    good = memory.valid
    assert np.max(np.abs(tiled.u[good] - memory.u[good])) < 1e-4


def test_too_little_memory_is_refused_before_any_point_is_matched(pair):
    reference, deformed, _, points = pair
    lazy_g = CountingVolume(reference)
    with pytest.raises(MemoryBudgetError, match="matching one point"):
        correlate_points_tiled(lazy_g, deformed, points, PARAMS, max_memory="1MB")
    assert lazy_g.regions == []


def test_bad_points_get_the_in_memory_messages(pair):
    reference, deformed, _, _ = pair
    with pytest.raises(ValueError, match="shape"):
        correlate_points_tiled(reference, deformed, np.zeros((4, 2)), PARAMS)
    with pytest.raises(ValueError, match="move the points"):
        correlate_points_tiled(reference, deformed, np.zeros((3, 3)), PARAMS)


def test_closing_the_run_stops_it(pair):
    """Closing the generator after the first group stops the other groups (cancel)."""
    reference, deformed, _, points = pair
    lazy_g = CountingVolume(reference)
    run = correlate_points_tiled_iter(
        lazy_g, deformed, points, PARAMS, group_voxels=16, workers=1, batch_shape=4
    )
    for report in run:
        if report.stage == "plan" and "groups of points" in report.message:
            groups = int(report.message.split()[0])
            before = len(lazy_g.regions)
        if report.stage == "IC-GN" and report.message.startswith("group 1 of"):
            break
    run.close()
    assert groups > 4
    assert len(lazy_g.regions) - before <= 2  # the first group (and one already started)


def test_a_distributed_cluster_gives_the_local_points(pair):
    """The groups travel to worker processes (pickled) and come back with the local answer."""
    import distributed

    reference, deformed, _, points = pair
    subset = points[:20]
    local = correlate_points_tiled(reference, deformed, subset, PARAMS, group_voxels=32)
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
    ) as cluster:
        remote = correlate_points_tiled(
            ArrayVolume(reference),
            ArrayVolume(deformed),
            subset,
            PARAMS,
            group_voxels=32,
            scheduler=cluster.scheduler_address,
        )
    assert remote.metadata["tiled"]["scheduler"] == cluster.scheduler_address
    np.testing.assert_array_equal(remote.status, local.status)
    np.testing.assert_allclose(remote.u, local.u, rtol=0, atol=1e-9)
