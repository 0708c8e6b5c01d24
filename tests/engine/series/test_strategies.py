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


def _series_volumes(field_of, seed):
    """States 0, 1, 2 of one textured sample, state k moved by ``field_of(k)`` (``U_0→k``),
    cut from a larger volume so that material enters the view as it would in a scan."""
    big = synthetic.textured_volume(tuple(n + 2 * MARGIN for n in SHAPE), 2.0, seed=seed)
    crop = tuple(slice(MARGIN, MARGIN + n) for n in SHAPE)
    volumes = [np.ascontiguousarray(big[crop])]
    for k in (1, 2):
        truth = field_of(k)
        moved = synthetic.deform_volume(big, lambda p, t=truth: t(np.asarray(p) - MARGIN))
        volumes.append(np.ascontiguousarray(moved[crop]))
    return volumes


@pytest.fixture(scope="module")
def states():
    return _series_volumes(_state_field, seed=11)


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


@pytest.mark.parametrize(
    ("strategy", "options"),
    [
        ("total", {"correct_total": True}),
        ("incremental", {"correct_total": True}),
        ("incremental", {"correct_increments": True}),
    ],
)
def test_the_uncorrected_totals_are_the_series_without_correction(states, strategy, options):
    """``uncorrected`` holds what the same series gives with no self-correction (total: each
    measured ``U_0→k``; incremental: the measured increments composed), node for node, and the
    summary's uncorrected residual is that series' residual."""
    plain = series(states, PARAMS, strategy=strategy)
    assert [a is b for a, b in zip(plain.totals, plain.uncorrected)] == [True, True]
    assert not plain.self_corrected
    corrected = series(
        states, PARAMS, strategy=strategy, correction_options={"max_passes": 1}, **options
    )
    assert corrected.self_corrected and len(corrected.uncorrected) == 2
    for k, (mine, theirs) in enumerate(zip(corrected.uncorrected, plain.totals), start=1):
        np.testing.assert_array_equal(mine.u, theirs.u)
        np.testing.assert_array_equal(mine.status, theirs.status)
        assert mine.metadata["series"]["uncorrected"] is True
        assert mine.metadata["series"]["state"] == k
    rows, plain_rows = corrected.summary(), plain.summary()
    for row, plain_row in zip(rows[1:], plain_rows[1:]):
        assert row["mean_gray_residual_uncorrected"] == pytest.approx(
            plain_row["mean_gray_residual"], rel=1e-12
        )


BAND_WIDTH, BAND_SLIP = 3.0, 3.0  # half-width and slip per state, voxels


def _band(k):
    """Known ``U_0→k`` that bends inside a subvolume: a narrow shear band and a shift."""
    return synthetic.shear_band(
        CENTER, width=BAND_WIDTH, slip=k * BAND_SLIP, shift=(0.6 * k, -0.4 * k, 0.8 * k)
    )


@pytest.fixture(scope="module")
def bending_states():
    return _series_volumes(_band, seed=5)


def test_where_the_field_bends_the_corrected_totals_beat_the_uncorrected(bending_states):
    """Incremental, merged totals corrected: each uncorrected and corrected total evaluated on
    its own pair (V0, Vk); in the band (a first-order subvolume cannot follow it) the corrected
    total is much closer to the known field, and its gray residual and accuracy index better."""
    from napari_dvc_correct.engine.correction.cleaning import clean
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields

    params = CorrelationParams(subvolume=15, step=5)
    result = series(
        bending_states,
        params,
        strategy="incremental",
        correct_total=True,
        correction_options={"max_passes": 1},
    )
    normal = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    for k, (corrected, uncorrected) in enumerate(zip(result.totals, result.uncorrected), 1):
        points = corrected.points.reshape(-1, 3)
        band = np.abs((points - CENTER) @ normal) < BAND_WIDTH
        truth = _band(k)(points)
        rmse = {
            name: float(np.sqrt(np.mean(np.sum((f.u.reshape(-1, 3) - truth)[band] ** 2, 1))))
            for name, f in (("uncorrected", uncorrected), ("corrected", corrected))
        }
        # measured (40³, 15³ subvolumes, one pass): band 0.38 -> 0.09, 0.76 -> 0.27 voxel
        assert rmse["uncorrected"] > 0.3 and rmse["corrected"] < 0.5 * rmse["uncorrected"], rmse
        fields = {
            "u": clean(uncorrected, fill_masked=True),
            "c": clean(corrected, fill_masked=True),
        }
        items = evaluate_fields(bending_states[0], bending_states[k], fields)
        assert items["c"].accuracy > items["u"].accuracy
        assert items["c"].mean_residual < 0.5 * items["u"].mean_residual
        info = corrected.metadata["series"]
        assert info["mean_gray_residual"] < info["mean_gray_residual_uncorrected"]
