"""The View dock: one quantity at a time, with its colorbar, before/after toggled, a 3-D view.

Every field shows as one quantity layer and its arrows (:func:`..layers.field_layers`). This dock
picks the quantity for all of them at once (the same colour range for the fields compared), which
field is on view (the others are hidden, not stacked), whether the colorbar and arrows show, and
an oblique 3-D view that shows a band across the specimen rather than looking down z.

The quantities (strain tensors, principal strains, percentiles) and the line profile are computed
in thread workers (:class:`._workers.LatestWorker`), so the viewer stays responsive on large grids:
the layers keep showing the previous quantity until the new one is ready, a quick second choice
supersedes the first (only the latest is shown), and every result is kept per field, so switching
back to a quantity seen before is instant.
"""

from __future__ import annotations

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import QCheckBox, QComboBox, QFormLayout, QLabel, QPushButton, QWidget

from .. import layers as L
from .. import point_layers as P
from .. import viewer_layers as V
from . import correct_model, profile_model
from ._base import compact, follow_layers
from ._plots import ProfileCanvas
from ._workers import LatestWorker

#: Camera of the 3-D view (napari's Euler angles, degrees): tilted 20–30° off the y axis, so a
#: band that contains y (a shear band slipping in the z-x plane) reads as a band, in depth.
OBLIQUE_ANGLES = (-20.0, 30.0, 120.0)
ALL_FIELDS = "all (overlaid)"
PROFILE_LINE = "profile line"


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
        self.draw_line = QPushButton("Line profile: draw a line")
        self.draw_line.setToolTip(
            "Adds a Shapes layer in line mode: click the start and the end of a line across "
            "the band; the plot shows the displacement and strain along it for every field"
        )
        form.addRow(self.draw_line)
        self.profile = ProfileCanvas()
        self.profile.setVisible(False)  # until a line is drawn
        form.addRow(self.profile)
        self.draw_line.clicked.connect(lambda checked=False: self.start_line())

        self.quantity.currentIndexChanged.connect(lambda *a: self.set_quantity())
        self.shown.currentIndexChanged.connect(lambda *a: self.show_source())
        self.swap.clicked.connect(lambda checked=False: self.before_after())
        self.colorbar.toggled.connect(lambda *a: self._decorate())
        self.arrows.toggled.connect(lambda *a: self.show_source())
        self.view_3d.clicked.connect(lambda checked=False: self.oblique_3d())
        self.view_2d.clicked.connect(lambda checked=False: setattr(self.viewer.dims, "ndisplay", 2))
        self._watched: set = set()
        self._quantity_worker = LatestWorker(self._quantity_failed)
        self._profile_worker = LatestWorker(self.message.setText)
        self._pending: dict | None = None
        self.profile_groups: list | None = None
        self._profile_values: dict = {}
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()
        compact(self)

    # -- line profile -----------------------------------------------------------------------
    def start_line(self):
        """The profile's Shapes layer (made the first time), selected in line-drawing mode."""
        layer = L.find_layer(self.viewer, PROFILE_LINE)
        if layer is None:
            kwargs = {
                "name": PROFILE_LINE,
                "ndim": max(3, self.viewer.dims.ndim),
                "edge_color": "cyan",
                "edge_width": 1.0,
                "metadata": {L.MARKER: {"kind": "profile", "source": "profile"}},
            }
            (layer,) = V.show_layers(self.viewer, [([], kwargs, "shapes")])
            layer.events.data.connect(lambda event=None: self.update_profile())
        self.viewer.layers.selection.active = layer
        layer.mode = "add_line"
        return layer

    def update_profile(self):
        """Plot the profiles along the last line drawn, computed in a worker.

        Returns the worker (None without a line or a field); the plot and
        :attr:`profile_groups` follow when it returns.
        """
        layer = L.find_layer(self.viewer, PROFILE_LINE)
        if layer is None or len(layer.data) == 0:
            return None
        vertices = np.asarray(layer.data[-1], float)
        start, end = (np.asarray(layer.data_to_world(v)) for v in (vertices[0], vertices[-1]))
        fields = {}
        for quantity_layer in L.quantity_layers(self.viewer):
            entry = L.plugin_metadata(quantity_layer)
            fields.setdefault(entry["source"], entry["field"])
        if not fields:
            self.message.setText("No field yet: run Correlate.")
            return None
        alive = {id(f) for f in fields.values()}  # values of replaced fields are dropped
        for key in [k for k in list(self._profile_values) if k[0] not in alive]:
            del self._profile_values[key]
        args = (fields, self.quantity.currentData(), start, end, self._profile_values)
        return self._profile_worker.start(_profiles, *args, on_returned=self._plot_profile)

    def _plot_profile(self, groups) -> None:
        self.profile_groups = groups
        self.profile.plot(groups)
        self.profile.setVisible(True)

    def _quantity_failed(self, text: str) -> None:
        self._pending = None
        self.message.setText(text)

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
        for layer in L.quantity_layers(self.viewer):
            if id(layer) not in self._watched:  # visibility set elsewhere (a new result...)
                layer.events.visible.connect(self._visibility_changed)
                layer.events.name.connect(self._visibility_changed)  # its quantity changed
                self._watched.add(id(layer))
                L.remember_quantity(layer)  # switching back to it is instant
        sources = self.sources()
        self.shown.blockSignals(True)
        self.shown.clear()
        self.shown.addItems(sources + ([ALL_FIELDS] if len(sources) > 1 else []))
        self.shown.blockSignals(False)
        inserted = getattr(event, "value", None)
        entry = L.plugin_metadata(inserted) if inserted is not None else None
        if entry is not None and entry.get("kind") == "quantity":
            if inserted.visible:  # a field opened from a file comes on view alone, as a result
                V.hide_other_fields(self.viewer, [inserted])
            quantity = entry.get("quantity")
            if quantity != self.quantity.currentData():
                self.quantity.blockSignals(True)
                self.quantity.setCurrentIndex(self.quantity.findData(quantity))
                self.quantity.blockSignals(False)
        self._decorate()

    @property
    def busy(self) -> bool:
        """True while a quantity or a profile is being computed."""
        return self._quantity_worker.busy or self._profile_worker.busy

    def set_quantity(self, quantity: str | None = None):
        """Show ``quantity`` (a key of :data:`..layers.QUANTITIES`) in every field layer.

        Values seen before come from the fields' caches at once; the others are computed in a
        worker, which is returned (None when nothing needed computing). The layers change
        together when all are ready, with one colour range.
        """
        if quantity is not None:
            self.quantity.setCurrentIndex(self.quantity.findData(quantity))
            return self._quantity_worker.worker  # the combo's signal came back here
        quantity = self.quantity.currentData()
        phases = L.find_layer(self.viewer, "phases")  # Evaluate's labels, drawn over the field:
        if phases is not None:  # its colours mixed into the quantity chosen (ticked back at will)
            phases.visible = False
        for layer in P.points_result_layers(self.viewer):  # a colour per point: at once
            P.color_points(layer, quantity)
        ready, problems, todo = {}, [], []
        for layer in L.quantity_layers(self.viewer):
            entry = L.plugin_metadata(layer)
            residual = self._layer(entry["source"], "residual")
            residual = None if residual is None else residual.data
            if quantity == "residual" and residual is None:
                problems.append(
                    f"no gray residual for the '{entry['source']}' field yet: run Evaluate first"
                )
                continue
            key = (quantity, id(residual) if quantity == "residual" else None)
            shown = entry.setdefault("shown", {})
            if key in shown:
                ready[entry["name"]] = shown[key]
            else:
                todo.append((entry["name"], entry, key, quantity, residual))
        self._pending = {"quantity": quantity, "ready": ready, "problems": problems}
        if not todo:
            self._quantity_worker.cancel()
            self._apply_pending()
            return None
        what = QUANTITY_WHAT.get(quantity, quantity)
        self.message.setText(f"computing {what} for {len(todo)} field(s)…")
        return self._quantity_worker.start(
            _quantity_updates,
            todo,
            on_yielded=self._quantity_computed,
            on_returned=lambda result: self._apply_pending(),
        )

    def _quantity_computed(self, value, current: bool) -> None:
        """One field's values (main thread): kept in its cache, and shown if still wanted."""
        name, entry, key, result, problem = value
        if result is not None:
            shown = entry.setdefault("shown", {})
            if key[0] == "residual":  # one residual kept: an older one is a whole volume
                for old in [k for k in shown if k[0] == "residual"]:
                    del shown[old]
            shown[key] = result
        if current and self._pending is not None:
            if result is not None:
                self._pending["ready"][name] = result
            else:
                self._pending["problems"].append(problem)

    def _apply_pending(self) -> None:
        pending, self._pending = self._pending, None
        if pending is None:
            return
        shown = []
        for name, (data, kwargs) in pending["ready"].items():
            layer = L.find_layer(self.viewer, name)
            if layer is not None:  # (a field replaced meanwhile keeps its new layer)
                L.apply_quantity(layer, data, kwargs)
                shown.append(layer)
        limits = L.shared_limits(shown, pending["quantity"])
        for layer in shown if limits is not None else []:
            layer.contrast_limits = limits
        self.message.setText("; ".join(pending["problems"]))
        self._decorate()
        self.update_profile()

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
        """Toggle between the field on view and its corrected one (or the panel's uncorrected and
        corrected fields); the source now on view."""
        pair = correct_model.before_after_pair(self.sources(), self._visible_sources())
        if pair is None:
            self.message.setText("Before/after needs an uncorrected and a corrected field.")
            return None
        target = pair[1]
        self.show_source(target)
        return target

    def _visibility_changed(self, event=None) -> None:
        try:
            self._decorate()
        except RuntimeError:  # the dock was closed
            pass

    def _visible_sources(self) -> list[str]:
        return [L.plugin_metadata(x)["source"] for x in L.quantity_layers(self.viewer) if x.visible]

    def _decorate(self) -> None:
        """Colorbar on the one quantity layer on top that is visible; caption with units."""
        visible = self._visible_sources()
        if visible:  # the choice says what is on view, however it got there
            self.shown.blockSignals(True)
            self.shown.setCurrentText(visible[0] if len(visible) == 1 else ALL_FIELDS)
            self.shown.blockSignals(False)
        layers = L.quantity_layers(self.viewer)
        visible = [x for x in layers if x.visible]
        top = visible[-1] if visible else None
        shown = L.plugin_metadata(top).get("quantity") if top is not None else None
        if shown is not None and shown != self.quantity.currentData() and not self.busy:
            # what is on view, however it got there (a new result shows the last quantity)
            self.quantity.blockSignals(True)
            self.quantity.setCurrentIndex(self.quantity.findData(shown))
            self.quantity.blockSignals(False)
        for layer in layers:
            layer.colorbar.visible = bool(layer is top and self.colorbar.isChecked())
        text = L.caption(top) if top is not None else "No field yet: run Correlate."
        title = L.colorbar_title(top) if top is not None else ""
        points = [x for x in P.points_result_layers(self.viewer) if x.visible]
        if top is None and points:  # only points of interest: their colours are the caption
            top, text = points[-1], P.points_caption(points[-1])
            title = text
        self.caption.setText(text)  # the whole caption in the panel, the short title on canvas
        V.text_overlay(self.viewer).text = title if top is not None else ""
        V.text_overlay(self.viewer).visible = top is not None

    def oblique_3d(self) -> None:
        """3-D view from an oblique angle, the quantity as an attenuated maximum projection."""
        self.viewer.dims.ndisplay = 3
        self.viewer.reset_view()  # (resets the angles too: set them after)
        scene = getattr(self.viewer, "scene", None)  # napari 0.9; older ones: viewer.camera
        camera = scene.camera if scene is not None else self.viewer.camera
        camera.angles = OBLIQUE_ANGLES
        camera.zoom *= 0.75  # the rotated volume fits the canvas
        for layer in L.quantity_layers(self.viewer):
            if layer.visible and np.asarray(layer.data).ndim >= 3:
                layer.rendering = "attenuated_mip"  # the nearest high values, not all of them
                quantity = L.plugin_metadata(layer).get("quantity")
                if L.QUANTITIES.get(quantity, ("", ""))[1] == "positive strain":
                    # the band stands out: the lower half of the values drawn dark
                    values = np.asarray(layer.data)
                    finite = values[np.isfinite(values)]
                    if finite.size:
                        low, high = np.percentile(finite, [50.0, 99.5])
                        if high > low:
                            layer.contrast_limits = [float(low), float(high)]


QUANTITY_WHAT = {key: what for key, (what, _) in L.QUANTITIES.items()}


def _quantity_updates(todo):
    """Worker: the new values of each field layer, one yield per field (so a newer choice can
    stop it between two fields). Touches no layer."""
    for name, entry, key, quantity, residual in todo:
        try:
            result = L.quantity_update(entry, quantity, residual=residual)
        except ValueError as error:
            yield name, entry, key, None, str(error)
            continue
        yield name, entry, key, result, None


def _profiles(fields, quantity, start, end, values_cache):
    """Worker: the line profiles (:func:`.profile_model.profiles`); a generator, so a newer
    line or quantity can stop it before it starts."""
    yield None
    return profile_model.profiles(fields, quantity, start, end, values_cache=values_cache)
