"""The rule of the image pyramid, in one place: each level's subvolume half-size and search radius,
and the memory of the coarsest level's search window. The engine's levels and the tiled halo
read it; a light module (no kernels), so the checks before a run can use it."""

from __future__ import annotations

import math
from typing import NamedTuple

from .initial_guess import pyramid_levels
from .params import CorrelationParams


class LevelReach(NamedTuple):
    """What a subvolume spans at one pyramid level, in that level's (binned) voxels.

    Attributes
    ----------
    factor : int
        Binning factor ``2**lev``.
    half : int
        Subvolume half-size ``M`` at the level.
    search_radius : int
        Radius of the integer (FFT) search around the shift carried to the level.
    """

    factor: int
    half: int
    search_radius: int


def level_reach(params: CorrelationParams, lev: int) -> LevelReach:
    """Subvolume half-size and search radius of pyramid level ``lev`` for ``params``.

    Level 0 keeps the run's half-size ``M`` and search radius ``R``. A coarse level of factor
    ``f = 2**lev`` uses ``max(4, M // f)`` (at least a 9-voxel subvolume) and
    ``ceil(R / f) + 1`` (one binned voxel more for the rounding of the carried shift).

    Raises
    ------
    ValueError
        For a negative level.
    """
    lev = int(lev)
    if lev < 0:
        raise ValueError(f"a pyramid level must be >= 0, got {lev}")
    radius = params.effective_search_radius
    if lev == 0:
        return LevelReach(1, params.half, radius)
    factor = 2**lev
    return LevelReach(factor, max(4, params.half // factor), math.ceil(radius / factor) + 1)


def search_window_bytes(params: CorrelationParams, volume_shape) -> int:
    """Peak memory of the largest per-POI search window of the FFT search, bytes.

    The window is searched at the coarsest pyramid level (:func:`.initial_guess.pyramid_levels`),
    whose subvolume and search radius are :func:`level_reach`'s: edge ``2 M_L + 1 + 2 R_L``
    binned voxels, about 64 bytes per voxel (the window, its spectrum, the ZNCC and the box sums
    in float64); at least one POI is searched at a time.
    """
    levels = pyramid_levels(params.effective_search_radius, params.subvolume, volume_shape)
    reach = level_reach(params, levels)
    span = 2 * reach.half + 1 + 2 * reach.search_radius
    return 64 * span**3
