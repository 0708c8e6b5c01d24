"""Integer-voxel initial guesses that survive large displacements.

Three tools, used by :mod:`correlate` from coarse to fine:

- :func:`global_shift`: the rigid translation of the whole specimen by phase correlation of
  binned volumes (catches shifts of tens of voxels without any parameter).
- :func:`fft_search`: per-POI ZNCC over every integer shift within a search radius, computed with
  FFTs, with a parabolic sub-voxel peak.
- :func:`pyramid_levels` / :func:`bin_volume`: a binned pyramid so that displacements larger than the
  subvolume are searched at a coarse level with a small radius.

Reliability-guided propagation (re-matching failed POIs from their best converged neighbours) lives
in :mod:`correlate`, next to the matcher it drives.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft


def bin_volume(volume: np.ndarray, factor: int = 2) -> np.ndarray:
    """Block mean of ``volume`` over ``factor³`` voxels (float32); the remainder is cropped.

    Coarse voxel ``i`` covers fine voxels ``factor·i … factor·i + factor − 1``, so its centre sits
    at fine position ``factor·i + (factor − 1)/2``.
    """
    if factor == 1:
        return np.asarray(volume, dtype=np.float32)
    shape = tuple(n // factor for n in volume.shape)
    if min(shape) < 1:
        raise ValueError(f"volume {volume.shape} is too small to bin by {factor}")
    cropped = volume[: shape[0] * factor, : shape[1] * factor, : shape[2] * factor]
    # one slab of ``factor`` planes at a time: the float32 copy of another dtype and the float64
    # sums numpy's mean makes are a slab's, not the volume's (same sums, same order)
    out = np.empty(shape, np.float32)
    for k in range(shape[0]):
        slab = np.asarray(cropped[k * factor : (k + 1) * factor], dtype=np.float32)
        blocks = slab.reshape(1, factor, shape[1], factor, shape[2], factor)
        out[k] = blocks.mean(axis=(1, 3, 5), dtype=np.float64)[0].astype(np.float32)
    return out


def pyramid_levels(search_radius: int, subvolume: int, volume_shape, max_coarse_radius: int = 4):
    """Number of binning levels ``L`` (factor ``2**L``) for the integer search.

    The coarsest level is the first whose radius ``ceil(R / 2**L)`` is at most
    ``max_coarse_radius``, as long as the binned subvolume keeps at least 9 voxels per edge and the
    binned volume at least 16.
    """
    levels = 0
    while int(np.ceil(search_radius / 2**levels)) > max_coarse_radius:
        next_sub = subvolume // 2 ** (levels + 1)
        next_volume = min(volume_shape) // 2 ** (levels + 1)
        if next_sub < 9 or next_volume < 16:
            break
        levels += 1
    return levels


def global_shift(reference: np.ndarray, deformed: np.ndarray, max_size: int = 96) -> np.ndarray:
    """Rigid translation ``t`` (z, y, x voxels, integers) with ``F(X + t) ≈ G(X)``.

    Phase correlation of Hann-windowed, binned copies of both volumes (binned so that the largest
    edge is at most ``max_size``). The estimate is accurate to about the binning factor; the per-POI
    search refines it.
    """
    factor = max(1, int(np.ceil(max(reference.shape) / max_size)))
    g = bin_volume(reference, factor).astype(np.float64)
    f = bin_volume(deformed, factor).astype(np.float64)
    window = np.ones(g.shape)
    for axis, n in enumerate(g.shape):
        shape = [1, 1, 1]
        shape[axis] = n
        window = window * np.hanning(n).reshape(shape)
    g = (g - g.mean()) * window
    f = (f - f.mean()) * window
    cross = np.conj(sfft.rfftn(g)) * sfft.rfftn(f)
    if not np.any(cross):  # a textureless volume: no shift to find (and no 0/0 warning)
        return np.zeros(3, np.int64)
    cross /= np.abs(cross) + 1e-12 * np.abs(cross).max()
    corr = sfft.irfftn(cross, s=g.shape)
    peak = np.array(np.unravel_index(np.argmax(corr), corr.shape))
    shape = np.array(g.shape)
    peak = np.where(peak > shape // 2, peak - shape, peak)
    return (peak * factor).astype(np.int64)


def _box_sums(volumes: np.ndarray, edge: int) -> np.ndarray:
    """Sums over every ``edge³`` window of a stack of cubes (B, S, S, S) -> (B, S−edge+1, ...)."""
    out = volumes
    for axis in (1, 2, 3):
        cumulative = np.cumsum(out, axis=axis)
        zero = np.zeros_like(np.take(cumulative, [0], axis=axis))
        cumulative = np.concatenate([zero, cumulative], axis=axis)
        n = cumulative.shape[axis]
        out = np.take(cumulative, np.arange(edge, n), axis=axis) - np.take(
            cumulative, np.arange(0, n - edge), axis=axis
        )
    return out


def fft_search(
    reference: np.ndarray,
    deformed: np.ndarray,
    centers: np.ndarray,
    half: int,
    guesses: np.ndarray,
    radius: int,
    batch_bytes: int = 64 * 2**20,
) -> tuple[np.ndarray, np.ndarray]:
    """Best integer shift (with parabolic sub-voxel peak) of each subvolume within ``radius``.

    The ZNCC of every shift is computed at once per POI: the numerator by FFT cross-correlation,
    the deformed windows' sums and sums of squares by cumulative sums. POIs are processed in
    batches of stacked FFTs. Where a POI's search window leaves the volume, the part beyond is
    filled with the mean gray value of its part inside (a local value, so a region of the volume
    holding the window gives the same answer as the whole volume).

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        Volumes ``G`` and ``F`` at one pyramid level.
    centers : ndarray, shape (N, 3), int
        Subvolume centres (z, y, x) in ``reference``; the subvolume must lie inside it.
    half : int
        Subvolume half-size ``M``.
    guesses : ndarray, shape (N, 3)
        Displacement around which to search (rounded to integers).
    radius : int
        Search over shifts ``guess + s`` with ``|s_k| <= radius``.
    batch_bytes : int
        Approximate memory of one batch of stacked FFTs (bounds the peak memory).

    Returns
    -------
    displacement : ndarray, shape (N, 3), float64
        Estimated displacement (voxels).
    peak : ndarray, shape (N,), float64
        ZNCC at the best integer shift (NaN for flat subvolumes).
    """
    edge = 2 * half + 1
    span = edge + 2 * radius
    n_shifts = 2 * radius + 1
    shape = np.array(deformed.shape)
    guesses = np.rint(guesses).astype(np.int64)
    out = np.zeros((len(centers), 3))
    peaks = np.full(len(centers), np.nan)
    fft_shape = (span, span, span)
    batch = max(1, int(batch_bytes // (8 * 8 * span**3)))
    for first in range(0, len(centers), batch):
        index = np.arange(first, min(first + batch, len(centers)))
        subs = np.empty((len(index), edge, edge, edge))
        regions = np.empty((len(index), span, span, span))
        for row, i in enumerate(index):
            z, y, x = centers[i]
            subs[row] = reference[
                z - half : z + half + 1, y - half : y + half + 1, x - half : x + half + 1
            ]
            low = centers[i] + guesses[i] - half - radius
            high = low + span
            if np.all(low >= 0) and np.all(high <= shape):
                regions[row] = deformed[low[0] : high[0], low[1] : high[1], low[2] : high[2]]
                continue
            # beyond the volume: the mean of the window's part inside it (a local value, so a
            # region of the volume (tiled batches) fills as the whole volume does)
            src_low = np.maximum(low, 0)
            src_high = np.minimum(high, shape)
            if np.all(src_high > src_low):
                inside = deformed[
                    src_low[0] : src_high[0], src_low[1] : src_high[1], src_low[2] : src_high[2]
                ]
                regions[row] = float(np.mean(inside, dtype=np.float64))
                regions[
                    row,
                    src_low[0] - low[0] : src_high[0] - low[0],
                    src_low[1] - low[1] : src_high[1] - low[1],
                    src_low[2] - low[2] : src_high[2] - low[2],
                ] = inside
            else:
                regions[row] = float(np.mean(subs[row]))
        subs -= subs.mean(axis=(1, 2, 3), keepdims=True)
        norm_sub = np.sqrt(np.sum(subs * subs, axis=(1, 2, 3)))
        spectrum = sfft.rfftn(regions, s=fft_shape, axes=(1, 2, 3), workers=-1)
        spectrum *= np.conj(sfft.rfftn(subs, s=fft_shape, axes=(1, 2, 3), workers=-1))
        numerator = sfft.irfftn(spectrum, s=fft_shape, axes=(1, 2, 3), workers=-1)
        numerator = numerator[:, :n_shifts, :n_shifts, :n_shifts]
        sums = _box_sums(regions, edge)
        sums2 = _box_sums(regions * regions, edge)
        variance = sums2 - sums * sums / edge**3
        floor = 1e-9 * np.maximum(1.0, np.max(sums2, axis=(1, 2, 3), keepdims=True))
        with np.errstate(invalid="ignore", divide="ignore"):
            ncc = numerator / (norm_sub[:, None, None, None] * np.sqrt(np.maximum(variance, floor)))
        ncc[norm_sub == 0] = -np.inf
        flat_best = np.argmax(ncc.reshape(len(index), -1), axis=1)
        best = np.stack(np.unravel_index(flat_best, ncc.shape[1:]), axis=1)
        rows = np.arange(len(index))
        peak = ncc[rows, best[:, 0], best[:, 1], best[:, 2]]
        sub_voxel = np.zeros((len(index), 3))
        for axis in range(3):
            inner = (best[:, axis] > 0) & (best[:, axis] < n_shifts - 1)
            before = best.copy()
            before[:, axis] = np.maximum(best[:, axis] - 1, 0)
            after = best.copy()
            after[:, axis] = np.minimum(best[:, axis] + 1, n_shifts - 1)
            a = ncc[rows, before[:, 0], before[:, 1], before[:, 2]]
            c = ncc[rows, after[:, 0], after[:, 1], after[:, 2]]
            with np.errstate(invalid="ignore", divide="ignore"):  # flat subvolumes: -inf
                curvature = a - 2 * peak + c
                offset = np.clip(0.5 * (a - c) / curvature, -0.5, 0.5)
            sub_voxel[:, axis] = np.where(inner & (curvature < 0), offset, 0.0)
        flat = norm_sub == 0
        out[index] = guesses[index] + best - radius + np.where(flat[:, None], 0.0, sub_voxel)
        out[index[flat]] = guesses[index[flat]]
        peaks[index] = np.where(flat, np.nan, peak)
    return out, peaks
