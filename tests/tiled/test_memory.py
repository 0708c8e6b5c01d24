"""Regions and memory of tiled correlation: sizes in and out, halos, the peak estimate, the batch."""

import math

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import grid_for_volume
from napari_dvc_correct.tiled.memory import (
    BYTES_PER_FIELD_POINT,
    BYTES_PER_HELD_POINT,
    BYTES_PER_SEED_POINT,
    COARSE_PREFILTER_MARGIN,
    PREFILTER_MARGIN,
    SHIFT_BLOCK_VOXELS,
    SPLINE_SUPPORT,
    STRAIN_ALLOWANCE,
    MemoryBudgetError,
    available_memory,
    choose_batch_shape,
    estimate_peak_memory,
    format_bytes,
    halo,
    parse_memory,
)

PARAMS = CorrelationParams(subvolume=31, step=8)  # half 15, search radius max(8, 15) = 15


# --- parse_memory / format_bytes ---------------------------------------------------------------
@pytest.mark.parametrize(
    ("size", "expected"),
    [
        ("2GB", 2 * 10**9),
        ("512 MiB", 512 * 2**20),
        ("1.5GiB", 3 * 2**29),
        ("512M", 512 * 10**6),
        (" 2 gb ", 2 * 10**9),
        ("100", 100),
        (4096, 4096),
        (np.int64(2**33), 2**33),
        (1.5e9, 1_500_000_000),
    ],
)
def test_parse_memory(size, expected):
    value = parse_memory(size)
    assert value == expected
    assert type(value) is int


@pytest.mark.parametrize("size", ["lots", "2 parsecs", "", "   ", "GB", "MiB"])
def test_parse_memory_refuses_what_is_not_a_size(size):
    with pytest.raises(ValueError, match="is not a memory size: use e.g. 2GB"):
        parse_memory(size)


@pytest.mark.parametrize("size", [0, -5, "0", "-1GB", "0 MiB"])
def test_parse_memory_refuses_sizes_that_are_not_positive(size):
    with pytest.raises(ValueError, match="a memory size must be > 0"):
        parse_memory(size)


@pytest.mark.parametrize(
    ("n", "text"),
    [
        (0, "0 B"),
        (1023, "1023 B"),
        (1536, "1.50 KiB"),
        (5 * 2**20, "5.00 MiB"),
        (3 * 2**30 + 2**29, "3.50 GiB"),
        (2 * 2**40, "2.00 TiB"),
        (2**50, "1024.00 TiB"),
    ],
)
def test_format_bytes(n, text):
    assert format_bytes(n) == text


def test_format_and_parse_agree():
    for n in (2**20, 3 * 2**30, 7 * 2**30 + 2**29):
        assert parse_memory(format_bytes(n)) == n


def test_available_memory_is_a_positive_int():
    available = available_memory()
    assert isinstance(available, int) and available > 0


# --- halo --------------------------------------------------------------------------------------
def test_halo_at_full_resolution():
    reach_g, reach_f = halo(PARAMS, 0)
    # G: the subvolume (15), one voxel of rounding and the prefilter margin
    assert reach_g == 15 + 1 + PREFILTER_MARGIN
    # F: the subvolume strained by 25 % (ceil(18.75) = 19), the search radius, the spline taps
    assert reach_f == 19 + 15 + 1 + SPLINE_SUPPORT + PREFILTER_MARGIN


def test_halo_with_one_pyramid_level():
    # level 1 (factor 2): half 7, radius ceil(15 / 2) + 1 = 9, rounding 2·2, margin 6 binned voxels
    reach_g, reach_f = halo(PARAMS, 1)
    assert reach_g == 2 * (7 + 1 + COARSE_PREFILTER_MARGIN) + 4
    assert reach_f == 2 * (9 + 9 + 1 + SPLINE_SUPPORT + COARSE_PREFILTER_MARGIN) + 4
    assert (reach_g, reach_f) >= halo(PARAMS, 0)


