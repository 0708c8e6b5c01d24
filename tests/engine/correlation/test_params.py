"""CorrelationParams: the documented defaults, clear refusals of bad values, a lossless round trip."""

import dataclasses
import json

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams


def test_defaults():
    params = CorrelationParams()
    assert params.subvolume == 31
    assert params.half == 15
    assert params.step == 8
    assert params.order == 1
    assert params.search_radius is None
    assert params.max_iterations == 50
    assert params.tolerance == 1e-3
    assert params.min_mask_fraction == 0.5
    assert params.min_texture == 0.05
    assert params.min_zncc == 0.5
    assert params.batch_size == 256
    # issue 10/14: the noise stop and the rules correlate used to hide
    assert params.noise_tolerance == 0.1
    assert params.min_max_update == 4.0
    assert params.median_test_min_pois == 9
    assert (params.repair_attempts, params.repair_attempts_out_of_bounds) == (3, 1)


@pytest.mark.parametrize(
    ("subvolume", "search_radius", "effective"),
    [(31, None, 15), (11, None, 8), (61, None, 30), (31, 3, 3), (11, 0, 0)],
)
def test_effective_search_radius(subvolume, search_radius, effective):
    # None: max(8, subvolume // 2); an explicit radius (0 included) is kept
    params = CorrelationParams(subvolume=subvolume, search_radius=search_radius)
    assert params.effective_search_radius == effective
    assert isinstance(params.effective_search_radius, int)


def test_numpy_integers_are_accepted():
    params = CorrelationParams(subvolume=np.int64(21), step=np.int32(4), search_radius=np.int64(6))
    assert params.half == 10
    assert params.effective_search_radius == 6


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"subvolume": 20}, r"subvolume must be odd \(2M\+1\), got 20"),
        ({"subvolume": 3}, "subvolume must be an odd integer >= 5, got 3"),
        ({"subvolume": 21.0}, "subvolume must be an odd integer >= 5, got 21.0"),
        ({"step": 0}, "step must be an integer >= 1, got 0"),
        ({"step": 2.5}, "step must be an integer >= 1, got 2.5"),
        ({"order": 3}, "order must be 1 or 2, got 3"),
        ({"search_radius": -1}, "search_radius must be an integer >= 0, got -1"),
        ({"search_radius": 4.5}, "search_radius must be an integer >= 0, got 4.5"),
        ({"max_iterations": 0}, "max_iterations must be >= 1, got 0"),
        ({"tolerance": -1e-3}, "tolerance must be > 0, got -0.001"),
        ({"tolerance": 0.0}, "tolerance must be > 0, got 0.0"),
        ({"tolerance": float("nan")}, "tolerance must be > 0, got nan"),
        ({"min_mask_fraction": 0.0}, r"min_mask_fraction must be in \(0, 1\], got 0.0"),
        ({"min_mask_fraction": 1.5}, r"min_mask_fraction must be in \(0, 1\], got 1.5"),
        ({"min_texture": 1.0}, r"min_texture must be in \[0, 1\), got 1.0"),
        ({"min_texture": -0.1}, r"min_texture must be in \[0, 1\), got -0.1"),
        ({"min_zncc": 1.2}, r"min_zncc must be in \[-1, 1\], got 1.2"),
        ({"min_zncc": float("nan")}, r"min_zncc must be in \[-1, 1\], got nan"),
        ({"batch_size": 0}, "batch_size must be >= 1, got 0"),
        ({"noise_tolerance": 1.0}, r"noise_tolerance must be in \[0, 1\), got 1.0"),
        ({"min_max_update": 0.0}, "min_max_update must be > 0 voxels, got 0.0"),
        ({"repair_attempts": -1}, "repair_attempts must be an integer >= 0, got -1"),
        ({"median_test_min_pois": 2.5}, "median_test_min_pois must be an integer >= 0, got 2.5"),
    ],
)
def test_bad_values_are_refused_with_the_rule_and_the_value(changes, message):
    with pytest.raises(ValueError, match=message):
        CorrelationParams(**changes)


def test_every_problem_is_reported_at_once():
    with pytest.raises(ValueError) as info:
        CorrelationParams(subvolume=20, step=0, order=3)
    text = str(info.value)
    assert "subvolume must be odd" in text
    assert "step must be" in text
    assert "order must be" in text
    assert text.count(";") == 2


def test_boundary_values_are_accepted():
    params = CorrelationParams(
        subvolume=5,
        step=1,
        order=2,
        search_radius=0,
        max_iterations=1,
        min_mask_fraction=1.0,
        min_texture=0.0,
        min_zncc=-1.0,
        batch_size=1,
    )
    assert params.half == 2


def test_frozen_and_replace_validates():
    params = CorrelationParams(subvolume=21)
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.step = 4
    changed = params.replace(step=4)
    assert (changed.subvolume, changed.step) == (21, 4)
    assert params.step == 8  # the original is unchanged
    with pytest.raises(ValueError, match="step must be"):
        params.replace(step=0)


def test_round_trip_through_a_dict_and_json():
    params = CorrelationParams(subvolume=21, step=5, order=2, search_radius=12, tolerance=1e-5)
    values = params.to_dict()
    assert values["subvolume"] == 21 and values["search_radius"] == 12
    assert set(values) == {f.name for f in dataclasses.fields(CorrelationParams)}
    assert CorrelationParams.from_dict(values) == params
    # through JSON (how a field's metadata stores them)
    assert CorrelationParams.from_dict(json.loads(json.dumps(values))) == params


def test_from_dict_ignores_unknown_keys_and_fills_missing_ones():
    params = CorrelationParams.from_dict({"subvolume": 25, "engine_version": "0.1", "other": 3})
    assert params == CorrelationParams(subvolume=25)
    with pytest.raises(ValueError, match="subvolume must be odd"):
        CorrelationParams.from_dict({"subvolume": 24})


def test_the_subvolume_window_is_a_gaussian_truncated_at_three_std():
    """Voxels farther than ``WINDOW_TRUNCATE`` std (3) from the POI weigh 0, the others the
    Gaussian's weight: on 15³ under std 3 that drops 19 % of the voxels (652 of 3 375, the
    box's corners beyond 9 voxels) and 0.8 % of the weight; a window of std 4.5 reaches past
    the corners (7·√3 ≈ 12.1 voxels) and keeps them all."""
    from napari_dvc_correct.engine.correlation.params import WINDOW_TRUNCATE, gaussian_window

    assert WINDOW_TRUNCATE == 3.0
    weights = CorrelationParams(subvolume=15, window=3.0).subvolume_weights()
    whole = gaussian_window(7, 3.0)
    r = np.arange(-7, 8)
    r2 = r[:, None, None] ** 2 + r[None, :, None] ** 2 + r[None, None, :] ** 2
    assert np.array_equal(weights[r2 <= 81], whole[r2 <= 81])
    assert np.all(weights[r2 > 81] == 0.0) and np.sum(r2 > 81) == 652
    assert 1.0 - weights.sum() / whole.sum() == pytest.approx(0.0081, abs=1e-4)
    wide = CorrelationParams(subvolume=15, window=4.5).subvolume_weights()
    assert np.array_equal(wide, gaussian_window(7, 4.5))
    assert CorrelationParams(subvolume=15).subvolume_weights() is None
    with pytest.raises(ValueError, match="radius"):
        gaussian_window(7, 3.0, 0.0)
