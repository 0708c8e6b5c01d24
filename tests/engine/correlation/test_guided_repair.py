"""Seeds of the initial guess laid out on the whole POI grid, so a box of the grid (a tiled batch)
starts its POIs from the in-memory run's guesses."""

import heapq

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import _grid_centers
from napari_dvc_correct.engine.correlation.guided_repair import (
    _testable_seeds,
    is_good,
    neighbour_outliers,
    repair,
    seed_axes,
    seed_guesses,
)
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.correlation.pyramid import PyramidLevel
from napari_dvc_correct.engine.fields.field import Status, grid_for_volume

PARAMS = CorrelationParams(subvolume=11, step=4, search_radius=8)  # seeds every 3 POIs


def test_seed_axes_of_the_whole_grid_are_every_stride_and_the_last():
    axes = seed_axes((10, 7, 3), 3)
    for axis, expected in zip(axes, ([0, 3, 6, 9], [0, 3, 6], [0, 2])):
        np.testing.assert_array_equal(axis, expected)


@pytest.mark.parametrize("offset, shape", [((2, 0, 4), (6, 7, 6)), ((1, 1, 1), (1, 2, 2))])
def test_seed_axes_of_a_box_are_the_whole_grids_seeds_in_it(offset, shape):
    whole_shape = (10, 7, 10)
    whole = seed_axes(whole_shape, 3)
    box = seed_axes(shape, 3, (offset, whole_shape))
    for w, b, o, n in zip(whole, box, offset, shape):
        np.testing.assert_array_equal(b + o, w[(w >= o) & (w < o + n)])
    with pytest.raises(ValueError, match="exceeds the grid"):
        seed_axes((6, 7, 6), 3, ((5, 0, 0), whole_shape))


def test_only_seeds_with_their_whole_neighbourhood_in_the_box_are_tested():
    whole_shape = (10, 10, 10)  # seeds at 0, 3, 6, 9 on every axis
    testable, count = _testable_seeds(seed_axes(whole_shape, 3), whole_shape, 3, None)
    assert testable.all() and count == 64
    # a box from POI 2 to 9 on z (seeds 3, 6, 9: the first lacks seed 0), whole on y and x
    anchor = ((2, 0, 0), whole_shape)
    axes = seed_axes((8, 10, 10), 3, anchor)
    testable, count = _testable_seeds(axes, (8, 10, 10), 3, anchor)
    testable = testable.reshape(3, 4, 4)
    assert count == 64
    assert not testable[0].any() and testable[1:].all()


@pytest.fixture(scope="module")
def band():
    """A shear band (strongly non-affine), so each POI's guess depends on which seed it copies."""
    reference = synthetic.textured_volume((48, 48, 48), 2.0, seed=4)
    truth = synthetic.shear_band((24.0, 24.0, 24.0), width=6.0, slip=5.0, shift=(2.4, -3.1, 1.7))
    deformed = synthetic.deform_volume(reference, truth)
    level = PyramidLevel.build(1, reference, deformed, None, PARAMS.half, PARAMS.min_texture)
    grid = grid_for_volume(reference.shape, PARAMS.subvolume, PARAMS.step)
    centers, _ = _grid_centers(grid, reference.shape, PARAMS.half)
    shape = tuple(grid[2])
    guesses = seed_guesses(level, centers, shape, np.array([2, -3, 2]), 8, 1, PARAMS)
    return level, centers, shape, guesses.reshape(*shape, -1)


@pytest.mark.parametrize("offset, box", [((2, 3, 1), (6, 5, 7)), ((0, 4, 2), (5, 5, 7))])
def test_a_box_with_a_margin_gets_the_whole_grids_guesses(band, offset, box):
    level, centers, shape, whole = band
    window = tuple(slice(o, o + n) for o, n in zip(offset, box))
    index = np.arange(len(centers)).reshape(shape)[window].ravel()
    anchored = seed_guesses(
        level, centers[index], box, np.array([2, -3, 2]), 8, 1, PARAMS, anchor=(offset, shape)
    ).reshape(*box, -1)
    # the box's own POIs: one POI (stride // 2) in from its faces inside the whole grid
    core = tuple(
        slice(0 if o == 0 else 1, n if o + n == total else n - 1)
        for o, n, total in zip(offset, box, shape)
    )
    np.testing.assert_allclose(anchored[core], whole[window][core], rtol=0, atol=1e-12)
    # laid out on the box's own grid (before), the seeds and so the guesses differ
    own = seed_guesses(level, centers[index], box, np.array([2, -3, 2]), 8, 1, PARAMS)
    own = own.reshape(*box, -1)
    assert np.abs(own[core] - whole[window][core]).max() > 1e-3


