"""Which layers the panels offer in their pickers: the user's scans and regions, not our results."""

from __future__ import annotations

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