def test_halo_grows_with_the_search_radius_and_the_subvolume():
    reach_g, reach_f = halo(PARAMS, 0)
    wider = halo(PARAMS.replace(search_radius=30), 0)
    assert wider == (reach_g, reach_f + 15)  # the search reaches into F only
    larger = halo(PARAMS.replace(subvolume=41, search_radius=15), 0)
    assert larger[0] == reach_g + 5
    assert larger[1] == reach_f + (25 - 19)  # the strained half: ceil(20 · 1.25) = 25
    deeper = [halo(PARAMS.replace(search_radius=r), 0)[1] for r in (8, 16, 32, 64)]
    assert deeper == sorted(deeper) and len(set(deeper)) == 4


# --- estimate_peak_memory ----------------------------------------------------------------------
SHAPE = (256, 256, 256)


def test_without_workers_the_estimate_is_the_fixed_part():
    grid = grid_for_volume(SHAPE, PARAMS.subvolume, PARAMS.step)
    points = int(np.prod(grid[2]))
    for dtype, itemsize in ((np.uint8, 1), (np.uint16, 2), (np.float32, 4)):
        per_point = BYTES_PER_FIELD_POINT + BYTES_PER_SEED_POINT + BYTES_PER_HELD_POINT
        fixed = points * per_point + SHIFT_BLOCK_VOXELS * (2 * (4 + itemsize) + 8)
        assert estimate_peak_memory(SHAPE, dtype, PARAMS, (4, 4, 4), workers=0) == fixed


def test_estimate_is_linear_in_the_workers():
    one, two, three = (
        estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4), workers=w) for w in (1, 2, 3)
    )
    fixed = estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4), workers=0)
    batch = one - fixed
    assert batch > 0
    assert two == fixed + 2 * batch
    assert three == fixed + 3 * batch


def test_estimate_grows_with_batch_workers_shift_mask_and_dtype():
    base = estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4))
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (8, 8, 8)) > base
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 8)) > base
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4), workers=2) > base
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4), shift=(20, 0, 0)) > base
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4), masked=True) > base
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (4, 4, 4), margin=1) > base
    assert estimate_peak_memory(SHAPE, np.float32, PARAMS, (4, 4, 4)) > base
    # a batch larger than the grid is the whole grid
    grid_shape = grid_for_volume(SHAPE, PARAMS.subvolume, PARAMS.step)[2]
    whole = estimate_peak_memory(SHAPE, np.uint16, PARAMS, grid_shape)
    assert estimate_peak_memory(SHAPE, np.uint16, PARAMS, (999, 999, 999)) == whole
    # the paper's workload: far beyond one batch of a few POIs, far below the whole volume
    paper = CorrelationParams(subvolume=141, step=10)
    need = estimate_peak_memory((2000, 2000, 3000), np.uint16, paper, (8, 8, 8))
    assert 1 << 30 < need < 2000 * 2000 * 3000 * 4


# --- choose_batch_shape ------------------------------------------------------------------------
def test_chosen_batch_is_the_largest_that_fits_the_budget():
    shape = (512, 512, 512)
    small = choose_batch_shape(shape, np.uint16, PARAMS, 1 << 30, workers=2)
    large = choose_batch_shape(shape, np.uint16, PARAMS, 4 << 30, workers=2)
    assert np.prod(small) < np.prod(large)
    for budget, batch in ((1 << 30, small), (4 << 30, large)):
        assert len(set(batch)) == 1  # cubic (the grid is larger than the batch here)
        assert estimate_peak_memory(shape, np.uint16, PARAMS, batch, workers=2) <= budget
        bigger = tuple(b + 1 for b in batch)
        assert estimate_peak_memory(shape, np.uint16, PARAMS, bigger, workers=2) > budget
    # more workers share the same budget: smaller batches
    assert np.prod(choose_batch_shape(shape, np.uint16, PARAMS, 4 << 30, workers=4)) < np.prod(
        large
    )


