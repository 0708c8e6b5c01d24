"""napari layer data tuples of a field at scattered points of interest (a Points layer result).

:func:`points_layers` turns a :class:`.engine.fields.scattered.ScatteredField` (what the Correlate panel
returns for the points of a Points layer) into a Points layer coloured by one quantity, with every
quantity as a feature, and the displacement arrows; :func:`color_points` switches the colour in
place (the View panel's quantity chooser). Placement as the scans: positions in reference voxels
``(z, y, x)`` with ``scale = voxel_size`` and ``translate = offset``. No Qt here.
"""

from __future__ import annotations

import numpy as np

from .layers import MARKER, LayerDataTuple, dense_placement, layer_name, plugin_metadata
from .quantities import (
    DEFAULT_QUANTITY,
    QUANTITIES,
    STATUS_COLORS,
    as_triple,
    point_quantities,
    quantity_style,
    unit_of,
)


def point_spacing(points: np.ndarray, default: float = 1.0) -> float:
    """Median distance from a point to its nearest neighbour (voxels); ``default`` for one."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return float(default)
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(points).query(points, k=2)
    spacing = float(np.median(distance[:, 1]))
    return spacing if spacing > 0 else float(default)


def points_result_layers(viewer) -> list:
    """The plugin's points-of-interest result layers (kind ``"points"``), in layer order."""
    return [x for x in viewer.layers if (plugin_metadata(x) or {}).get("kind") == "points"]


def points_in(layers) -> dict:
    """Fields at points of interest carried by ``layers``, by source name, in layer order (first
    layer of each wins): the :class:`.engine.fields.scattered.ScatteredField` of every points result
    (the companion of :func:`.layers.fields_in`, which holds the grid fields)."""
    found = {}
    for layer in layers:
        entry = plugin_metadata(layer) or {}
        if entry.get("kind") == "points" and entry.get("points_field") is not None:
            found.setdefault(entry["source"], entry["points_field"])
    return found


#: Napari colormaps of the quantity kinds (as :func:`quantity_style` for the grid layers).
_POINT_COLORMAPS = {
    "displacement": "coolwarm",
    "strain": "coolwarm",
    "magnitude": "viridis",
    "positive strain": "inferno",
    "zncc": "magma",
}


def points_style(values: dict, quantity: str) -> dict:
    """Napari Points keyword arguments that colour the points by ``quantity`` (a feature).

    Signed quantities get a diverging map centred on zero, the others the colormaps of the
    grid layers; the status gets its own colours (:data:`STATUS_COLORS`, converged white).
    """
    if quantity == "status":
        codes = values["status"].astype(int)
        colors = [STATUS_COLORS.get(int(c), "white") for c in codes]
        return {"face_color": ["white" if c == "transparent" else c for c in colors]}
    data = np.asarray(values[quantity], dtype=np.float64)
    style = quantity_style(quantity, data.astype(np.float32))
    low, high = style["contrast_limits"]
    return {
        "face_color": quantity,
        "face_colormap": _POINT_COLORMAPS[QUANTITIES[quantity][1]],
        "face_contrast_limits": (float(low), float(high)),
    }


