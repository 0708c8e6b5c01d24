"""The View dock: one quantity at a time, with its colorbar, before/after toggled, a 3-D view.

Every field shows as one quantity layer and its arrows (:func:`..layers.field_layers`). This dock
picks the quantity for all of them at once (the same colour range for the fields compared), which
field is on view (the others are hidden, not stacked), whether the colorbar and arrows show, and
an oblique 3-D view that shows a band across the specimen rather than looking down z.
"""

from __future__ import annotations

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import QCheckBox, QComboBox, QFormLayout, QLabel, QPushButton, QWidget

from .. import layers as L
from ._base import follow_layers

#: Camera of the 3-D view: azimuth/elevation that show the three faces of the volume.
OBLIQUE_ANGLES = (0.0, -35.0, 145.0)
ALL_FIELDS = "all (overlaid)"


class ViewWidget(QWidget):
    """Choose the quantity shown, the field on view and the 3-D view."""

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        form = QFormLayout(self)
        self.quantity = QComboBox()
        for key, (what, _) in L.QUANTITIES.items():
            self.quantity.addItem(f"{key} — {what}", key)
        self.quantity.setCurrentIndex(self.quantity.findData(L.DEFAULT_QUANTITY))
        form.addRow("Quantity", self.quantity)
        self.shown = QComboBox()
        form.addRow("Field on view", self.shown)
        self.swap = QPushButton("Before ⇄ after")
        self.swap.setToolTip("Toggle between the uncorrected and the corrected field")
        form.addRow(self.swap)
        self.colorbar = QCheckBox("colorbar")
        self.colorbar.setChecked(True)
        self.arrows = QCheckBox("displacement arrows")
        self.arrows.setChecked(True)
        form.addRow(self.colorbar)
        form.addRow(self.arrows)
        self.view_3d = QPushButton("Oblique 3-D view")
        self.view_2d = QPushButton("2-D slices")
        form.addRow(self.view_3d)
        form.addRow(self.view_2d)
        self.caption = QLabel("")
        self.caption.setWordWrap(True)
        self.caption.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        form.addRow(self.caption)
        self.message = QLabel("")
        self.message.setWordWrap(True)
        form.addRow(self.message)

        self.quantity.currentIndexChanged.connect(lambda *a: self.set_quantity())
        self.shown.currentIndexChanged.connect(lambda *a: self.show_source())
        self.swap.clicked.connect(lambda checked=False: self.before_after())
        self.colorbar.toggled.connect(lambda *a: self._decorate())
        self.arrows.toggled.connect(lambda *a: self.show_source())
        self.view_3d.clicked.connect(lambda checked=False: self.oblique_3d())
        self.view_2d.clicked.connect(lambda checked=False: setattr(self.viewer.dims, "ndisplay", 2))
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()

    # -- state --------------------------------------------------------------------------------
    def sources(self) -> list[str]:
        return [L.plugin_metadata(x)["source"] for x in L.quantity_layers(self.viewer)]

    def _layer(self, source: str, kind: str = "quantity"):
        for layer in self.viewer.layers:
            entry = L.plugin_metadata(layer) or {}
            if entry.get("kind") == kind and entry.get("source") == source:
                return layer
        return None

    def _layers_changed(self, event=None) -> None:
        """Follow new fields: the newest one on view, showing the chosen quantity."""
        sources = self.sources()
        visible = [
            L.plugin_metadata(x)["source"] for x in L.quantity_layers(self.viewer) if x.visible
        ]
        self.shown.blockSignals(True)
        self.shown.clear()
        self.shown.addItems(sources + ([ALL_FIELDS] if len(sources) > 1 else []))
        if len(visible) == 1:
            self.shown.setCurrentText(visible[0])
        elif len(visible) > 1:
            self.shown.setCurrentText(ALL_FIELDS)
        self.shown.blockSignals(False)
        inserted = getattr(event, "value", None)
        entry = L.plugin_metadata(inserted) if inserted is not None else None
        if entry is not None and entry.get("kind") == "quantity":
            quantity = entry.get("quantity")
            if quantity != self.quantity.currentData():
                self.quantity.blockSignals(True)
                self.quantity.setCurrentIndex(self.quantity.findData(quantity))
                self.quantity.blockSignals(False)
        self._decorate()

    def set_quantity(self, quantity: str | None = None) -> None:
        """Show ``quantity`` (a key of :data:`..layers.QUANTITIES`) in every field layer."""
        if quantity is not None:
            self.quantity.setCurrentIndex(self.quantity.findData(quantity))
            return  # the combo's signal comes back here
        quantity = self.quantity.currentData()
        problems = []
        shown = []
        for layer in L.quantity_layers(self.viewer):
            source = L.plugin_metadata(layer)["source"]
            residual = self._layer(source, "residual")
            try:
                L.show_quantity(
                    layer, quantity, residual=None if residual is None else residual.data
                )
                shown.append(layer)
            except ValueError as error:
                problems.append(str(error))
        limits = L.shared_limits(shown, quantity)
        for layer in shown if limits is not None else []:
            layer.contrast_limits = limits
        self.message.setText("; ".join(problems))
        self._decorate()

    def show_source(self, source: str | None = None) -> None:
        """Put the field ``source`` on view (or all of them, overlaid) and hide the others."""
        if source is not None:
            self.shown.setCurrentText(source)
            return
        chosen = self.shown.currentText()
        for layer in self.viewer.layers:
            entry = L.plugin_metadata(layer) or {}
            if entry.get("kind") in ("quantity", "vectors"):
                on = chosen == ALL_FIELDS or entry.get("source") == chosen
                if entry["kind"] == "vectors":
                    on = on and self.arrows.isChecked()
                layer.visible = on
        self._decorate()

    def before_after(self) -> str | None:
        """Toggle between the uncorrected and the corrected field; the source now on view."""
        sources = self.sources()
        pair = [s for s in ("uncorrected", "corrected") if s in sources]
        if len(pair) < 2:
            self.message.setText("Before/after needs an uncorrected and a corrected field.")
            return None
        current = self.shown.currentText()
        target = "uncorrected" if current == "corrected" else "corrected"
        self.show_source(target)
        return target

    def _decorate(self) -> None:
        """Colorbar on the one quantity layer on top that is visible; caption with units."""
        layers = L.quantity_layers(self.viewer)
        visible = [x for x in layers if x.visible]
        top = visible[-1] if visible else None
        for layer in layers:
            layer.colorbar.visible = bool(layer is top and self.colorbar.isChecked())
        text = L.caption(top) if top is not None else "No field yet: run Correlate."
        self.caption.setText(text)
        self.viewer.text_overlay.text = text if top is not None else ""
        self.viewer.text_overlay.visible = top is not None

    def oblique_3d(self) -> None:
        """3-D view from an oblique angle, the quantity as a maximum projection."""
        self.viewer.dims.ndisplay = 3
        self.viewer.camera.angles = OBLIQUE_ANGLES
        self.viewer.reset_view()
        for layer in L.quantity_layers(self.viewer):
            if layer.visible and np.asarray(layer.data).ndim >= 3:
                layer.rendering = "mip"