def test_a_generous_budget_gives_the_whole_grid():
    grid_shape = tuple(grid_for_volume(SHAPE, PARAMS.subvolume, PARAMS.step)[2])
    assert choose_batch_shape(SHAPE, np.uint16, PARAMS, 1 << 50) == grid_shape


def test_refuses_when_not_even_one_poi_fits():
    one = estimate_peak_memory(SHAPE, np.uint16, PARAMS, (1, 1, 1), workers=2)
    assert choose_batch_shape(SHAPE, np.uint16, PARAMS, one, workers=2) == (1, 1, 1)
    with pytest.raises(
        MemoryBudgetError, match="even one POI per batch needs an estimated"
    ) as info:
        choose_batch_shape(SHAPE, np.uint16, PARAMS, one - 1, workers=2)
    assert format_bytes(one) in str(info.value)
    assert "2 concurrent batch(es)" in str(info.value)
    # a bad input for the command line (ValueError), and a memory error for callers
    assert isinstance(info.value, ValueError) and isinstance(info.value, MemoryError)


# --- the halo and the engine's pyramid ---------------------------------------------------------
def _engine_levels(monkeypatch, params, size):
    """Each pyramid level's subvolume half-size and the coarsest level's search radius, as the
    engine's correlation uses them on a ``size``³ pair."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation import correlate as engine
    from napari_dvc_correct.engine.progress import run_to_completion

    halves, radii = {}, {}
    build_level = engine.build_level
    search = engine.seed_guesses

    def recording_level(lev, *args):
        level = build_level(lev, *args)
        halves[lev] = level.half
        return level

    def recording_search(level, centers, grid_shape, shift, radius, *args, **kwargs):
        lev = int(round(math.log2(level.factor)))
        halves[lev], radii[lev] = level.half, radius
        return search(level, centers, grid_shape, shift, radius, *args, **kwargs)

    monkeypatch.setattr(engine, "build_level", recording_level)
    monkeypatch.setattr(engine, "seed_guesses", recording_search)
    reference = synthetic.textured_volume((size,) * 3, feature_size=2.0, seed=2)
    deformed = synthetic.deform_volume(reference, synthetic.translation((1.5, -2.0, 0.5)))
    matched, fine = run_to_completion(engine.match_iter(reference, deformed, params))
    halves[0] = fine.half
    return matched.metadata["pyramid_levels"], halves, radii


@pytest.mark.parametrize(
    "subvolume, radius, size, levels",
    [(15, 4, 40, 0), (19, 12, 48, 1), (21, None, 48, 1), (41, 20, 84, 2)],
)
def test_the_halo_covers_exactly_what_the_engine_reads(
    monkeypatch, subvolume, radius, size, levels
):
    params = CorrelationParams(subvolume=subvolume, step=24, search_radius=radius)
    engine_levels, halves, radii = _engine_levels(monkeypatch, params, size)
    assert engine_levels == levels
    assert sorted(halves) == list(range(levels + 1))
    assert list(radii) == [levels]  # the integer search runs at the coarsest level only
    reach_g, reach_f = halo(params, levels)
    need_g, need_f = [], []
    for lev, half in halves.items():
        f = 2**lev
        rounding = 0 if lev == 0 else 2 * f
        margin = PREFILTER_MARGIN if lev == 0 else COARSE_PREFILTER_MARGIN
        search = radii.get(lev, math.ceil(params.effective_search_radius / f) + (lev > 0))
        need_g.append(f * (half + 1 + margin) + rounding)
        strained = math.ceil(half * (1 + STRAIN_ALLOWANCE))
        need_f.append(f * (strained + search + 1 + SPLINE_SUPPORT + margin) + rounding)
    # the engine's subvolume and search at every level, as wide as the halo and no wider
    assert reach_g == max(need_g)
    assert reach_f == max(need_f)
