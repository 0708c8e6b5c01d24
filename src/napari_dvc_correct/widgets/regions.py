"""The Region box of the panels: whole volume, cylinder or box along z, threshold, drawn layer.

A thin Qt form over :mod:`.regions_model`; the panel asks :meth:`RegionBox.mask` for the mask of
its volumes (None for the whole volume) and shows :func:`.regions_model.kept_pois` before a run.
"""

from __future__ import annotations

import numpy as np
from napari.layers import Labels, Shapes
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QSpinBox,
    QWidget,
)

from .. import layers as L
from . import regions_model as model
from ._base import LayerCombo


def _is_region_layer(layer) -> bool:
    entry = L.plugin_metadata(layer)
    return isinstance(layer, (Labels, Shapes)) and (entry is None or "kind" not in entry)


def _spin(low=0, high=100000, value=0, double=False, suffix=" vx"):
    box = QDoubleSpinBox() if double else QSpinBox()
    if double:
        box.setDecimals(2)
    box.setRange(low, high)
    box.setValue(value)
    if suffix:
        box.setSuffix(suffix)
    return box


def _pair(a, b) -> QWidget:
    row = QWidget()
    layout = QHBoxLayout(row)
    layout.setContentsMargins(0, 0, 0, 0)
    layout.addWidget(a)
    layout.addWidget(b)
    return row


