"""The Correlate dock: pick the scans and the parameters, preview the POI grid, run DVC."""

from __future__ import annotations

import time

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QHBoxLayout,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QSpinBox,
)

from .. import layers as L
from .. import point_layers as P
from .. import viewer_layers as V
from ..engine.correlation.params import MIN_SUBVOLUME, CorrelationParams
from ..engine.run_options import RunOptions
from . import correlate_model as model
from . import points_model, regions_model
from ._base import EngineWidget, LayerCombo, follow_layers, one_line, pair_in_order
from ._layer_kinds import is_mask, is_scan, is_user_points, layer_role
from ._workers import Debouncer
from .poi_readout import PoiReadout, poi_readout_box
from .regions import RegionBox

MODES = {
    "pair": "Pair: reference → deformed",
    "series4d": "Series: one 4-D layer (state, z, y, x)",
    "series": "Series: several layers (in list order)",
}
PLACEMENTS = {
    "grid": "regular grid (one POI every Step)",
    "points": "the points of a Points layer",
}
PREVIEW_POINTS = "POI grid (preview)"
PREVIEW_BOX = "subvolume (preview)"


class CorrelateWidget(PoiReadout, EngineWidget):
    """Run DVC between two scans (or along a scan series) and show the field as layers."""

    run_text = "Run DVC"

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(napari_viewer, parent)
        self.mode = QComboBox()
        for key, text in MODES.items():
            self.mode.addItem(text, key)
        self.form.addRow("Input", self.mode)
        self.reference = LayerCombo(self.viewer, is_scan)
        self.deformed = LayerCombo(self.viewer, is_scan)
        self.form.addRow("Reference (G)", self.reference)
        self.form.addRow("Deformed (F)", self.deformed)
        self.series_list = QListWidget()
        self.series_list.setMaximumHeight(110)
        self.form.addRow("States", self.series_list)
        self.strategy = QComboBox()
        self.strategy.addItem("total (every state against the first)", "total")
        self.strategy.addItem("incremental (state by state, composed)", "incremental")
        self.form.addRow("Strategy", self.strategy)
        self.correct_states = QCheckBox("self-correct every state")
        self.form.addRow("", self.correct_states)

        defaults = CorrelationParams()
        self.subvolume = QSpinBox()
        self.subvolume.setRange(MIN_SUBVOLUME, 401)
        self.subvolume.setSingleStep(2)
        self.subvolume.setValue(defaults.subvolume)
        self.subvolume.setSuffix(" vx")
        self.subvolume.setToolTip("Subvolume edge 2M+1 (odd), voxels")
        self.step = QSpinBox()
        self.step.setRange(1, 400)
        self.step.setValue(defaults.step)
        self.step.setSuffix(" vx")
        self.step.setToolTip("Spacing of the points of interest, voxels")
        self.order = QComboBox()
        self.order.addItem("1st order (affine, 12 parameters)", 1)
        self.order.addItem("2nd order (quadratic, 30 parameters)", 2)
        self.order.setCurrentIndex(self.order.findData(defaults.order))
        self.search_radius = QSpinBox()
        self.search_radius.setRange(0, 2000)
        self.search_radius.setSpecialValueText("auto")  # 0: CorrelationParams' None
        self.search_radius.setValue(defaults.search_radius or 0)
        self.search_radius.setSuffix(" vx")
        self.search_radius.setToolTip("Largest displacement to search for; 0 = auto")
        self.placement = QComboBox()
        for key, text in PLACEMENTS.items():
            self.placement.addItem(text, key)
        self.placement.setToolTip(
            "Where the points of interest are: a grid over the volume (or the region), or the "
            "points of a napari Points layer drawn over the scans (a pair only; the Step then "
            "sets the grid of the initial guess around them)"
        )
        self.points = LayerCombo(self.viewer, is_user_points)
        self.points.setToolTip(
            "A Points layer with 3-D points (z, y, x) over the reference scan; each point is "
            "matched at its nearest voxel and its subvolume must fit inside the volume"
        )
        self.form.addRow("POIs", self.placement)
        self.form.addRow("Points layer", self.points)
        self.form.addRow("Subvolume", self.subvolume)
        self.form.addRow("Step", self.step)
        self.form.addRow("Shape function", self.order)
        self.form.addRow("Search radius", self.search_radius)
        self.device = QComboBox()
        for key, text in model.DEVICES.items():
            self.device.addItem(text, key)
        self.device.setCurrentIndex(self.device.findData(RunOptions.device))
        self.device.setToolTip(
            "auto: a CUDA GPU when numba sees a working one, else the CPU (the run says which)"
        )
        self.form.addRow("Device", self.device)
        self.voxel_size = QDoubleSpinBox()
        self.voxel_size.setDecimals(4)
        self.voxel_size.setRange(1e-4, 1e6)
        self.voxel_size.setValue(1.0)
        self.voxel_size.setToolTip(
            "Physical size of a voxel (isotropic): it sets the scans' scale, the scale bar, the "
            "units of the displacements shown and the voxel size written with every export"
        )
        self.unit = QComboBox()
        for unit in model.UNITS:
            self.unit.addItem(unit or "voxels (no unit)", unit)
        voxel_row = QHBoxLayout()
        voxel_row.addWidget(self.voxel_size)
        voxel_row.addWidget(self.unit)
        self.form.addRow("Voxel size", voxel_row)
        self.add_out_of_core_row(
            "For scans larger than memory or opened lazily (Dask/Zarr): the field is the "
            "in-memory one (to ~1e-7 voxel), measured in batches that fit the memory limit; "
            "ticked by itself for such scans. A pair or a series on the grid; a pair at points."
        )
        self.preview = QCheckBox("preview the POI grid and one subvolume")
        self.preview.setChecked(True)
        self.form.addRow(self.preview)
        self.estimate_label = QLabel("")
        self.estimate_label.setWordWrap(True)
        self.form.addRow("Estimate", self.estimate_label)
        self.region = RegionBox(self.viewer)
        self.controls.addWidget(self.region)

        self.region.failed.connect(self.estimate_label.setText)
        self.poi_box, self.poi_label = poi_readout_box()
        self.body.addWidget(self.poi_box)

        self._update = Debouncer(self.update_preview, 200, self)
        for signal in (
            self.mode.currentIndexChanged,
            self.reference.currentIndexChanged,
            self.deformed.currentIndexChanged,
            self.subvolume.valueChanged,
            self.step.valueChanged,
            self.order.currentIndexChanged,
            self.search_radius.valueChanged,
            self.preview.toggled,
            self.tiled.toggled,
            self.series_list.itemChanged,
            self.placement.currentIndexChanged,
            *self.region.changed_signals(),
        ):
            signal.connect(self._settings_changed)
        self._preview_held = False
        self.mode.currentIndexChanged.connect(self._mode_changed)
        self.placement.currentIndexChanged.connect(self._mode_changed)
        self.points.currentIndexChanged.connect(self._points_edited)
        self._watched_points: set = set()
        self.reference.currentIndexChanged.connect(self._show_voxel_size)
        self._voxel_edited = False
        self.voxel_size.valueChanged.connect(lambda *a: setattr(self, "_voxel_edited", True))
        self.voxel_size.editingFinished.connect(self.apply_voxel_size)
        self.unit.currentIndexChanged.connect(self.apply_voxel_size)
        self.subvolume.editingFinished.connect(self._make_odd)
        follow_layers(self.viewer, self, self._layers_changed)
        self.viewer.mouse_drag_callbacks.append(self._on_click)
        self._layers_changed()
        self._mode_changed()
        self._show_voxel_size()

    # -- choices ------------------------------------------------------------------------------
    @property
    def current_mode(self) -> str:
        return self.mode.currentData()

    def _make_odd(self) -> None:
        if self.subvolume.value() % 2 == 0:
            self.subvolume.setValue(self.subvolume.value() + 1)

    def _mode_changed(self, *args) -> None:
        mode = self.current_mode
        self.deformed.setEnabled(mode == "pair")
        self.series_list.setEnabled(mode == "series")
        self.strategy.setEnabled(mode != "pair")
        self.correct_states.setEnabled(mode != "pair")
        label = self.form.labelForField(self.reference)
        if label is not None:
            label.setText("4-D series" if mode == "series4d" else "Reference (G)")
        self.points.setEnabled(self.placement.currentData() == "points")

    def _layers_changed(self, event=None) -> None:
        """Pick sensible inputs: the roles the sample data declares, else two different images."""
        images = self.reference.layers()
        inserted = getattr(event, "value", None) if event is not None else None
        if inserted is not None:  # napari ignores units that disagree (and warns on every draw)
            V.match_units(self.viewer, inserted)
        for layer in images if inserted is None else [inserted]:
            role = layer_role(layer)
            if role == "reference":
                self.reference.set_layer(layer)
            elif role == "deformed":
                self.deformed.set_layer(layer)
            elif role == "series":
                self.mode.setCurrentIndex(list(MODES).index("series4d"))
                self.reference.set_layer(layer)
        if self.current_mode == "pair":
            pair_in_order(self.reference, self.deformed, event)
        self._refresh_series_list(images)
        for layer in self.points.layers():  # moving or adding a point updates the estimate
            if id(layer) not in self._watched_points:
                layer.events.data.connect(self._points_edited)
                self._watched_points.add(id(layer))
        if inserted is not None and is_user_points(inserted):
            self.points.set_layer(inserted)
        poi_input = self.placement.currentData() == "points" and is_user_points(inserted)
        if inserted is None or is_scan(inserted) or is_mask(inserted) or poi_input:
            self._update.trigger()

    def _points_edited(self, event=None) -> None:
        if self.placement.currentData() == "points":
            self._update.trigger()

    def _scans(self) -> list:
        """The layers the current choice correlates (pair, 4-D series or ticked layers)."""
        mode = self.current_mode
        if mode == "pair":
            chosen = [self.reference.layer(), self.deformed.layer()]
        elif mode == "series4d":
            chosen = [self.reference.layer()]
        else:
            chosen = [self.viewer.layers[name] for name in self._ticked()]
        return [x for x in chosen if x is not None]

    def _show_voxel_size(self, *args) -> None:
        """Show the reference layer's voxel size (its scale along x) and unit; tick 'out of
        core' for a lazily backed or very large scan."""
        layer = self.reference.layer()
        if layer is None:
            return
        if layer.ndim == 3:
            self.tiled.setChecked(model.suggest_tiled([model.layer_volume(layer)]))
        if layer.ndim in (3, 4):  # the region's defaults follow the scans' size
            self.region.set_volume(
                layer.data.shape[-3:], model.layer_volume(layer, 0 if layer.ndim == 4 else None)
            )
        self.voxel_size.blockSignals(True)
        self.voxel_size.setValue(float(np.asarray(layer.scale)[-1]))
        self.voxel_size.blockSignals(False)
        unit = str(layer.units[-1]) if getattr(layer, "units", None) else ""
        symbol = {"nanometer": "nm", "micrometer": "µm", "millimeter": "mm"}.get(unit, "")
        self.unit.blockSignals(True)
        self.unit.setCurrentIndex(max(0, self.unit.findData(symbol)))
        self.unit.blockSignals(False)

    def apply_voxel_size(self, *args) -> None:
        """Give the chosen scans the voxel size (once typed) and unit of the form.

        The scans' scale, the scale bar, the fields' placement and the exports follow.
        """
        edited, self._voxel_edited = self._voxel_edited, False
        unit = self.unit.currentData()
        scans = self._scans()
        if edited:  # an anisotropic scale stays until the user types a size
            with V.KeepSliceAndFrame(self.viewer):  # the scan fills the canvas again
                for layer in scans:
                    layer.scale = model.voxel_scale(layer.scale, self.voxel_size.value())
        if unit:
            # every layer, not only the chosen scans (the others are a series' states): napari
            # ignores units that disagree and warns on every draw
            for layer in self.viewer.layers:
                layer.units = (unit,) * layer.ndim
            V.canvas_overlay(self.viewer, "scale_bar").visible = True
        self._update.trigger()

    def _ticked(self) -> list[str]:
        return [
            self.series_list.item(i).text()
            for i in range(self.series_list.count())
            if self.series_list.item(i).checkState() == Qt.CheckState.Checked
        ]

    def _refresh_series_list(self, images) -> None:
        checked = {
            self.series_list.item(i).text()
            for i in range(self.series_list.count())
            if self.series_list.item(i).checkState() == Qt.CheckState.Checked
        }
        self.series_list.blockSignals(True)
        self.series_list.clear()
        for layer in images:
            if layer.ndim != 3:
                continue
            item = QListWidgetItem(layer.name)
            item.setFlags(item.flags() | Qt.ItemFlag.ItemIsUserCheckable)
            item.setCheckState(
                Qt.CheckState.Checked if layer.name in checked else Qt.CheckState.Unchecked
            )
            self.series_list.addItem(item)
        self.series_list.blockSignals(False)

    def set_series_layers(self, names) -> None:
        """Tick the layers of a series (in the viewer's order); for scripts and tests."""
        for i in range(self.series_list.count()):
            item = self.series_list.item(i)
            state = Qt.CheckState.Checked if item.text() in names else Qt.CheckState.Unchecked
            item.setCheckState(state)

    def params(self):
        return model.make_params(
            self.subvolume.value(),
            self.step.value(),
            self.order.currentData(),
            self.search_radius.value(),
        )

    def job(self) -> model.CorrelationJob:
        """Check the choices and gather what the engine needs (raises ValueError)."""
        params = self.params()
        mode = self.current_mode
        reference = self.reference.layer()
        if mode == "pair":
            deformed = self.deformed.layer()
            model.check_pair(
                getattr(reference, "name", None),
                getattr(reference, "data", np.empty(0)).shape,
                getattr(deformed, "name", None),
                getattr(deformed, "data", np.empty(0)).shape,
            )
            volumes = [model.layer_volume(reference), model.layer_volume(deformed)]
            names = [reference.name, deformed.name]
            strategy = "pair"
        elif mode == "series4d":
            if reference is None:
                raise ValueError("choose the 4-D Image layer that holds the scan series")
            if reference.ndim != 4:
                raise ValueError(
                    f"'{reference.name}' has {reference.ndim} dimensions: the 4-D mode needs "
                    "(state, z, y, x)"
                )
            n_states = reference.data.shape[0]
            if n_states < 2:
                raise ValueError(f"'{reference.name}' holds only one state")
            volumes = [model.layer_volume(reference, t) for t in range(n_states)]
            names = [f"{reference.name}[{t}]" for t in range(n_states)]
            strategy = self.strategy.currentData()
        else:
            names = self._ticked()
            if len(names) < 2:
                raise ValueError("tick at least two layers of the series (first = reference)")
            chosen = [self.viewer.layers[name] for name in names]
            for layer in chosen:
                model.check_volume(layer.data.shape, layer.name)
            if len({layer.data.shape for layer in chosen}) > 1:
                raise ValueError("the layers of a series must all have the same shape")
            reference = chosen[0]
            volumes = [model.layer_volume(layer) for layer in chosen]
            strategy = self.strategy.currentData()
        model.check_volume(volumes[0].shape, names[0])
        if params.subvolume > min(volumes[0].shape):
            raise ValueError(
                f"subvolume {params.subvolume} is larger than the volume {volumes[0].shape}"
            )
        voxel_size, offset = model.layer_placement(reference)
        self.region.set_volume(volumes[0].shape, volumes[0])
        mask = self.region.mask(volumes[0].shape, volumes[0], (voxel_size, offset))
        # a lazy threshold or Labels region is counted by the run, not by reading it here
        quick = mask is not None and regions_model.counts_quickly(mask)
        kept = regions_model.check_kept(mask, params) if quick else None
        voxel_size, offset = model.layer_placement(reference)
        points, points_layer = self._points(reference, strategy, volumes[0].shape, params)
        tiled = self.tiled.isChecked()
        memory = model.check_tiled(strategy, points, self.max_memory.text()) if tiled else None
        return model.CorrelationJob(
            volumes=volumes,
            params=params,
            mask=mask,
            strategy=strategy,
            correct_states=strategy != "pair" and self.correct_states.isChecked(),
            voxel_size=voxel_size,
            offset=offset,
            names=names,
            device=self.device.currentData(),
            unit=self.unit.currentData() or None,
            kept=kept,
            points=points,
            points_layer=points_layer,
            tiled=tiled,
            max_memory=memory,
        )

    def _points(self, reference, strategy, shape, params):
        """The chosen points of interest in reference voxels and their layer's name, or
        ``(None, "")`` for the grid; ValueError when they cannot be used."""
        if self.placement.currentData() != "points":
            return None, ""
        layer = self.points.layer()
        points = points_model.job_points(layer, reference, strategy, shape, params)
        return points, layer.name

    # -- sessions -------------------------------------------------------------------------------
    def settings(self) -> dict:
        """The panel's choices, JSON-friendly (for a session file)."""
        return {
            "mode": self.current_mode,
            "reference": self.reference.currentText(),
            "deformed": self.deformed.currentText(),
            "series": self._ticked(),
            "strategy": self.strategy.currentData(),
            "correct_states": self.correct_states.isChecked(),
            "subvolume": self.subvolume.value(),
            "step": self.step.value(),
            "order": self.order.currentData(),
            "search_radius": self.search_radius.value(),
            "device": self.device.currentData(),
            "unit": self.unit.currentData(),
            "region": self.region.settings(),
            "placement": self.placement.currentData(),
            "tiled": self.tiled.isChecked(),
            "max_memory": self.max_memory.text(),
            "points": self.points.currentText(),
        }

    def restore(self, settings: dict) -> None:
        """Take back :meth:`settings` (missing entries keep their current value)."""
        for combo, key in (
            (self.mode, "mode"),
            (self.strategy, "strategy"),
            (self.order, "order"),
            (self.device, "device"),
            (self.placement, "placement"),
        ):
            if key in settings and combo.findData(settings[key]) >= 0:
                combo.setCurrentIndex(combo.findData(settings[key]))
        self.reference.set_layer(settings.get("reference", ""))
        self.deformed.set_layer(settings.get("deformed", ""))
        self.points.set_layer(settings.get("points", ""))
        self.set_series_layers(settings.get("series", []))
        self.correct_states.setChecked(bool(settings.get("correct_states", False)))
        self.tiled.setChecked(bool(settings.get("tiled", self.tiled.isChecked())))
        self.max_memory.setText(str(settings.get("max_memory", "")))
        for box, key in ((self.subvolume, "subvolume"), (self.step, "step")):
            if key in settings:
                box.setValue(int(settings[key]))
        self.search_radius.setValue(int(settings.get("search_radius", 0)))
        self.unit.blockSignals(True)  # the scans' scale came back with them
        self.unit.setCurrentIndex(max(0, self.unit.findData(settings.get("unit", ""))))
        self.unit.blockSignals(False)
        self._show_voxel_size()
        if "region" in settings:
            self.region.restore(settings["region"])
        self._update.trigger()

    # -- preview and estimate ------------------------------------------------------------------
    def _settings_changed(self, *args) -> None:
        self._preview_held = False  # the user changed something: the preview may show again
        self._update.trigger()

    def hold_preview(self) -> None:
        """Keep the grid preview hidden (a reopened session shows its fields, as after a run)
        until a setting of the panel changes."""
        self._update.flush()
        self._preview_held = True
        self._set_preview_visible(False)

    def update_preview(self) -> None:
        """Redraw the POI grid preview and the estimate (debounced from every change).

        A region's mask is computed in a worker first (a threshold with pores filled takes
        seconds on a large scan); the preview follows when it is ready."""
        scans = [x for x in self._scans() if x.ndim in (3, 4)]
        if scans:  # (the reference, or state 0 of a 4-D series: what job() measures on)
            volume = model.layer_volume(scans[0], 0 if scans[0].ndim == 4 else None)
            self.region.set_volume(volume.shape, volume)
            if self.region.compute_ahead(volume, self.update_preview):
                self.estimate_label.setText("computing the region's mask…")
                return
        try:
            job = self.job()
        except ValueError as error:
            self.estimate_label.setText(one_line(error))
            self._set_preview_visible(False)
            return
        if job.points is not None:
            self.estimate_label.setText(
                f"{len(job.points):,} points of interest from '{job.points_layer}', each with "
                f"its {job.params.subvolume}³ subvolume inside the volume; initial guess on a "
                f"grid of step {job.params.step} around them"
            )
            self._set_preview_visible(False)
            return
        estimate = model.estimate_run(job.shape, job.params, n_pairs=len(job.volumes) - 1)
        region = f"; {job.kept.text()}" if job.kept is not None else ""
        if job.mask is not None and job.kept is None:
            region = "; the run marks the POIs outside the region (read as it runs)"
        self.estimate_label.setText(estimate.text() + region)
        if not self.preview.isChecked() or self._preview_held:
            self._set_preview_visible(False)
            return
        points, box, _ = model.grid_preview(job.shape, job.params)
        if job.kept is not None:  # the POIs the region keeps, so the region shows
            points = points[regions_model.kept_at(job.mask, job.params, points)]
        placement = L.dense_placement(job.voxel_size, job.offset)
        points_style = {
            "size": max(1.0, job.params.step / 3),
            "face_color": "yellow",
            "border_width": 0,
            "opacity": 0.7,
        }
        box_style = {
            "shape_type": "rectangle",
            "edge_color": "cyan",
            "face_color": "transparent",
            "edge_width": 0.5,
        }
        self._show_preview(PREVIEW_POINTS, points, "points", placement, points_style)
        self._show_preview(PREVIEW_BOX, box, "shapes", placement, box_style)
        self._slice_on_grid(job)

    def _slice_on_grid(self, job) -> None:
        """In 2-D, move the z slider onto a plane of POIs if it sits between two (or the grid
        preview shows nothing): the central plane of the grid."""
        if self.viewer.dims.ndisplay != 2 or self.viewer.dims.ndim < 3:
            return
        origin, step, shape = model.grid_for_volume(
            job.shape, job.params.subvolume, job.params.step
        )
        axis = self.viewer.dims.ndim - 3
        vs, off = float(job.voxel_size[0]), float(job.offset[0])
        z = (float(self.viewer.dims.point[axis]) - off) / vs  # voxels
        index = (z - origin[0]) / step[0]
        on_grid = abs(index - round(index)) * step[0] < 0.5 and 0 <= round(index) < shape[0]
        if not on_grid:
            centre = origin[0] + step[0] * (shape[0] // 2)
            self.viewer.dims.set_point(axis, off + centre * vs)

    def _show_preview(self, name: str, data, layer_type: str, placement: dict, style: dict):
        """Update the preview layer ``name`` in place, or make it the first time."""
        layer = L.find_layer(self.viewer, name)
        if layer is not None:
            layer.data = data
            layer.scale, layer.translate = placement["scale"], placement["translate"]
            layer.visible = True
            return
        meta = {L.MARKER: {"kind": "preview", "source": "preview"}}
        kwargs = {"name": name, "metadata": meta, **style, **placement}
        V.show_layers(self.viewer, [(data, kwargs, layer_type)])

    def _set_preview_visible(self, visible: bool) -> None:
        for name in (PREVIEW_POINTS, PREVIEW_BOX):
            layer = L.find_layer(self.viewer, name)
            if layer is not None:
                layer.visible = visible

    # -- running ------------------------------------------------------------------------------
    def prepare(self):
        self._update.timer.stop()
        if self._voxel_edited:  # typed but not confirmed yet
            self.apply_voxel_size()
        job = self.job()
        self._started = (
            time.perf_counter(),
            job.shape,
            job.params,
            len(job.volumes) - 1,
            job.mask is not None,
        )
        return model.run_job(job)

    def on_result(self, result: model.CorrelationResult) -> None:
        started, shape, params, n_pairs, _ = self._started
        model.record_timing(time.perf_counter() - started, shape, params, n_pairs)
        self._set_preview_visible(False)
        placement = {"voxel_size": result.voxel_size, "offset": result.offset}
        if result.fields and result.fields[0][0] == "points":
            self.show_message(P.show_points(self.viewer, result.fields[0][1], placement))
            return
        if len(result.fields) == 1:
            source, field = result.fields[0]
            yield from V.show_field_steps(self.viewer, L.field_layers(field, source, **placement))
        else:  # a series: one 4-D field, state 0 (no displacement) first, made in the worker
            source = "series " + result.fields[0][0].split(" ", 2)[2]
            tuples = L.field_layers(result.series, source, **placement)
            yield from V.show_field_steps(self.viewer, tuples)
        self.show_message(model.done_message(result, region_given=self._started[4]))
