"""The rule of the image pyramid (engine/correlation/pyramid_rule.py) on known answers."""

import math

import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.correlation.pyramid_rule import level_reach


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


def test_the_search_window_s_memory_is_that_of_the_coarsest_level_s_reach():
    from napari_dvc_correct.engine.correlation.pyramid_rule import search_window_bytes

    # no pyramid (radius 4 at full resolution): a 21³ subvolume searched ±4 spans 29 voxels
    flat = CorrelationParams(subvolume=21, step=8, search_radius=4)
    assert search_window_bytes(flat, (64, 64, 64)) == 64 * 29**3
    # radius 20 on a 41³ subvolume: two levels (factor 4): half max(4, 20 // 4) = 5,
    # radius ceil(20 / 4) + 1 = 6, span 2·5 + 1 + 2·6 = 23 binned voxels
    deep = CorrelationParams(subvolume=41, step=8, search_radius=20)
    assert search_window_bytes(deep, (256, 256, 256)) == 64 * 23**3
    # a larger radius never needs less
    wider = CorrelationParams(subvolume=41, step=8, search_radius=60)
    assert search_window_bytes(wider, (256, 256, 256)) >= search_window_bytes(deep, (256,) * 3)
