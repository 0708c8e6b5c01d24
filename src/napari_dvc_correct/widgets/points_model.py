"""Points of interest from a napari Points layer, without Qt: world to voxel, and the checks.

The Correlate panel's choice *POIs: the points of a Points layer* (run by
:func:`.correlate_model.run_points_job`).
"""

from __future__ import annotations

import numpy as np


def job_points(points_layer, reference_layer, strategy: str, shape, params) -> np.ndarray:
    """The points of interest of a run from ``points_layer``, in reference voxels (checked).

    Raises ValueError for a series, without a Points layer, or when a point's subvolume does
    not fit (:func:`check_points`).
    """
    if strategy != "pair":
        raise ValueError(
            "points of interest from a Points layer work on a pair: choose 'Pair' as the "
            "input, or the regular grid for a series"
        )
    if points_layer is None:
        raise ValueError(
            "choose the Points layer of the points of interest (add one with the "
            "'New points layer' button of the layer list and click on the scan)"
        )
    points = points_in_voxels(points_layer, reference_layer)
    check_points(points, shape, params.subvolume, points_layer.name)
    return points


def points_in_voxels(points_layer, image_layer) -> np.ndarray:
    """The points of a napari Points layer as voxel indices ``(z, y, x)`` of an Image layer.

    A Points layer stores its ``data`` in its own data coordinates; the world position of a
    point is ``data * scale + translate`` of the Points layer (identity for a layer added with
    ``viewer.add_points`` on top of the scans: its data are then world coordinates), and the
    voxel index in the scan is ``(world - translate) / scale`` of the Image layer. Only the last
    three axes count (a point on a 4-D series keeps its z, y, x). Rotations, shears and affine
    transforms of either layer are not taken into account.

    Returns
    -------
    ndarray (N, 3), float64
        Fractional voxel indices (voxel ``i`` is centred at ``i``), in the layer's order.
    """
    data = np.asarray(points_layer.data, dtype=np.float64)
    if data.ndim != 2 or data.shape[1] < 3:
        raise ValueError(
            f"the Points layer '{points_layer.name}' has {data.shape[-1] if data.ndim == 2 else 0}"
            "-D points: points of interest need (z, y, x); add the Points layer while the 3-D "
            "scans are open (3-D points)"
        )
    if len(data) == 0:
        raise ValueError(f"the Points layer '{points_layer.name}' holds no point: add some first")
    p_scale = np.asarray(points_layer.scale, dtype=np.float64)[-3:]
    p_translate = np.asarray(points_layer.translate, dtype=np.float64)[-3:]
    world = data[:, -3:] * p_scale + p_translate
    scale = np.asarray(image_layer.scale, dtype=np.float64)[-3:]
    translate = np.asarray(image_layer.translate, dtype=np.float64)[-3:]
    return (world - translate) / scale


def check_points(points: np.ndarray, volume_shape, subvolume: int, name: str = "points") -> None:
    """Refuse points whose subvolume would not fit in the volume, saying which and by how much.

    A point is matched at its nearest voxel ``c = rint(p)``; its subvolume of ``subvolume``
    voxels fits when ``M <= c <= n - 1 - M`` on every axis (``M = subvolume // 2``), as in
    :func:`..engine.correlation.correlate_points.correlate_points`.
    """
    points = np.asarray(points, dtype=np.float64)
    if not np.all(np.isfinite(points)):
        raise ValueError(f"the points of '{name}' have non-finite coordinates")
    half = int(subvolume) // 2
    shape = np.asarray(volume_shape, dtype=np.float64)
    centers = np.rint(points)
    outside = np.any((centers < 0) | (centers > shape - 1), axis=1)
    near = np.any((centers < half) | (centers > shape - 1 - half), axis=1) & ~outside
    if not (outside.any() or near.any()):
        return
    parts = []
    if outside.any():
        parts.append(f"{int(outside.sum())} outside the volume {tuple(int(n) for n in shape)}")
    if near.any():
        parts.append(
            f"{int(near.sum())} closer than {half} voxels to its border (half the subvolume "
            f"of {subvolume})"
        )
    bad = np.flatnonzero(outside | near)[:3]
    where = ", ".join(
        f"#{i} at (z, y, x) = ({points[i, 0]:.1f}, {points[i, 1]:.1f}, {points[i, 2]:.1f})"
        for i in bad
    )
    low, high = half, (shape - 1 - half).astype(int)
    raise ValueError(
        f"{len(points)} points in '{name}': " + " and ".join(parts) + f" (e.g. {where}); "
        f"keep them within z {low}–{high[0]}, y {low}–{high[1]}, x {low}–{high[2]} voxels, "
        "or choose a smaller subvolume"
    )
