"""The Correlate panel's read-out of a clicked POI: the values of the node nearest to a click."""

from __future__ import annotations

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import QGroupBox, QLabel, QVBoxLayout

from .. import layers as L
from . import correlate_model as model


def poi_readout_box() -> tuple[QGroupBox, QLabel]:
    """The "Clicked POI" box and its label."""
    box = QGroupBox("Clicked POI")
    layout = QVBoxLayout(box)
    label = QLabel("Click a point of the field to see its values.")
    label.setWordWrap(True)
    label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
    layout.addWidget(label)
    return box, label


class PoiReadout:
    """Mixin of a panel with ``viewer`` and ``poi_label``: a click shows the nearest node's
    displacement, ZNCC, status, provenance and iterations (register :meth:`_on_click` in the
    viewer's ``mouse_drag_callbacks``)."""

    # -- clicked POI --------------------------------------------------------------------------
    def _field_layer(self):
        """The field layer whose values a click shows: the selected one, else the topmost."""
        active = self.viewer.layers.selection.active
        if active is not None and L.field_of(active) is not None:
            return active
        for layer in reversed(self.viewer.layers):
            if L.field_of(layer) is not None and layer.visible:
                return layer
        return None

    def inspect(self, world_position) -> dict | None:
        """Show the values of the node nearest to ``world_position`` (z, y, x world units)."""
        layer = self._field_layer()
        if layer is None:
            return None
        field = L.field_of(layer)
        entry = L.plugin_metadata(layer)
        voxel_size = np.asarray(field.metadata.get("voxel_size", (1, 1, 1)), float)
        offset = np.asarray(field.metadata.get("offset", (0, 0, 0)), float)
        position = (np.asarray(world_position, float)[-3:] - offset) / voxel_size
        index = model.nearest_node(field, position)
        if index is None:
            return None
        values = model.describe_poi(field, index)
        self.poi_label.setText(model.poi_text(values, entry.get("source", "")))
        return values

    def _on_click(self, viewer, event) -> None:
        if event.type != "mouse_press" or event.button != 1:
            return
        try:
            self.inspect(event.position)
        except RuntimeError:  # the dock was closed: stop listening
            if self._on_click in viewer.mouse_drag_callbacks:
                viewer.mouse_drag_callbacks.remove(self._on_click)
