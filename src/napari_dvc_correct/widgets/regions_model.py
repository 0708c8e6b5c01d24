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

from ..engine.field import grid_for_volume
from ..engine.params import CorrelationParams

#: Region kinds offered by the panels: key -> label.
KINDS = {
    "all": "whole volume",
    "cylinder": "cylinder along z",
    "box": "box",
    "threshold": "material: gray above a threshold (holes filled)",
    "layer": "Labels/Shapes layer (extruded over the z range)",
}


def _z_slice(shape, z_range) -> slice:
    nz = int(shape[0])
    low, high = (0, nz) if z_range is None else (int(z_range[0]), int(z_range[1]))
    low, high = max(0, low), min(nz, high)
    if high <= low:
        raise ValueError(f"the z range {z_range} selects no slice of a volume of {nz} slices")
    return slice(low, high)


def box_mask(shape, z_range=None, y_range=None, x_range=None) -> np.ndarray:
    """Voxels with ``z_range[0] <= z < z_range[1]`` (same for y, x); a range None = all."""
    mask = np.zeros(tuple(int(n) for n in shape), bool)
    index = tuple(_z_slice((shape[a],), r) for a, r in enumerate((z_range, y_range, x_range)))
    mask[index] = True
    return mask


def cylinder_mask(shape, centre_yx=None, radius=None, z_range=None) -> np.ndarray:
    """A cylinder along z: ``(y - cy)² + (x - cx)² <= r²`` over ``z_range`` (voxels).

    Defaults: centred in the slice, radius 45 % of the smaller of ny, nx, every slice.
    """
    nz, ny, nx = (int(n) for n in shape)
    cy, cx = ((ny - 1) / 2, (nx - 1) / 2) if centre_yx is None else map(float, centre_yx)
    r = 0.45 * min(ny, nx) if radius is None else float(radius)
    if not r > 0:
        raise ValueError(f"the cylinder radius must be > 0 voxels, got {r}")
    y, x = np.ogrid[:ny, :nx]
    disc = (y - cy) ** 2 + (x - cx) ** 2 <= r * r
    mask = np.zeros((nz, ny, nx), bool)
    mask[_z_slice(shape, z_range)] = disc
    return mask


def threshold_mask(volume: np.ndarray, threshold: float, fill_holes: bool = True) -> np.ndarray:
    """Voxels brighter than ``threshold``; with ``fill_holes`` closed pores inside are filled.

    Holes are filled slice by slice (z) and in 3-D, so a pore open to the top or bottom of the
    volume counts as inside the specimen as long as it is enclosed in its slice.
    """
    from scipy.ndimage import binary_fill_holes

    mask = np.asarray(volume) > float(threshold)
    if fill_holes:
        mask = binary_fill_holes(mask)
        for z in range(mask.shape[0]):
            mask[z] = binary_fill_holes(mask[z])
    return mask


def extrude(mask_2d: np.ndarray, shape, z_range=None) -> np.ndarray:
    """A 2-D ``(ny, nx)`` outline repeated through ``z_range`` of a volume of ``shape``."""
    mask_2d = np.asarray(mask_2d) != 0
    if mask_2d.shape != tuple(shape[1:]):
        raise ValueError(f"a {mask_2d.shape} outline does not fit slices of {tuple(shape[1:])}")
    mask = np.zeros(tuple(int(n) for n in shape), bool)
    mask[_z_slice(shape, z_range)] = mask_2d
    return mask


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


def layer_mask(layer, shape, z_range=None, voxel_size=None, offset=None) -> np.ndarray:
    """Mask from a Labels layer (non-zero; a 2-D one is extruded) or a Shapes layer (extruded).

    Shapes vertices are placed through the world: the layer's own ``scale``/``translate``, then
    the volume's ``voxel_size``/``offset`` (z, y, x), so a shape drawn over a scaled scan lands
    on the right voxels.
    """
    if hasattr(layer, "shape_type"):  # Shapes
        vs = np.ones(2) if voxel_size is None else np.asarray(voxel_size, float)[-2:]
        off = np.zeros(2) if offset is None else np.asarray(offset, float)[-2:]
        scale, translate = np.asarray(layer.scale)[-2:], np.asarray(layer.translate)[-2:]
        vertices = [
            ((np.asarray(v, float)[:, -2:] * scale + translate) - off) / vs for v in layer.data
        ]
        outline = shapes_outline(vertices, layer.shape_type, shape[1:])
        return extrude(outline, shape, z_range)
    data = np.asarray(layer.data)
    if data.ndim == 2:
        return extrude(data, shape, z_range)
    if data.shape != tuple(shape):
        raise ValueError(
            f"the Labels layer '{layer.name}' has shape {data.shape} but the volumes are "
            f"{tuple(shape)}"
        )
    mask = data != 0
    if z_range is not None:
        mask &= box_mask(shape, z_range)
    return mask


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
    """Mask voxels a subvolume needs for its POI to be measured (icgn.py's rule)."""
    return max(params.min_mask_fraction * params.subvolume**3, 3 * 4 + 1)


def kept_at(mask: np.ndarray, params: CorrelationParams, points: np.ndarray) -> np.ndarray:
    """For POI centres ``points`` (N, 3) voxels: is each one measured inside ``mask``?"""
    table = summed_volume(mask)
    centres = np.rint(np.asarray(points, float)).astype(int)
    z0, y0, x0 = (centres - params.half).T
    z1, y1, x1 = (centres + params.half + 1).T
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


def kept_pois(mask: np.ndarray, params: CorrelationParams) -> Kept:
    """POIs of the grid of ``params`` whose subvolume is at least ``min_mask_fraction`` inside.

    The engine's rule (icgn.py): a POI with fewer mask voxels in its subvolume is marked masked.
    Counted exactly with a summed-volume table.
    """
    mask = np.asarray(mask, bool)
    origin, step, shape = grid_for_volume(mask.shape, params.subvolume, params.step)
    axes = [np.asarray(origin[a]) + step[a] * np.arange(shape[a]) for a in range(3)]
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
