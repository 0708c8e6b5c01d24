"""The seed pass's jobs: every seed of the whole grid in exactly one batch box, with its region."""

from types import SimpleNamespace

import numpy as np

from napari_dvc_correct.engine.correlation.guided_repair import seed_axes
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.tiled import seeds

SHAPE = (60, 70, 80)
PARAMS = CorrelationParams(subvolume=15, step=5)  # a seed every 3 nodes


def _grid():
    origin = np.array([8.0, 8.0, 8.0])
    step = np.array([5.0, 5.0, 5.0])
    shape = tuple(int((n - 16) // 5) + 1 for n in SHAPE)  # nodes 8 .. n - 8
    return origin, step, shape


def test_every_seed_falls_in_one_job_whose_region_holds_it():
    origin, step, grid_shape = _grid()
    axes = seed_axes(grid_shape, 3)
    assert [a[0] for a in axes] == [0, 0, 0] and [a[-1] for a in axes] == [
        n - 1 for n in grid_shape
    ]
    assert axes[0].tolist() == [0, 3, 6, 8]
    z_boxes = [(0, 1), (1, 3), (3, grid_shape[0])]  # the second holds no seed
    batches = [
        (z, (0, grid_shape[1]), (x0, min(x0 + 7, grid_shape[2])))
        for z in z_boxes
        for x0 in range(0, grid_shape[2], 7)
    ]
    whole = SimpleNamespace(shift=np.zeros(3, np.int64), texture_std={1: 1.0})
    jobs, seed_flat, seed_shape = seeds.seed_jobs(
        batches, PARAMS, SHAPE, (origin, step, grid_shape), 1, whole, {"threads": 1}
    )
    assert seed_shape == [len(a) for a in axes]
    assert len(seed_flat) == np.prod(seed_shape)
    rows = np.concatenate([job.rows for job in jobs])
    assert sorted(rows.tolist()) == list(range(len(seed_flat)))  # each seed once
    for job in jobs:
        assert job.threads == 1 and job.levels == 1 and job.params is PARAMS
        index = np.stack(np.unravel_index(seed_flat[job.rows], grid_shape), -1)
        np.testing.assert_array_equal(job.centers, origin + step * index)
        half = PARAMS.subvolume // 2
        assert np.all(job.region_low <= job.centers.min(0) - half)
        assert np.all(job.centers.max(0) + half < job.region_high)
        assert np.all(job.region_low % 2 == 0)  # aligned on the binned volume (2**levels)
        assert np.all(job.region_low >= 0) and np.all(job.region_high <= SHAPE)
    assert len(jobs) == len(batches) - 2  # the boxes without a seed get no job
