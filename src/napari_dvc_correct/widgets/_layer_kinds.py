"""Which layers the panels offer in their pickers: the user's scans and regions, not our results."""

from __future__ import annotations

import re

from napari.layers import Image, Labels, Points, Shapes

from .. import layers as L


def made_by_us(layer) -> bool:
    """Layers the plugin computed (fields, previews...), as opposed to input scans."""
    entry = L.plugin_metadata(layer)
    return entry is not None and "kind" in entry


def layer_role(layer) -> str | None:
    """``"reference"``, ``"deformed"`` or ``"series"`` for the sample data's layers."""
    entry = L.plugin_metadata(layer)
    return entry.get("role") if entry is not None else None


def is_scan(layer) -> bool:
    """A gray-level volume the user opened (not RGB, not one of our result layers)."""
    return isinstance(layer, Image) and not layer.rgb and not made_by_us(layer)


def is_mask(layer) -> bool:
    """A layer that can serve as a region: labels or shapes the user made."""
    return isinstance(layer, (Labels, Shapes)) and not made_by_us(layer)


def is_user_points(layer) -> bool:
    """A Points layer the user made (points of interest), not one of our previews or results."""
    return isinstance(layer, Points) and not made_by_us(layer)


#: Plugin layers that belong to one field and carry its source name.
_FIELD_KINDS = ("quantity", "vectors", "residual")


def distinct_source(layers, layer) -> str | None:
    """Give the field layer ``layer`` (just added to ``layers``) a source no other field uses.

    Two files with the same stem (``aldvc.npz``, ``aldvc.mat``) give two fields named
    ``aldvc``; napari numbers the second one's layers (``|u| (aldvc) [1]``) but the panels list
    fields by source, so the second could not be chosen. The newcomer becomes ``aldvc [1]``
    (its layer names follow: ``|u| (aldvc [1])``), and the other layers of the same field (the
    same :class:`DisplacementField` object, e.g. its arrows) take the same new name. A layer that
    replaces an older one of the same field name (a new result) keeps its name: the older one
    has left ``layers`` by then. Returns the new source, or None when nothing changed.
    """
    entry = L.plugin_metadata(layer)
    if entry is None or entry.get("kind") not in _FIELD_KINDS or "source" not in entry:
        return None
    source, field = entry["source"], entry.get("field")
    others = [
        (x, L.plugin_metadata(x))
        for x in layers
        if x is not layer and (L.plugin_metadata(x) or {}).get("kind") in _FIELD_KINDS
    ]
    clash = any(
        e.get("source") == source and e.get("kind") == entry["kind"] and e.get("field") is not field
        for _, e in others
    )
    if not clash:
        return None
    sibling = next(
        (e["source"] for _, e in others if field is not None and e.get("field") is field), None
    )
    taken = {e.get("source") for _, e in others}
    new = sibling
    number = 1
    while new is None or (new in taken and new != sibling):
        new, number = f"{source} [{number}]", number + 1
    name = re.sub(r" \[\d+\]$", "", layer.name)
    if name.endswith(f"({source})"):
        name = name[: -len(source) - 2] + f"({new})"
    entry["source"] = new
    if "name" in entry:
        entry["name"] = name
    layer.name = name
    return new
