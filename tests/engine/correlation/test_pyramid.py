"""The per-level rule of the image pyramid (subvolume half-size and search radius)."""

import math

import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.correlation.pyramid import level_reach


def test_level_zero_keeps_the_run_s_subvolume_and_radius():
    params = CorrelationParams(subvolume=31, search_radius=23)
    assert level_reach(params, 0) == (1, 15, 23)
    # no radius given: max(8, M)
    assert level_reach(CorrelationParams(subvolume=21), 0).search_radius == 10
    assert level_reach(CorrelationParams(subvolume=9), 0).search_radius == 8


@pytest.mark.parametrize(
    "subvolume, radius, lev, half, coarse_radius",
    [
        (31, 15, 1, 7, 9),  # 15 // 2, ceil(15 / 2) + 1
        (31, 40, 2, 4, 11),  # 15 // 4 = 3 -> at least 4; ceil(40 / 4) + 1
        (41, 20, 2, 5, 6),
        (65, 64, 3, 4, 9),
    ],
)
def test_coarse_levels_bin_the_subvolume_and_the_radius(
    subvolume, radius, lev, half, coarse_radius
):
    reach = level_reach(CorrelationParams(subvolume=subvolume, search_radius=radius), lev)
    assert reach.factor == 2**lev
    assert reach.half == half
    assert reach.search_radius == coarse_radius
    # the binned search still covers the run's radius
    assert reach.factor * (reach.search_radius - 1) >= radius
    assert reach.half == max(4, (subvolume // 2) // 2**lev)
    assert reach.search_radius == math.ceil(radius / 2**lev) + 1


def test_a_negative_level_is_refused():
    with pytest.raises(ValueError, match="level must be >= 0"):
        level_reach(CorrelationParams(), -1)