class RegionBox(QGroupBox):
    """Where to measure: the region's kind and its few numbers, in voxels of the volume."""

    def __init__(self, viewer, parent=None) -> None:
        super().__init__("Region", parent)
        self.viewer = viewer
        form = QFormLayout(self)
        self.kind = QComboBox()
        for key, text in model.KINDS.items():
            self.kind.addItem(text, key)
        form.addRow("Measure in", self.kind)
        self.z_from, self.z_to = _spin(), _spin(value=100000)
        self.z_row = _pair(self.z_from, self.z_to)
        form.addRow("z from / to", self.z_row)
        self.centre_y, self.centre_x = _spin(double=True), _spin(double=True)
        self.radius = _spin(0.5, 100000, 10, double=True)
        self.centre_row = _pair(self.centre_y, self.centre_x)
        form.addRow("centre y / x", self.centre_row)
        form.addRow("radius", self.radius)
        self.y_from, self.y_to = _spin(), _spin(value=100000)
        self.x_from, self.x_to = _spin(), _spin(value=100000)
        self.y_row, self.x_row = _pair(self.y_from, self.y_to), _pair(self.x_from, self.x_to)
        form.addRow("y from / to", self.y_row)
        form.addRow("x from / to", self.x_row)
        self.threshold = _spin(-1e9, 1e9, 0, double=True, suffix="")
        self.fill_holes = QCheckBox("fill closed pores")
        self.fill_holes.setChecked(True)
        self.threshold_row = _pair(self.threshold, self.fill_holes)
        form.addRow("gray above", self.threshold_row)
        self.layer = LayerCombo(viewer, _is_region_layer, optional=True)
        form.addRow("layer", self.layer)
        self._rows = {
            "cylinder": (self.z_row, self.centre_row, self.radius),
            "box": (self.z_row, self.y_row, self.x_row),
            "threshold": (self.z_row, self.threshold_row),
            "layer": (self.z_row, self.layer),
        }
        self._form = form
        self._shape = None
        self._cache = (None, None)
        self.kind.currentIndexChanged.connect(self._kind_changed)
        self._kind_changed()

    # -- choices --------------------------------------------------------------------------
    @property
    def current_kind(self) -> str:
        return self.kind.currentData()

    def set_kind(self, kind: str) -> None:
        self.kind.setCurrentIndex(self.kind.findData(kind))

    def _kind_changed(self, *args) -> None:
        shown = self._rows.get(self.current_kind, ())
        every = {w for rows in self._rows.values() for w in rows}
        for widget in every:
            self._form.setRowVisible(widget, widget in shown)

    def changed_signals(self) -> list:
        """Signals of every control, for the panel's debounced preview."""
        signals = [self.kind.currentIndexChanged, self.layer.currentIndexChanged]
        signals += [self.fill_holes.toggled]
        for box in (self.z_from, self.z_to, self.centre_y, self.centre_x, self.radius):
            signals.append(box.valueChanged)
        for box in (self.y_from, self.y_to, self.x_from, self.x_to, self.threshold):
            signals.append(box.valueChanged)
        return signals

    @property
    def volume_shape(self) -> tuple | None:
        """Shape of the volume the defaults were set for (None before any)."""
        return self._shape

    def set_volume(self, shape, volume=None) -> None:
        """Defaults for a volume of ``shape``: full ranges, centred cylinder, Otsu threshold."""
        shape = tuple(int(n) for n in shape)
        if shape == self._shape:
            return
        self._shape = shape
        nz, ny, nx = shape
        for box, n in ((self.z_to, nz), (self.y_to, ny), (self.x_to, nx)):
            box.setValue(n)
        for box in (self.z_from, self.y_from, self.x_from):
            box.setValue(0)
        self.centre_y.setValue((ny - 1) / 2)
        self.centre_x.setValue((nx - 1) / 2)
        self.radius.setValue(round(0.45 * min(ny, nx), 1))
        if volume is not None:
            from .evaluate_model import automatic_thresholds

            try:
                self.threshold.setValue(float(automatic_thresholds(volume, 2)[0]))
            except ValueError:
                pass  # a constant volume: no threshold to suggest

    # -- the mask -------------------------------------------------------------------------
    def _key(self, shape, volume):
        kind = self.current_kind
        values = [b.value() for b in (self.z_from, self.z_to)]
        if kind == "cylinder":
            values += [b.value() for b in (self.centre_y, self.centre_x, self.radius)]
        elif kind == "box":
            values += [b.value() for b in (self.y_from, self.y_to, self.x_from, self.x_to)]
        elif kind == "threshold":
            values += [self.threshold.value(), self.fill_holes.isChecked(), id(volume)]
        elif kind == "layer":
            layer = self.layer.layer()
            values += [id(layer), id(getattr(layer, "data", None))]
            if isinstance(layer, Shapes):
                values += [len(layer.data)] + [float(np.sum(v)) for v in layer.data]
        return (kind, tuple(shape), tuple(values))

    def mask(self, shape, volume=None, placement=None) -> np.ndarray | None:
        """The region's mask for volumes of ``shape`` (None = whole volume); ValueError if bad.

        ``volume`` is the reference, for the threshold region; ``placement`` its
        ``(voxel_size, offset)``, for drawn shapes.
        """
        kind = self.current_kind
        if kind == "all":
            return None
        key = self._key(shape, volume)
        if self._cache[0] == key:
            return self._cache[1]
        z_range = (self.z_from.value(), self.z_to.value())
        if kind == "cylinder":
            mask = model.cylinder_mask(
                shape, (self.centre_y.value(), self.centre_x.value()), self.radius.value(), z_range
            )
        elif kind == "box":
            mask = model.box_mask(
                shape,
                z_range,
                (self.y_from.value(), self.y_to.value()),
                (self.x_from.value(), self.x_to.value()),
            )
        elif kind == "threshold":
            if volume is None:
                raise ValueError("choose the reference volume first")
            mask = model.threshold_mask(volume, self.threshold.value(), self.fill_holes.isChecked())
            mask &= model.box_mask(shape, z_range)
        else:
            layer = self.layer.layer()
            if layer is None:
                raise ValueError(
                    "the region is a layer but no mask is chosen: pick a Labels or Shapes layer"
                )
            voxel_size, offset = placement if placement is not None else (None, None)
            mask = model.layer_mask(layer, shape, z_range, voxel_size, offset)
        if not mask.any():
            raise ValueError("the region is empty: no voxel is selected")
        self._cache = (key, mask)
        return mask

    # -- sessions -------------------------------------------------------------------------
    def _boxes(self) -> dict:
        names = ("z_from", "z_to", "centre_y", "centre_x", "radius", "y_from", "y_to")
        names += ("x_from", "x_to", "threshold")
        return {name: getattr(self, name) for name in names}

    def settings(self) -> dict:
        values = {name: box.value() for name, box in self._boxes().items()}
        return {
            "kind": self.current_kind,
            "fill_holes": self.fill_holes.isChecked(),
            "layer": self.layer.currentText(),
            **values,
        }

    def restore(self, settings: dict) -> None:
        self.set_kind(settings.get("kind", "all"))
        self.fill_holes.setChecked(bool(settings.get("fill_holes", True)))
        self.layer.set_layer(settings.get("layer", ""))
        for name, box in self._boxes().items():
            if name in settings:
                box.setValue(settings[name])