def points_layers(
    points_field,
    source: str = "points",
    *,
    voxel_size=None,
    offset=None,
    quantity: str = DEFAULT_QUANTITY,
    exaggerate: bool = True,
) -> list[LayerDataTuple]:
    """A field at scattered points (:class:`.engine.fields.scattered.ScatteredField`) as two layers.

    * a Points layer at the points (voxel positions, placed with ``scale = voxel_size`` and
      ``translate = offset`` like the scans), coloured by ``quantity`` with every quantity of
      :func:`.quantities.point_quantities` as a feature (napari shows them under the cursor;
      :func:`color_points` switches the colour), points without a value drawn hollow with a
      red rim; the discs are at most 0.7 of the points' typical spacing across;
    * the displacement arrows from each point (voxels, same placement, so an arrow has its true
      length in world units unless ``exaggerate``: then, as for a grid, the longest spans the
      typical spacing of the points when the largest displacement is under half of it, and
      ``length`` says the factor).

    Both carry ``metadata["dvc_correct"]`` with kind ``"points"``/``"point vectors"``, the
    source and the field (``"points_field"``).
    """
    values = point_quantities(points_field)
    if quantity not in values:
        quantity = DEFAULT_QUANTITY
    valid = np.asarray(points_field.valid, dtype=bool)
    placement = dense_placement(voxel_size, offset)
    half = float(points_field.params.get("subvolume", 9)) / 2
    spacing = point_spacing(points_field.points, default=2 * half)
    size = max(1.5, min(half / 2, 0.7 * spacing))  # discs that do not hide their neighbours
    key = f"points ({source})"
    extra = {"quantity": quantity, "unit": _points_unit(points_field, quantity), "key": key}
    point_kwargs = {
        "name": layer_name(quantity, source),
        "features": values,
        "size": size,
        "border_width": 0.08,
        "border_width_is_relative": True,
        "border_color": ["#202020" if v else "red" for v in valid],
        "metadata": {MARKER: {"kind": "points", "source": source, "points_field": points_field}},
        **points_style(values, quantity),
        **placement,
    }
    point_kwargs["metadata"][MARKER].update(extra)
    u = np.where(valid[:, None], points_field.u, 0.0)
    magnitude = np.linalg.norm(u, axis=1)
    length = 1.0
    if exaggerate and magnitude.size and 0 < magnitude.max() < 0.5 * spacing:
        length = float(spacing / magnitude.max())
    data = np.stack([points_field.points, u], axis=1)[valid]
    vector_kwargs = {
        "name": layer_name("displacement", source),
        "features": {"magnitude": magnitude[valid]},
        "edge_color": "black",  # the points carry the colours; one colour reads over both
        "edge_width": max(0.3, size / 8),
        "vector_style": "arrow",
        "length": length,
        "metadata": {
            MARKER: {"kind": "point vectors", "source": source, "key": f"arrows ({source})"}
        },
        **placement,
    }
    return [(points_field.points, point_kwargs, "points"), (data, vector_kwargs, "vectors")]


def _points_unit(points_field, quantity: str) -> str:
    kind = QUANTITIES[quantity][1]
    if kind in ("magnitude", "displacement"):
        unit = points_field.metadata.get("unit")
        if unit:
            return str(unit)
        size = as_triple(points_field.metadata.get("voxel_size"), 1.0)
        return "vx" if np.allclose(size, 1.0) else "scale units"
    return unit_of(quantity, None)


def color_points(layer, quantity: str) -> bool:
    """Colour a points layer of :func:`points_layers` by ``quantity``; False if it has none."""
    entry = plugin_metadata(layer)
    features = {name: np.asarray(layer.features[name]) for name in layer.features.columns}
    if quantity not in features:
        return False
    style = points_style(features, quantity)
    if isinstance(style["face_color"], list):
        layer.face_color = style["face_color"]
    else:
        layer.face_colormap = style["face_colormap"]
        layer.face_contrast_limits = style["face_contrast_limits"]
        layer.face_color = quantity
    entry.update(quantity=quantity, unit=_points_unit(entry["points_field"], quantity))
    layer.name = layer_name(quantity, entry["source"])
    return True


def points_caption(layer) -> str:
    """What a points layer's colours show, with units and the colour range (short enough for
    the canvas overlay), e.g. ``"ux [vx] at the points: displacement along x; coolwarm -2.9 to
    2.9"``."""
    entry = plugin_metadata(layer) or {}
    quantity = entry.get("quantity", "")
    what = QUANTITIES.get(quantity, ("", ""))[0]
    text = f"{quantity} [{entry.get('unit', '')}] at the points: {what}"
    if quantity != "status" and quantity:
        low, high = layer.face_contrast_limits
        text += f"; {layer.face_colormap.name} {low:.3g} to {high:.3g}"
    else:
        text += "; converged white, failed in colour"
    return text


def show_points(viewer, points_field, placement: dict) -> str:
    """Show a points result (replacing the last one): the points coloured by the quantity on
    view (default ``|u|``) and their arrows, the caption on the canvas. Returns the panel's
    message: the counts by status. It does not name the quantity: the View panel recolours the
    points later, and the canvas caption (kept by the View panel) says what is shown."""
    from .layers import quantity_layers
    from .viewer_layers import canvas_overlay, show_layers, text_overlay

    current = next((x for x in quantity_layers(viewer) if x.visible), None)
    quantity = plugin_metadata(current).get("quantity") if current is not None else None
    tuples = points_layers(
        points_field, "points", quantity=quantity or DEFAULT_QUANTITY, **placement
    )
    layer, _ = show_layers(viewer, tuples)
    caption = points_caption(layer)
    text_overlay(viewer).text = caption
    text_overlay(viewer).visible = True
    canvas_overlay(viewer, "scale_bar").visible = True
    counts = points_field.node_counts().text().replace(" nodes", " points", 1)
    return (
        f"Done: {points_field.n_points} points: {counts}; the canvas caption says what the "
        "colours show."
    )