def _one_at_a_time(level, centers, grid_shape, params, zncc, status, iterations, settings):
    """The repair as it was written before its matches were batched (first order, the
    settings' threshold), for comparison: one ``level.match`` call per re-match."""
    good = is_good(status, zncc, settings.min_zncc)
    good &= ~neighbour_outliers(params.reshape(-1, 3, 4)[:, :, 0], good, grid_shape)
    retry = np.isin(status, [int(Status.MASKED), int(Status.LOW_TEXTURE)])
    bad = ~good & ~retry & np.isin(status, [0, 1, 2, 3, 6, 7])
    grid_index = np.arange(len(centers)).reshape(grid_shape)
    offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]
    offsets.remove((0, 0, 0))
    heap = [(-zncc[i], i) for i in np.flatnonzero(good)]
    heapq.heapify(heap)
    attempts = np.zeros(len(centers), np.int64)
    most = np.where(status == 3, settings.repair_attempts_out_of_bounds, settings.repair_attempts)
    calls = 0
    while heap and bad.any():
        _, i = heapq.heappop(heap)
        iz, iy, ix = np.unravel_index(i, grid_shape)
        for a, b, c in offsets:
            jz, jy, jx = iz + a, iy + b, ix + c
            if not all(0 <= v < n for v, n in zip((jz, jy, jx), grid_shape)):
                continue
            j = grid_index[jz, jy, jx]
            if not bad[j] or attempts[j] >= most[j]:
                continue
            attempts[j] += 1
            guess = params[i].reshape(3, 4).copy()
            guess[:, 0] += guess[:, 1:4] @ (centers[j] - centers[i]).astype(np.float64)
            trial = np.ascontiguousarray(guess.reshape(1, -1))
            t_zncc, t_status, t_its = level.match(centers[j : j + 1], trial, 1, settings)
            calls += 1
            if t_status[0] in (0, 1) and t_zncc[0] >= settings.min_zncc:
                params[j], zncc[j], status[j], iterations[j] = (
                    trial[0],
                    t_zncc[0],
                    t_status[0],
                    t_its[0],
                )
                bad[j] = False
                heapq.heappush(heap, (-zncc[j], j))
    return int(bad.sum()), calls


def test_the_batched_repair_repairs_exactly_as_one_match_at_a_time(band):
    """Re-matches computed ahead, many per call, give the one-at-a-time repair's result."""
    level, centers, shape, guesses = band
    params = np.ascontiguousarray(guesses.reshape(len(centers), -1))
    params[::3, 0] += 6.0  # a third of the POIs start far off: they fail and are repaired
    zncc, status, iterations = level.match(centers, params, 1, PARAMS)
    arrays = [a.copy() for a in (params, zncc, status, iterations)]
    left, calls = _one_at_a_time(level, centers, shape, *arrays, PARAMS)
    assert calls > 10 and np.sum(np.any(arrays[0] != params, axis=1)) > 10  # POIs repaired
    for batch in (1, 7, 64):
        other = [a.copy() for a in (params, zncc, status, iterations)]
        counts = {}
        assert repair(level, centers, shape, *other, 1, PARAMS, batch=batch, counts=counts) == left
        for a, b in zip(arrays, other):
            np.testing.assert_array_equal(a, b)
        assert counts["repair_trials"] == calls
        assert counts["repair_matches"] >= calls
        assert counts["repair_calls"] < calls


class _RecordingLevel:
    """A level whose matches always succeed at ZNCC 0.99 and record the centres asked for."""

    def __init__(self, shape, half):
        self.reference = np.zeros(shape, np.float32)
        self.half = half
        self.asked = []

    def match(self, centers, warps, order, params):
        self.asked.append(np.array(centers))
        n = len(centers)
        return np.full(n, 0.99), np.zeros(n, np.int64), np.ones(n, np.int64)


def test_the_repair_never_matches_a_poi_whose_subvolume_leaves_the_volume():
    # a given grid (an imported field corrected with a larger subvolume) has nodes whose
    # subvolume does not fit; they are OUT_OF_BOUNDS, and re-matching them read outside the
    # volume (a segfault on a 48³ pair, subvolume 31, nodes 8..40)
    half, shape = 15, (48, 48, 48)
    axis = np.arange(8, 41, 4)
    grid_shape = (len(axis),) * 3
    centers = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    fits = np.all((centers >= half) & (centers <= 47 - half), axis=1)
    status = np.where(fits, int(Status.CONVERGED), int(Status.OUT_OF_BOUNDS)).astype(np.int64)
    status[np.flatnonzero(fits)[::4]] = int(Status.DIVERGED)  # some that fit failed too
    zncc = np.where(status == int(Status.CONVERGED), 0.95, np.nan)
    params = np.zeros((len(centers), 12))
    level = _RecordingLevel(shape, half)
    repair(level, centers, grid_shape, params, zncc, status, np.zeros(len(centers), np.int64),
           1, PARAMS)  # fmt: skip
    asked = np.concatenate(level.asked)
    assert len(asked) > 0  # the failed POIs that fit were re-matched
    assert np.all((asked >= half) & (asked <= 47 - half))
    assert np.all(status[~fits] == int(Status.OUT_OF_BOUNDS))
