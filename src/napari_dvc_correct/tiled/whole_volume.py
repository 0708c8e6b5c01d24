"""The whole-volume pass of tiled correlation: one read of both volumes, block by block.

Each block (a Dask task) is binned exactly as :func:`..engine.correlation.initial_guess.global_shift` bins the
whole volumes, for the rigid shift, and gives the gray moments of the reference (inside the mask)
binned by every pyramid factor, for the low-texture test; the pass also checks that every value is
finite. :func:`combine` assembles the blocks' shares into a :class:`WholeVolume`.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from ..engine.correlation.initial_guess import bin_volume, global_shift
from ..engine.progress import Progress
from ..io.lazy import iter_blocks
from . import scheduling
from .memory import SHIFT_BLOCK_VOXELS


def _shift_factor(shape) -> int:
    """Binning factor of :func:`.initial_guess.global_shift` (largest binned edge ≤ 96)."""
    return max(1, int(np.ceil(max(shape) / 96)))


@dataclass
class _Moments:
    """Count, mean and sum of squared deviations of gray values; ``+`` combines two (Chan et al.)."""

    count: float = 0.0
    mean: float = 0.0
    m2: float = 0.0

    @classmethod
    def of(cls, values: np.ndarray) -> _Moments:
        values = np.asarray(values, np.float64).reshape(-1)
        if values.size == 0:
            return cls()
        mean = float(values.mean())
        return cls(float(values.size), mean, float(np.sum((values - mean) ** 2)))

    def __add__(self, other: _Moments) -> _Moments:
        count = self.count + other.count
        if count == 0:
            return _Moments()
        delta = other.mean - self.mean
        mean = self.mean + delta * other.count / count
        m2 = self.m2 + other.m2 + delta * delta * self.count * other.count / count
        return _Moments(count, mean, m2)

    @property
    def std(self) -> float:
        return math.sqrt(self.m2 / self.count) if self.count else float("nan")


def _read_checked(volume, region, name):
    block = volume.read_region(region)
    if not np.all(np.isfinite(block)):
        z, y = region[0], region[1]
        raise ValueError(
            f"the {name} volume contains NaN or infinite values (in z {z.start}:{z.stop}, "
            f"y {y.start}:{y.stop})"
        )
    return block


def _whole_blocks(block, z, y, factor, shape):
    """The part of ``block`` (at rows ``z``, ``y``) that ``bin_volume(whole, factor)`` keeps."""
    keep_z = min(z.stop, (shape[0] // factor) * factor) - z.start
    keep_y = min(y.stop, (shape[1] // factor) * factor) - y.start
    if keep_z < factor or keep_y < factor:
        return None
    return block[:keep_z, :keep_y]


def _volume_block(reference, deformed, mask, z, y, shift_factor, levels, shape):
    """One block's share of the whole-volume quantities: binned copies for the rigid shift, and
    the gray moments of the reference (inside the mask) binned by each pyramid factor."""
    region = (z, y, slice(None))
    g = _read_checked(reference, region, "reference")
    f = _read_checked(deformed, region, "deformed")
    m = None if mask is None else mask.read_region(region) != 0
    out = {"z": z.start // shift_factor, "y": y.start // shift_factor, "moments": {}}
    parts = [_whole_blocks(v, z, y, shift_factor, shape) for v in (g, f)]
    out["binned"] = None if parts[0] is None else [bin_volume(v, shift_factor) for v in parts]
    for lev in range(levels + 1):
        factor = 2**lev
        part = _whole_blocks(g, z, y, factor, shape)
        if part is None:
            out["moments"][factor] = _Moments()
            continue
        binned = bin_volume(part, factor)
        if m is not None:
            inside = _whole_blocks(m, z, y, factor, shape)
            if factor > 1:
                inside = bin_volume(inside.astype(np.float32), factor) >= 0.5
            binned = binned[inside]
        out["moments"][factor] = _Moments.of(binned)
    out["mask_count"] = 0 if m is None else int(m.sum())
    return out


def volume_tasks(reference, deformed, mask, levels):
    import dask

    shape = tuple(reference.shape)
    factor = _shift_factor(shape)
    task = dask.delayed(_volume_block, pure=False)
    volumes = [None if v is None else dask.delayed(v) for v in (reference, deformed, mask)]
    align = math.lcm(factor, 2**levels)
    blocks = iter_blocks(shape, SHIFT_BLOCK_VOXELS, align=align)
    return [task(*volumes, z, y, factor, levels, shape) for z, y in blocks], factor


@dataclass
class WholeVolume:
    """What the batches need to know about the whole volumes."""

    shift: np.ndarray  # rigid shift (z, y, x) voxels
    texture_std: dict  # binning factor -> gray std of the (masked) reference
    mask_count: int


def combine(results, shape, factor, levels) -> WholeVolume:
    binned_shape = tuple(n // factor for n in shape)
    g = np.zeros(binned_shape, np.float32)
    f = np.zeros(binned_shape, np.float32)
    moments = {2**lev: _Moments() for lev in range(levels + 1)}
    mask_count = 0
    for result in results:
        if result["binned"] is not None:
            block_g, block_f = result["binned"]
            z0, y0 = result["z"], result["y"]
            dz, dy = block_g.shape[:2]
            g[z0 : z0 + dz, y0 : y0 + dy] = block_g
            f[z0 : z0 + dz, y0 : y0 + dy] = block_f
        for key, value in result["moments"].items():
            moments[key] = moments[key] + value
        mask_count += result["mask_count"]
    # the binned volumes are at most 96 voxels per edge: global_shift bins them no further
    shift = (global_shift(g, f) * factor).astype(np.int64)
    return WholeVolume(shift, {k: v.std for k, v in moments.items()}, mask_count)


def whole_volume_iter(
    reference, deformed, mask, levels: int, run
) -> Generator[Progress, None, WholeVolume]:
    """The whole-volume pass: every block of the lazy volumes read once (Dask tasks), combined.

    ``levels``: the pyramid levels whose binned gray moments the low-texture test needs (0 for a
    run from an initial field); ``run``: ``(scheduler, workers, client)`` for
    :func:`.scheduling.running`. Yields one progress report per block.
    """
    scheduler, workers, client = run
    tasks, factor = volume_tasks(reference, deformed, mask, levels)
    results = []
    with scheduling.running(tasks, scheduler, workers, client) as finished:
        for done, (_, result) in enumerate(finished, start=1):
            results.append(result)
            yield Progress("whole volume", done, len(tasks), f"read block {done} of {len(tasks)}")
    return combine(results, tuple(int(n) for n in reference.shape), factor, levels)
