"""Where the points of interest go: a region (box or cylinder), a grid origin, or a list.

:func:`.field.grid_for_volume` places a grid over the whole volume, centred. Here the user chooses:

* :class:`Box` — an axis-aligned region, half-open voxel ranges ``z0:z1, y0:y1, x0:x1`` (like
  numpy slices: the node positions ``p`` satisfy ``z0 <= p_z < z1``...);
* :class:`Cylinder` — a cylinder with its axis along z (the usual CT rotation axis): centre
  ``(yc, xc)``, radius, and a z range; the grid covers its bounding box and the nodes outside the
  cylinder are marked ``NOT_COMPUTED`` (:func:`restrict_to_region`);
* an ``origin`` — the position of the first node, whole voxels (the grid then runs from there in
  steps of ``step`` until the region or the volume ends);
* explicit points — see :mod:`.correlate_points`.

Every node keeps its whole subvolume inside the volume, as in :func:`.field.grid_for_volume`.
Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fields.field import BORDER_MARGIN, DisplacementField, Provenance, Status


@dataclass(frozen=True)
class Box:
    """Axis-aligned region: node positions ``lo <= p < hi`` along each axis (voxels, z, y, x)."""

    lo: tuple
    hi: tuple

    def __post_init__(self) -> None:
        lo = tuple(float(v) for v in self.lo)
        hi = tuple(float(v) for v in self.hi)
        if len(lo) != 3 or len(hi) != 3:
            raise ValueError("a box needs 3 lower and 3 upper bounds (z, y, x)")
        if any(h <= low for low, h in zip(lo, hi)):
            raise ValueError(f"box bounds must have lo < hi on every axis, got {lo} and {hi}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    def bounds(self, volume_shape) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.lo), np.array(self.hi)

    def contains(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return np.all((points >= np.array(self.lo)) & (points < np.array(self.hi)), axis=1)


@dataclass(frozen=True)
class Cylinder:
    """Cylinder with its axis along z: ``(y - yc)² + (x - xc)² <= radius²`` and ``z0 <= z < z1``.

    ``z_range`` None means the whole height of the volume.
    """

    center: tuple
    radius: float
    z_range: tuple | None = None

    def __post_init__(self) -> None:
        center = tuple(float(v) for v in self.center)
        if len(center) != 2:
            raise ValueError("a cylinder's centre is (y, x)")
        if not float(self.radius) > 0:
            raise ValueError(f"cylinder radius must be > 0, got {self.radius}")
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "radius", float(self.radius))
        if self.z_range is not None:
            z0, z1 = (float(v) for v in self.z_range)
            if z1 <= z0:
                raise ValueError(f"cylinder z range must have z0 < z1, got {self.z_range}")
            object.__setattr__(self, "z_range", (z0, z1))

    def _z(self, volume_shape=None) -> tuple[float, float]:
        if self.z_range is not None:
            return self.z_range
        if volume_shape is None:
            return (-np.inf, np.inf)
        return (0.0, float(volume_shape[0]))

    def bounds(self, volume_shape) -> tuple[np.ndarray, np.ndarray]:
        z0, z1 = self._z(volume_shape)
        yc, xc = self.center
        r = self.radius
        return np.array([z0, yc - r, xc - r]), np.array([z1, yc + r + 1e-9, xc + r + 1e-9])

    def contains(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        z0, z1 = self._z()
        radial = (points[:, 1] - self.center[0]) ** 2 + (points[:, 2] - self.center[1]) ** 2
        return (radial <= self.radius**2 + 1e-9) & (points[:, 0] >= z0) & (points[:, 0] < z1)


Region = Box | Cylinder


def grid_for_region(
    volume_shape, subvolume: int, step, region: Region | None = None, origin=None
) -> tuple[tuple, tuple, tuple]:
    """POI grid ``(origin, step, shape)`` inside a region, every subvolume inside the volume.

    Parameters
    ----------
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the reference volume.
    subvolume : int
        Odd subvolume edge ``2M + 1``, voxels.
    step : int or 3 ints
        Node spacing, voxels.
    region : Box or Cylinder, optional
        Where the nodes may be (default: the whole volume). A cylinder gives its bounding box
        here; use :func:`restrict_to_region` on the result to drop the corners.
    origin : 3 ints, optional
        Position ``(z, y, x)`` of the first node, whole voxels. Default: the grid is centred in
        the room the region leaves (as :func:`.field.grid_for_volume` does for the whole volume).

    Returns
    -------
    origin, step, shape : tuples of 3

    Raises
    ------
    ValueError
        When no node fits (the region is outside the volume, or smaller than the border a
        subvolume needs), or the origin is not whole voxels or lies outside the room.
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    steps = tuple(int(s) for s in np.broadcast_to(np.asarray(step), (3,)))
    if min(steps) < 1:
        raise ValueError(f"step must be >= 1 voxel, got {step}")
    half = int(subvolume) // 2
    if origin is not None:
        origin = np.broadcast_to(np.asarray(origin, dtype=np.float64), (3,))
        if np.max(np.abs(origin - np.rint(origin))) > 1e-6:
            raise ValueError(f"origin must be whole voxels, got {tuple(origin)}")
        origin = np.rint(origin).astype(int)
    if region is None:
        lo, hi = np.zeros(3), np.array(volume_shape, dtype=np.float64)
    else:
        lo, hi = region.bounds(volume_shape)
    out_origin, out_shape = [], []
    for a, (n, s) in enumerate(zip(volume_shape, steps)):
        # room for node positions: the subvolume inside the volume (with the border margin when
        # the volume allows it), and the node inside the region
        margin = BORDER_MARGIN if n - 1 - 2 * half >= 2 * BORDER_MARGIN else 0
        first = max(half + margin, int(np.ceil(lo[a] - 1e-9)))
        last = min(n - 1 - half - margin, int(np.ceil(hi[a] - 1e-9)) - 1)
        if last < first:
            raise ValueError(
                f"no node fits along axis {'zyx'[a]}: the region spans [{lo[a]:g}, {hi[a]:g}) and "
                f"a subvolume of {subvolume} keeps nodes in [{half + margin}, "
                f"{n - 1 - half - margin}] of a volume of {n} voxels"
            )
        if origin is None:
            count = (last - first) // s + 1
            start = first + ((last - first) - (count - 1) * s) // 2
        else:
            start = int(origin[a])
            if not first <= start <= last:
                raise ValueError(
                    f"origin {tuple(int(o) for o in origin)} is outside the room for nodes along "
                    f"axis {'zyx'[a]} ([{first}, {last}])"
                )
            count = (last - start) // s + 1
        out_origin.append(float(start))
        out_shape.append(int(count))
    return tuple(out_origin), tuple(float(s) for s in steps), tuple(out_shape)


def restrict_to_region(field: DisplacementField, region: Region) -> DisplacementField:
    """The field with the nodes outside ``region`` marked ``NOT_COMPUTED`` (NaN displacement)."""
    outside = ~region.contains(field.points).reshape(field.shape)
    if not outside.any():
        return field
    out = field.copy()
    out.u[outside] = np.nan
    if out.gradient is not None:
        out.gradient[outside] = np.nan
    out.zncc[outside] = np.nan
    out.status[outside] = int(Status.NOT_COMPUTED)
    out.provenance[outside] = int(Provenance.NOT_COMPUTED)
    out.iterations[outside] = 0
    out.metadata["region"] = describe_region(region)
    return out


def describe_region(region: Region | None) -> dict | None:
    """JSON-serialisable description of a region (for metadata)."""
    if region is None:
        return None
    if isinstance(region, Box):
        return {"kind": "box", "lo": list(region.lo), "hi": list(region.hi)}
    return {
        "kind": "cylinder",
        "center_yx": list(region.center),
        "radius": region.radius,
        "z_range": None if region.z_range is None else list(region.z_range),
    }
