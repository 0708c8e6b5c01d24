"""Regions of interest as CT users draw them, without Qt: boolean masks ``(z, y, x)`` of a volume.

A CT specimen is usually a cylinder or a box standing along z, or "the material" (gray values
above a threshold); a shape drawn on one slice means "this outline, through a range of slices".
Every builder returns a boolean mask of the volume's shape; :func:`kept_pois` says how many POIs
of a grid the mask keeps (the engine's rule: a POI is measured when at least
``min_mask_fraction`` of its subvolume lies inside), so the panel can say so before a run and
refuse a mask that keeps none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..engine.correlation.params import CorrelationParams
from ..engine.correlation.shape_function import n_monomials
from ..engine.fields.field import grid_for_volume
from ..io.lazy import VolumeBase, normalize_slices

#: Region kinds offered by the panels: key -> label.
KINDS = {
    "all": "whole volume",
    "cylinder": "cylinder along z",
    "box": "box",
    "threshold": "material: gray above a threshold (holes filled)",
    "layer": "Labels/Shapes layer (extruded over the z range)",
}


def _z_slice(shape, z_range, axis: str = "z") -> slice:
    nz = int(shape[0])
    low, high = (0, nz) if z_range is None else (int(z_range[0]), int(z_range[1]))
    low, high = max(0, low), min(nz, high)
    if high <= low:
        if axis == "z":
            raise ValueError(f"the z range {z_range} selects no slice of a volume of {nz} slices")
        raise ValueError(f"the {axis} range {z_range} selects no voxel of the {nz} along {axis}")
    return slice(low, high)


class Region(VolumeBase):
    """A region of interest as a lazy boolean mask ``(z, y, x)``, computed block by block.

    Follows :class:`..io.lazy.LazyVolume` (``shape``, ``dtype``, ``read_region``), so an
    out-of-core run reads it batch by batch like the scans, and the mask of a
    2000 × 2000 × 3000 scan is never held whole; ``numpy.asarray(region)`` gives the whole mask
    for an in-memory run. The region lies within the slices ``z_range`` (``[z0, z1)``, voxels).
    """

    dtype = np.dtype(bool)

    def __init__(self, shape, z_range=None) -> None:
        self.shape = tuple(int(n) for n in shape)
        if len(self.shape) != 3:
            raise ValueError(f"a region needs a 3-D volume shape (z, y, x), got {self.shape}")
        self.z = _z_slice(self.shape, z_range)
        self._any = None

    def read_region(self, slices) -> np.ndarray:
        """The mask over ``slices`` (z, y, x), a bool array."""
        zs, ys, xs = normalize_slices(slices, self.shape)
        out = np.zeros((zs.stop - zs.start, ys.stop - ys.start, xs.stop - xs.start), bool)
        low, high = max(zs.start, self.z.start), min(zs.stop, self.z.stop)
        if high > low:
            out[low - zs.start : high - zs.start] = self._slab(slice(low, high), ys, xs)
        return out

    def _slab(self, zs: slice, ys: slice, xs: slice) -> np.ndarray:  # pragma: no cover
        """The mask over slices ``zs`` (inside the z range), rows ``ys``, columns ``xs``."""
        raise NotImplementedError

    def any(self) -> bool:
        """Whether the region selects a voxel (computed once, slab by slab)."""
        if self._any is None:
            self._any = self._compute_any()
        return self._any

    def known_empty(self) -> bool | None:
        """Whether the region is empty, if known without reading a volume (else None)."""
        return None if self._any is None else not self._any

    def _compute_any(self) -> bool:
        every_row, every_column = slice(0, self.shape[1]), slice(0, self.shape[2])
        return any(self._slab(zs, every_row, every_column).any() for zs in _slabs(self))


class PrismRegion(Region):
    """A region standing along z: one ``(ny, nx)`` cross-section through ``z_range``.

    Cylinders, boxes and outlines drawn on one slice are prisms; their POI counts need only
    the cross-section (:func:`kept_at`).
    """

    def __init__(self, shape, cross_section, z_range=None) -> None:
        super().__init__(shape, z_range)
        cross_section = np.asarray(cross_section) != 0
        if cross_section.shape != self.shape[1:]:
            raise ValueError(
                f"a {cross_section.shape} outline does not fit slices of {self.shape[1:]}"
            )
        self.cross_section = cross_section

    def _slab(self, zs, ys, xs):
        section = self.cross_section[ys, xs]
        return np.broadcast_to(section, (zs.stop - zs.start, *section.shape))

    def _compute_any(self) -> bool:
        return bool(self.cross_section.any())

    def known_empty(self) -> bool:
        return not self.any()  # one slice's cross-section: always cheap


class ThresholdRegion(Region):
    """Voxels of ``volume`` brighter than ``threshold`` within ``z_range``; with ``fill_holes``
    the closed pores of each z slice are filled.

    Filling slice by slice fills every pore closed in 3-D as well (a pore closed in 3-D is
    closed in each slice it crosses), so a block needs only its own slices, read whole in y
    and x. ``volume`` is any array or lazy array (Dask, Zarr) that slices like numpy.
    """

    def __init__(self, volume, threshold: float, fill_holes: bool = True, z_range=None) -> None:
        super().__init__(volume.shape, z_range)
        self.volume = volume
        self.threshold = float(threshold)
        self.fill_holes = bool(fill_holes)

    def _slab(self, zs, ys, xs):
        from scipy.ndimage import binary_fill_holes

        mask = _read(self.volume, (zs,)) > self.threshold
        if self.fill_holes:
            for k in range(mask.shape[0]):
                mask[k] = binary_fill_holes(mask[k])
        return mask[:, ys, xs]


class LabelsRegion(Region):
    """The non-zero voxels of a 3-D labels array (a Labels layer's data) within ``z_range``."""

    def __init__(self, labels, z_range=None) -> None:
        super().__init__(labels.shape, z_range)
        self.labels = labels

    def _slab(self, zs, ys, xs):
        return _read(self.labels, (zs, ys, xs)) != 0


def _read(array, index) -> np.ndarray:
    """``array[index]`` as a numpy array (Dask blocks computed)."""
    block = array[index]
    return np.asarray(block.compute() if hasattr(block, "compute") else block)


def _slabs(region: Region, z_range=None, voxels: int = 1 << 24):
    """z-slabs of about ``voxels`` voxels covering ``z_range`` (default the region's)."""
    nz, ny, nx = region.shape
    start, stop = (region.z.start, region.z.stop) if z_range is None else z_range
    depth = max(1, voxels // max(1, ny * nx))
    for z0 in range(start, stop, depth):
        yield slice(z0, min(stop, z0 + depth))


def whole(mask):
    """A region's mask as one boolean array for an in-memory run (None stays None); call it in
    the run's worker, not on the main thread: a threshold region reads the scan."""
    return None if mask is None else np.asarray(mask, bool)


def box_region(shape, z_range=None, y_range=None, x_range=None) -> PrismRegion:
    """Voxels with ``z_range[0] <= z < z_range[1]`` (same for y, x); a range None = all."""
    shape = tuple(int(n) for n in shape)
    section = np.zeros(shape[1:], bool)
    section[_z_slice((shape[1],), y_range, "y"), _z_slice((shape[2],), x_range, "x")] = True
    return PrismRegion(shape, section, z_range)


def cylinder_region(shape, centre_yx=None, radius=None, z_range=None) -> PrismRegion:
    """A cylinder along z: ``(y - cy)² + (x - cx)² <= r²`` over ``z_range`` (voxels).

    Defaults: centred in the slice, radius 45 % of the smaller of ny, nx, every slice.
    """
    nz, ny, nx = (int(n) for n in shape)
    cy, cx = ((ny - 1) / 2, (nx - 1) / 2) if centre_yx is None else map(float, centre_yx)
    r = 0.45 * min(ny, nx) if radius is None else float(radius)
    if not r > 0:
        raise ValueError(f"the cylinder radius must be > 0 voxels, got {r}")
    y, x = np.ogrid[:ny, :nx]
    return PrismRegion((nz, ny, nx), (y - cy) ** 2 + (x - cx) ** 2 <= r * r, z_range)


def box_mask(shape, z_range=None, y_range=None, x_range=None) -> np.ndarray:
    """:func:`box_region` as one boolean array."""
    return np.asarray(box_region(shape, z_range, y_range, x_range))


def cylinder_mask(shape, centre_yx=None, radius=None, z_range=None) -> np.ndarray:
    """:func:`cylinder_region` as one boolean array."""
    return np.asarray(cylinder_region(shape, centre_yx, radius, z_range))


def threshold_mask(volume: np.ndarray, threshold: float, fill_holes: bool = True) -> np.ndarray:
    """Voxels brighter than ``threshold``; with ``fill_holes`` closed pores inside are filled.

    Holes are filled slice by slice (z), which fills every pore closed in 3-D too, so a pore
    open to the top or bottom of the volume counts as inside the specimen as long as it is
    enclosed in its slice (:class:`ThresholdRegion` as one array).
    """
    return np.asarray(ThresholdRegion(np.asarray(volume), threshold, fill_holes))


def extrude(mask_2d: np.ndarray, shape, z_range=None) -> np.ndarray:
    """A 2-D ``(ny, nx)`` outline repeated through ``z_range`` of a volume of ``shape``."""
    return np.asarray(PrismRegion(shape, mask_2d, z_range))


def shapes_outline(shapes_data, shapes_types, slice_shape) -> np.ndarray:
    """Rasterise Shapes layer vertices (2-D or 3-D, data coordinates) on one ``(ny, nx)`` slice.

    3-D vertices keep their last two coordinates: a rectangle drawn on one slice of a 3-D Shapes
    layer is the outline of a prism through the slices.
    """
    from napari.layers import Shapes

    flat = [np.asarray(vertices, dtype=float)[:, -2:] for vertices in shapes_data]
    if not flat:
        raise ValueError("the Shapes layer holds no shape: draw the region first")
    layer = Shapes(flat, shape_type=list(shapes_types))
    return layer.to_masks(mask_shape=tuple(int(n) for n in slice_shape)).any(axis=0)


def layer_region(layer, shape, z_range=None, voxel_size=None, offset=None) -> Region:
    """Region from a Labels layer (non-zero; a 2-D one is extruded) or a Shapes layer (extruded).

    Shapes vertices are placed through the world: the layer's own ``scale``/``translate``, then
    the volume's ``voxel_size``/``offset`` (z, y, x), so a shape drawn over a scaled scan lands
    on the right voxels. A 3-D Labels layer is read block by block, never copied.
    """
    if hasattr(layer, "shape_type"):  # Shapes
        vs = np.ones(2) if voxel_size is None else np.asarray(voxel_size, float)[-2:]
        off = np.zeros(2) if offset is None else np.asarray(offset, float)[-2:]
        scale, translate = np.asarray(layer.scale)[-2:], np.asarray(layer.translate)[-2:]
        vertices = [
            ((np.asarray(v, float)[:, -2:] * scale + translate) - off) / vs for v in layer.data
        ]
        return PrismRegion(shape, shapes_outline(vertices, layer.shape_type, shape[1:]), z_range)
    data = layer.data
    if data.ndim == 2:
        return PrismRegion(shape, np.asarray(data), z_range)
    if tuple(data.shape) != tuple(shape):
        raise ValueError(
            f"the Labels layer '{layer.name}' has shape {tuple(data.shape)} but the volumes are "
            f"{tuple(shape)}"
        )
    return LabelsRegion(data, z_range)


def layer_mask(layer, shape, z_range=None, voxel_size=None, offset=None) -> np.ndarray:
    """:func:`layer_region` as one boolean array."""
    return np.asarray(layer_region(layer, shape, z_range, voxel_size, offset))


@dataclass(frozen=True)
class Kept:
    """How many POIs of a grid a mask keeps."""

    kept: int
    total: int

    def text(self) -> str:
        share = 100.0 * self.kept / self.total if self.total else 0.0
        return f"the region keeps {self.kept:,} of {self.total:,} POIs ({share:.0f} %)"


_last_table: list = [None, None]  # (mask, its summed-volume table): the last one asked for


def summed_volume(mask: np.ndarray) -> np.ndarray:
    """Summed-volume table of ``mask`` (``(nz+1, ny+1, nx+1)`` int64), kept for the last mask.

    The table costs three passes over the volume; the preview asks for it after every change of
    the step or the subvolume, so the last mask's table is kept (compared by identity: a mask is
    never changed in place here). A worker may compute it ahead (:meth:`.regions.RegionBox`).
    """
    cached_mask, cached_table = _last_table
    if cached_mask is mask:
        return cached_table
    table = np.zeros(tuple(n + 1 for n in mask.shape), np.int64)
    table[1:, 1:, 1:] = np.asarray(mask, bool).cumsum(0).cumsum(1).cumsum(2)
    _last_table[:] = [mask, table]
    return table


def _needed(params: CorrelationParams) -> float:
    """Mask voxels a subvolume needs for its POI to be measured (icgn.py's rule: the mask
    fraction, and one voxel more than the shape function's parameters)."""
    parameters = 3 * n_monomials(params.order)
    return max(params.min_mask_fraction * params.subvolume**3, parameters + 1)


def _box_sums_2d(table: np.ndarray, y0, y1, x0, x1) -> np.ndarray:
    """Sums over ``[y0, y1) × [x0, x1)`` from a 2-D summed-area table ``(ny+1, nx+1)``."""
    return table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]


def _summed_area(plane: np.ndarray) -> np.ndarray:
    table = np.zeros((plane.shape[0] + 1, plane.shape[1] + 1), np.int64)
    table[1:, 1:] = plane.cumsum(0, dtype=np.int64).cumsum(1)
    return table


def _prism_counts(region: PrismRegion, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mask voxels of ``region`` in the boxes ``[lo, hi)`` (N, 3): slices inside its z range
    times the cross-section's voxels in the (y, x) box."""
    table = _summed_area(region.cross_section)
    slices = _slices_inside(region, lo[:, 0], hi[:, 0])
    return slices * _box_sums_2d(table, lo[:, 1], hi[:, 1], lo[:, 2], hi[:, 2])


def _slices_inside(region: PrismRegion, z0, z1) -> np.ndarray:
    """Slices of ``[z0, z1)`` inside the region's z range (elementwise)."""
    return np.clip(np.minimum(z1, region.z.stop) - np.maximum(z0, region.z.start), 0, None)


def _sliding_counts(region: Region, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mask voxels of a lazy ``region`` in the boxes ``[lo, hi)`` (N, 3) of one z extent per
    row of POIs: a window of slices summed along z moves up the volume (each slice read at
    most twice, one ``(ny, nx)`` count held), and a 2-D summed-area table gives the boxes."""
    nz, ny, nx = region.shape
    counts = np.zeros(len(lo), np.int64)
    window = np.zeros((ny, nx), np.int32)
    low = high = 0

    def summed(z0, z1):
        total = np.zeros((ny, nx), np.int32)
        for zs in _slabs(region, z_range=(z0, z1)):
            total += region.read_region((zs, slice(0, ny), slice(0, nx))).sum(0, dtype=np.int32)
        return total

    for z0, z1 in sorted({(int(a), int(b)) for a, b in zip(lo[:, 0], hi[:, 0])}):
        if z0 >= high:  # a gap: start again
            window[:] = 0
            low = high = z0
        if z0 > low:
            window -= summed(low, z0)
        if z1 > high:
            window += summed(high, z1)
        low, high = z0, z1
        rows = (lo[:, 0] == z0) & (hi[:, 0] == z1)
        table = _summed_area(window)
        counts[rows] = _box_sums_2d(table, lo[rows, 1], hi[rows, 1], lo[rows, 2], hi[rows, 2])
    return counts


def counts_quickly(mask) -> bool:
    """Whether :func:`kept_at` is quick for ``mask`` (an array with its table, or a prism):
    False for a lazy threshold or labels region, whose count reads the whole volume."""
    return isinstance(mask, (np.ndarray, PrismRegion))


def emptiness(mask) -> bool | None:
    """True or False when it is known without reading a lazy volume, else None."""
    return mask.known_empty() if isinstance(mask, Region) else not mask.any()


def kept_at(mask, params: CorrelationParams, points: np.ndarray) -> np.ndarray:
    """For POI centres ``points`` (N, 3) voxels: is each one measured inside ``mask``?

    ``mask`` is a boolean array or a :class:`Region` (a lazy threshold or labels region is
    read slice by slice: see :func:`counts_quickly`).
    """
    centres = np.rint(np.asarray(points, float)).astype(int).reshape(-1, 3)
    shape = np.asarray(mask.shape)
    lo = np.clip(centres - params.half, 0, shape)
    hi = np.clip(centres + params.half + 1, 0, shape)
    if isinstance(mask, PrismRegion):
        inside = _prism_counts(mask, lo, hi)
    elif isinstance(mask, Region):
        inside = _sliding_counts(mask, lo, hi)
    else:
        table = summed_volume(mask)
        (z0, y0, x0), (z1, y1, x1) = lo.T, hi.T
        inside = (
            table[z1, y1, x1]
            - table[z0, y1, x1]
            - table[z1, y0, x1]
            - table[z1, y1, x0]
            + table[z0, y0, x1]
            + table[z0, y1, x0]
            + table[z1, y0, x0]
            - table[z0, y0, x0]
        )
    return inside >= _needed(params)


def kept_pois(mask, params: CorrelationParams) -> Kept:
    """POIs of the grid of ``params`` whose subvolume is at least ``min_mask_fraction`` inside.

    The engine's rule (icgn.py): a POI with fewer mask voxels in its subvolume is marked masked.
    Counted exactly: a summed-volume table of an array, the cross-section of a prism, slices
    summed along z for a lazy region.
    """
    mask = mask if isinstance(mask, Region) else np.asarray(mask, bool)
    origin, step, shape = grid_for_volume(mask.shape, params.subvolume, params.step)
    axes = [np.asarray(origin[a]) + step[a] * np.arange(shape[a]) for a in range(3)]
    if isinstance(mask, PrismRegion):  # separable: slices per grid plane × the (y, x) boxes
        centres = [np.rint(values).astype(np.int64) for values in axes]
        lo = [np.clip(c - params.half, 0, n) for c, n in zip(centres, mask.shape)]
        hi = [np.clip(c + params.half + 1, 0, n) for c, n in zip(centres, mask.shape)]
        y0, x0 = np.meshgrid(lo[1], lo[2], indexing="ij")
        y1, x1 = np.meshgrid(hi[1], hi[2], indexing="ij")
        section = _box_sums_2d(_summed_area(mask.cross_section), y0, y1, x0, x1)
        counts = np.multiply.outer(_slices_inside(mask, lo[0], hi[0]), section)
        return Kept(int(np.count_nonzero(counts >= _needed(params))), int(np.prod(shape)))
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return Kept(int(np.count_nonzero(kept_at(mask, params, points))), int(np.prod(shape)))


def check_kept(mask: np.ndarray, params: CorrelationParams) -> Kept:
    """:func:`kept_pois`, refusing a mask that keeps no POI (ValueError says what to change)."""
    kept = kept_pois(mask, params)
    if kept.kept == 0:
        raise ValueError(
            f"the region keeps none of the {kept.total:,} POIs (a POI needs "
            f"{100 * params.min_mask_fraction:.0f} % of its {params.subvolume}³ subvolume inside): "
            "enlarge the region, lower the subvolume, or check the z range"
        )
    return kept
