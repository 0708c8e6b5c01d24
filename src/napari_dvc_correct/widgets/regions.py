"""The Region box of the panels: whole volume, cylinder or box along z, threshold, drawn layer.

A thin Qt form over :mod:`.regions_model`; the panel asks :meth:`RegionBox.mask` for the mask of
its volumes (None for the whole volume) and shows :func:`.regions_model.kept_pois` before a run.
"""

from __future__ import annotations

import numpy as np
from napari.layers import Labels, Shapes
from qtpy.QtCore import Signal
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
from ._workers import LatestWorker
from .correlate_model import is_lazy


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

    #: The one-line message of a mask that could not be computed ahead (:meth:`compute_ahead`).
    failed = Signal(str)

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
        self._worker = LatestWorker(lambda text: self.failed.emit(text))
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
            values += [self.threshold.value(), self.fill_holes.isChecked(), _identity(volume)]
        elif kind == "layer":
            layer = self.layer.layer()
            values += [id(layer), id(getattr(layer, "data", None))]
            if isinstance(layer, Shapes):
                values += [len(layer.data)] + [float(np.sum(v)) for v in layer.data]
        return (kind, tuple(shape), tuple(values))

    def mask(self, shape, volume=None, placement=None):
        """The region's mask for volumes of ``shape`` (None = whole volume); ValueError if bad.

        A boolean array, or a lazy :class:`.regions_model.Region` (cylinders, boxes and drawn
        outlines always; a threshold or a Labels layer over a lazily backed scan), which an
        out-of-core run reads block by block. ``volume`` is the reference, for the threshold
        region; ``placement`` its ``(voxel_size, offset)``, for drawn shapes. Computed here
        unless :meth:`pending` ran it in a worker first (the panels' previews do).
        """
        kind = self.current_kind
        if kind == "all":
            return None
        key = self._key(shape, volume)
        if self._cache[0] != key:
            if kind == "layer":
                layer = self.layer.layer()
                if layer is None:
                    raise ValueError(
                        "the region is a layer but no mask is chosen: pick a Labels or Shapes layer"
                    )
                voxel_size, offset = placement if placement is not None else (None, None)
                z_range = (self.z_from.value(), self.z_to.value())
                mask = model.layer_region(layer, shape, z_range, voxel_size, offset)
                if not is_lazy(getattr(layer, "data", None)) and not model.counts_quickly(mask):
                    mask = np.asarray(mask)  # Labels in memory: one array, counted by its table
            else:
                mask = self._computer(shape, volume)()
            self._cache = (key, mask)
        mask = self._cache[1]
        if model.emptiness(mask):  # unknown for a lazy region not read yet: the run says
            raise ValueError("the region is empty: no voxel is selected")
        return mask

    def pending(self, shape, volume=None):
        """``(key, compute)`` when :meth:`mask` would have to compute a cylinder, box or
        threshold mask; None when it is instant (whole volume, already computed) or reads a
        drawn layer (done on the main thread). ``compute()`` touches no Qt object nor layer: a
        worker runs it, and :meth:`store` keeps its result. ValueError if the choice is bad.
        """
        kind = self.current_kind
        if kind in ("all", "layer"):
            return None
        key = self._key(shape, volume)
        if self._cache[0] == key:
            return None
        return key, self._computer(shape, volume)

    def store(self, key, mask) -> None:
        """Keep a mask :meth:`pending`'s ``compute`` made (main thread)."""
        self._cache = (key, mask)

    def compute_ahead(self, volume, then) -> bool:
        """Make the mask for ``volume`` (the reference) in a worker when it is not ready.

        Returns True when a worker started: it keeps the mask (and its summed-volume table,
        for the POI count) and then calls ``then()`` on the main thread; a newer call
        supersedes it. False when :meth:`mask` is instant or will report a bad choice itself.
        """
        try:
            pending = self.pending(volume.shape, volume)
        except ValueError:
            return False
        if pending is None:
            return False
        key, compute = pending

        def ready(mask) -> None:
            self.store(key, mask)
            then()

        self._worker.start(_mask_in_worker, compute, on_returned=ready)
        return True

    @property
    def busy(self) -> bool:
        """True while a mask is computed ahead."""
        return self._worker.busy

    def _computer(self, shape, volume):
        """A function of no argument that makes the mask of the current choices (read now)."""
        kind = self.current_kind
        z_range = (self.z_from.value(), self.z_to.value())
        if kind == "cylinder":
            centre, radius = (self.centre_y.value(), self.centre_x.value()), self.radius.value()
            return lambda: model.cylinder_region(shape, centre, radius, z_range)
        if kind == "box":
            ranges = (
                (self.y_from.value(), self.y_to.value()),
                (self.x_from.value(), self.x_to.value()),
            )
            return lambda: model.box_region(shape, z_range, *ranges)
        if volume is None:
            raise ValueError("choose the reference volume first")
        threshold, fill = self.threshold.value(), self.fill_holes.isChecked()
        region = model.ThresholdRegion(volume, threshold, fill, z_range)
        if is_lazy(volume):  # read slab by slab when a run (or the emptiness check) needs it
            return lambda: region
        return lambda: np.asarray(region)

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


def _identity(volume):
    """What identifies a volume for the mask cache: a numpy view by its memory, not its id (a
    state of a 4-D layer is a new view at every access)."""
    if isinstance(volume, np.ndarray):
        return (
            id(volume if volume.base is None else volume.base),
            volume.__array_interface__["data"][0],
            volume.shape,
        )
    return id(volume)


def _mask_in_worker(compute):
    """Worker: the mask, and what the panel's checks need of it (no Qt, no layer): an array's
    summed-volume table for the POI count, whether a lazy region selects any voxel."""
    yield None
    mask = compute()
    if isinstance(mask, np.ndarray):
        model.summed_volume(mask)
    else:
        mask.any()
    return mask
