"""Scan series (engine/series/strategies.py): total and incremental strategies against known fields."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.progress import Progress
from napari_dvc_correct.engine.series.strategies import series, series_iter

SHAPE = (40, 40, 40)
MARGIN = 12
GRADIENT = np.array([[0.04, 0.0, 0.02], [0.0, -0.02, 0.0], [0.01, 0.0, 0.03]])
SHIFT = np.array([1.3, -2.1, 2.6])
CENTER = np.array(SHAPE) / 2
PARAMS = CorrelationParams(subvolume=15, step=6)


def _state_field(k):
    """Known total displacement U_0→k: k times an affine step."""
    return synthetic.affine(k * GRADIENT, CENTER, k * SHIFT)


@pytest.fixture(scope="module")
def states():
    big = synthetic.textured_volume(tuple(n + 2 * MARGIN for n in SHAPE), 2.0, seed=11)
    crop = tuple(slice(MARGIN, MARGIN + n) for n in SHAPE)
    volumes = [np.ascontiguousarray(big[crop])]
    for k in (1, 2):
        truth = _state_field(k)
        moved = synthetic.deform_volume(big, lambda p, t=truth: t(np.asarray(p) - MARGIN))
        volumes.append(np.ascontiguousarray(moved[crop]))
    return volumes


def _rmse(field, truth):
    error = field.displacement - truth(field.points)
    good = field.valid.reshape(-1)
    return float(np.sqrt(np.mean(error[good] ** 2))), float(good.mean())


@pytest.mark.parametrize("strategy", ["incremental", "total"])
def test_both_strategies_recover_the_total_displacement(states, strategy):
    result = series(states, PARAMS, strategy=strategy)
    assert len(result.totals) == 2
    assert len(result.increments) == (2 if strategy == "incremental" else 0)
    for k, total in enumerate(result.totals, start=1):
        rmse, valid = _rmse(total, _state_field(k))
        assert valid > 0.9
        assert rmse < 0.05, (strategy, k, rmse)
        assert np.max(np.abs(total.u[total.valid] - 0)) > 2.0  # the fields are not trivial
        assert total.metadata["series"]["state"] == k
        assert total.origin == result.totals[0].origin
    rows = result.summary()
    assert [row["state"] for row in rows] == [0, 1, 2]
    assert rows[2]["mean_displacement"] > rows[1]["mean_displacement"] > 0
    assert rows[2]["mean_gray_residual"] < 0.05 * float(np.std(states[0]))


def test_incremental_superposition_composes_rather_than_adds(states):
    result = series(states, PARAMS, strategy="incremental")
    first, second = result.increments
    # the plain sum of the increments at the same node misses the displaced-position term
    summed = first.u + second.u
    truth = _state_field(2)(first.points).reshape(first.u.shape)
    good = first.valid & second.valid
    sum_error = np.sqrt(np.mean((summed - truth)[good] ** 2))
    composed_error, _ = _rmse(result.totals[1], _state_field(2))
    assert sum_error > 3 * composed_error
    assert sum_error > 0.05


def test_correcting_the_merged_total_records_its_passes(states):
    progress = []
    generator = series_iter(
        states[:2],
        PARAMS,
        strategy="incremental",
        correct_total=True,
        correction_options={"max_passes": 1},
    )
    while True:
        try:
            progress.append(next(generator))
        except StopIteration as stop:
            result = stop.value
            break
    assert all(isinstance(p, Progress) for p in progress)
    assert any("correction" in p.stage for p in progress)
    total = result.totals[0]
    assert "correction_passes" in total.metadata
    assert total.metadata["series"]["corrected_total"] is True
    rmse, _ = _rmse(total, _state_field(1))
    assert rmse < 0.05


def test_bad_input_is_refused(states):
    with pytest.raises(ValueError, match="at least 2"):
        series(states[:1], PARAMS)
    with pytest.raises(ValueError, match="strategy"):
        series(states, PARAMS, strategy="sideways")
    with pytest.raises(ValueError, match="same shape"):
        series([states[0], states[1][:-1]], PARAMS)


def test_incremental_series_at_points_follows_the_points(states):
    """Each increment measured where the points are in the previous state and added: the
    total at the first state's points is the known U_0→2, its gradient the product rule's."""
    points = np.array([[20.0, 20.0, 20.0], [15.5, 22.25, 18.0], [24.0, 17.0, 21.5]])
    result = series(states, PARAMS, strategy="incremental", points=points)
    truth = _state_field(2)
    total = result.totals[1]
    np.testing.assert_array_equal(total.points, points)
    assert total.valid.all()
    assert np.abs(total.u - truth(points)).max() < 0.05
    np.testing.assert_allclose(total.gradient, np.broadcast_to(2 * GRADIENT, (3, 3, 3)), atol=5e-3)
    increment = result.increments[1]
    np.testing.assert_allclose(increment.points, points + _state_field(1)(points), atol=0.05)
    with pytest.raises(ValueError, match="self-corrected"):
        series(states, PARAMS, points=points, correct_total=True)
    with pytest.raises(ValueError, match="total strategy"):
        series(states, PARAMS, points=points, mask=np.ones(SHAPE, bool))
