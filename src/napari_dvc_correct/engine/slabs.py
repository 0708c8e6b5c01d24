"""Slabs along z: the one way the engine walks a volume too large to process at once."""

from __future__ import annotations

from collections.abc import Iterator

#: Voxels per slab unless told otherwise (16 MB of float32).
SLAB_VOXELS = 1 << 22


def iter_slabs(shape, voxels: int = SLAB_VOXELS) -> Iterator[slice]:
    """Slices along z of a volume of ``shape`` ``(nz, ny, nx)`` holding at most about ``voxels``.

    Always at least one plane per slab; the slabs cover ``0 .. nz`` in order without overlap.
    """
    plane = max(1, int(shape[1]) * int(shape[2]))
    depth = max(1, int(voxels) // plane)
    for start in range(0, int(shape[0]), depth):
        yield slice(start, min(int(shape[0]), start + depth))
