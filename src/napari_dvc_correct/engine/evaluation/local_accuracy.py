"""Where a displacement field is wrong: the local residual and the local accuracy map.

The accuracy index of the paper (eq. 2, :mod:`.accuracy`) is one number for a whole volume: a
field can ruin a region and still score well, all the more if the ruined region's residual
becomes undefined (sent outside the scan) and drops out of the mean. Here the residual is averaged
over each node's subvolume region and turned into eq. 2 node by node, and the global index is
taken over the map with undefined regions counted as failed. :func:`.accuracy.evaluate_iter`
gives every field both.
"""

from __future__ import annotations

import numpy as np

from ..fields.field import DisplacementField


# --- local residual and local accuracy map -------------------------------------------------------
def local_mean_residual(residual: np.ndarray, field: DisplacementField, half: int) -> np.ndarray:
    """Mean residual over each node's subvolume region, per node (the local ``mean(r)``).

    Parameters
    ----------
    residual : ndarray, shape (nz, ny, nx), float
        Gray residual volume in the reference frame, ``|F(X + u(X)) - G(X)|`` (NaN where
        undefined), as from :func:`~.warp.gray_residual` or a pull-back.
    field : DisplacementField
        Gives the node positions (reference voxels, rounded to whole voxels).
    half : int
        Half-size ``M`` of the region: the ``(2M + 1)^3`` box centred on the node (the DVC's
        subvolume; clipped at the volume's borders).

    Returns
    -------
    ndarray, shape field.shape, float64
        Mean of the finite residual voxels of each node's box, gray levels; NaN where the box
        holds none.

    Notes
    -----
    Computed slab by slab from integral images in float64 (:func:`.binning.node_box_sums`, the
    code tiled evaluation runs block by block); :class:`NodeBoxMeans` gives the same numbers from
    slabs made one at a time.
    """
    from ..slabs import iter_slabs

    shape = np.shape(residual)
    means = NodeBoxMeans(field, shape, (half,))
    for zs in iter_slabs(shape):
        means.add(zs, residual[zs])
    return means.means()[0]


class NodeBoxMeans:
    """:func:`local_mean_residual` of a volume that is never held whole: its slabs along z are
    added one at a time, in the order of :func:`..slabs.iter_slabs` ``(shape)`` (the sums are
    float64 and added slab by slab, so these slabs give the same numbers to the bit), for one or
    several half-sizes at once.

    Parameters
    ----------
    field : DisplacementField
        Gives the node positions.
    shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the volume.
    halves : sequence of int
        Half-sizes of the nodes' boxes.
    """

    def __init__(self, field: DisplacementField, shape, halves) -> None:
        from .binning import node_voxels

        self.shape = tuple(int(n) for n in shape)
        self.centers = node_voxels(field, self.shape)
        self.halves = tuple(int(h) for h in halves)
        self.sums = [np.zeros(field.shape) for _ in self.halves]
        self.counts = [np.zeros(field.shape, np.int64) for _ in self.halves]

    def add(self, zs: slice, slab: np.ndarray) -> None:
        """Add the planes ``zs`` of the volume (``slab``: shape ``(len, ny, nx)``, any float; NaN
        where undefined)."""
        from .binning import node_box_sums

        box = (zs, slice(0, self.shape[1]), slice(0, self.shape[2]))
        slab = np.asarray(slab, np.float32)
        for half, sums, counts in zip(self.halves, self.sums, self.counts, strict=True):
            node_box_sums(slab, box, self.centers, half).add_to(sums, counts)

    def means(self) -> list[np.ndarray]:
        """Per half-size, each node's mean (float64, the grid's shape; NaN where its box holds
        no finite voxel)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return [
                np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
                for sums, counts in zip(self.sums, self.counts, strict=True)
            ]


def local_accuracy_map(local_residual: np.ndarray, background, contrast: float) -> np.ndarray:
    """Local accuracy index, eq. 2 node by node: ``p_i = 1 - (R_i - r0) / |g1 - g2|``.

    ``R_i`` is the mean residual over node ``i``'s subvolume region
    (:func:`local_mean_residual`), ``r0`` the volume's background residual (eq. 1) and
    ``|g1 - g2|`` the phase contrast. ``p_i`` is near 1 where the field explains the images down
    to the imaging noise and falls where the region's texture is misplaced; NaN where the region
    has no defined residual (the field sends it outside the scan, or it could not be inverted),
    which :func:`evaluate_iter` counts as a failed region.
    """
    r0 = float(getattr(background, "mean", background))
    if not contrast > 0:
        raise ValueError(f"the phase contrast must be > 0, got {contrast}")
    return 1.0 - (np.asarray(local_residual, dtype=np.float64) - r0) / float(contrast)


def region_half(field: DisplacementField) -> int:
    """Half-size of a node's region: the field's subvolume half, else its largest step."""
    subvolume = (field.params or {}).get("subvolume")
    if subvolume:
        return int(subvolume) // 2
    return int(np.ceil(max(field.step)))


def honest_accuracy(local_accuracy: np.ndarray) -> float:
    """Global accuracy index from the local map: the mean over every node, failed regions at 0.

    A node counts 0 where its region's residual is undefined (NaN: the field sends the region
    outside the scan or cannot be inverted there); elsewhere its local index counts, clipped to
    [0, 1], so a region below the average noise does not make up for a wrong one. Unlike eq. 2 on
    the voxels where the residual happens to be defined, this cannot rise when a field ruins a
    region so badly that its residual becomes undefined.
    """
    values = np.clip(np.asarray(local_accuracy, dtype=np.float64), 0.0, 1.0)
    values = np.where(np.isfinite(values), values, 0.0)
    return float(np.mean(values)) if values.size else float("nan")
