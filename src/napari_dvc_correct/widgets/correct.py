"""The Self-correct dock: run the paper's self-correcting strategy on a field, pass by pass."""

from __future__ import annotations

from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QSpinBox,
    QTableWidget,
    QTableWidgetItem,
)

from .. import layers as L
from .. import viewer_layers as V
from ..engine.correction.options import CorrectionOptions
from . import correct_model as model
from ._base import EngineWidget, LayerCombo, follow_layers, pair_in_order
from ._layer_kinds import is_scan
from .correlate_model import (
    check_tiled,
    layer_placement,
    layer_volume,
    named_volume,
    suggest_tiled,
)
from .regions import RegionBox


class CorrectWidget(EngineWidget):
    """Self-correct the current field with the DVC parameters that produced it."""

    run_text = "Self-correct"

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(napari_viewer, parent)
        self._source = "uncorrected"  # the field the running correction started from
        self.field = QComboBox()
        self._chosen = None  # the field (or series' list of fields) the pair was last set for
        self.form.addRow("Field", self.field)
        self.reference = LayerCombo(self.viewer, is_scan)
        self.deformed = LayerCombo(self.viewer, is_scan)
        self.form.addRow("Reference (G)", self.reference)
        self.form.addRow("Deformed (F)", self.deformed)
        self.frame = QComboBox()
        for key, text in model.FRAMES.items():
            self.frame.addItem(text, key)
        self.update_rule = QComboBox()
        for key, text in model.UPDATES.items():
            self.update_rule.addItem(text, key)
        defaults = CorrectionOptions()
        for combo, key in ((self.frame, defaults.frame), (self.update_rule, defaults.update)):
            combo.setCurrentIndex(combo.findData(key))
        self.max_passes = QSpinBox()
        self.max_passes.setRange(1, max(10, defaults.max_passes))
        self.max_passes.setValue(defaults.max_passes)
        self.form.addRow("Frame", self.frame)
        self.form.addRow("Update", self.update_rule)
        self.form.addRow("Passes (at most)", self.max_passes)
        self.noise_fit = QCheckBox("fit noise-only regions")
        self.noise_fit.setChecked(defaults.noise_fit)
        self.noise_fit.setToolTip(
            "after the passes, replace a node by the least-squares affine fit over its 3x3x3 "
            "neighbourhood where a chi-square test says the neighbourhood holds only matching noise"
        )
        self.form.addRow("Regularise", self.noise_fit)
        self.add_out_of_core_row(
            "Warps and correlates block by block through temporary Zarr arrays, for scans "
            "larger than memory or opened lazily (Dask/Zarr; then ticked by itself). A pair or each "
            "state of a series."
        )
        self.region = RegionBox(self.viewer)  # masked nodes keep their input values
        self.controls.addWidget(self.region)
        self.reference.currentIndexChanged.connect(self._reference_changed)
        self.table = QTableWidget(0, len(model.PASS_HEADERS))
        self.table.setHorizontalHeaderLabels(model.PASS_HEADERS)
        self.table.verticalHeader().setVisible(False)
        self.table.setMaximumHeight(150)
        self.body.addWidget(self.table)
        self.field.currentIndexChanged.connect(self._field_changed)
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()
        self._reference_changed()

    def choices(self) -> dict:
        """Fields this panel can correct: name -> a field, or the list of a series' states."""
        found: dict = {}
        for layer in L.quantity_layers(self.viewer):
            source = L.plugin_metadata(layer)["source"]
            if model.is_corrected(source):
                continue
            series = L.series_of(layer)
            found.setdefault(source, series[1:] if series else L.field_of(layer))
        return found

    def _layers_changed(self, event=None) -> None:
        current = self.field.currentText()
        names = list(self.choices())
        self.field.blockSignals(True)
        self.field.clear()
        self.field.addItems(names)
        self.field.blockSignals(False)
        if current in names:
            self.field.setCurrentText(current)
        elif "uncorrected" in names:
            self.field.setCurrentText("uncorrected")
        if self.field.currentText() != current:
            self._field_changed()
        else:
            self._follow_field()
        pair_in_order(self.reference, self.deformed, event)

    def showEvent(self, event) -> None:
        """Brought to the front: the pair of the field now under the chosen name."""
        self._follow_field()
        super().showEvent(event)

    def _follow_field(self) -> None:
        """Take the pair of a new field under the chosen name: a new run replaces its layers in
        place (no layer-list event), e.g. Correlate again on (a, c) after (a, b)."""
        if not _same(self.choices().get(self.field.currentText()), self._chosen):
            self._field_changed()

    def _field_changed(self, *args) -> None:
        chosen = self.choices().get(self.field.currentText())
        self._chosen = chosen
        series = isinstance(chosen, list)
        self.reference.setEnabled(not series)  # a series brings its own volumes
        self.deformed.setEnabled(not series)
        if chosen is not None and not series:
            self.reference.set_layer(chosen.metadata.get("reference_layer", ""))
            self.deformed.set_layer(chosen.metadata.get("deformed_layer", ""))
        elif series:  # a lazily backed or very large series: out of core
            try:
                first = named_volume(self.viewer.layers, chosen[0].metadata["reference_layer"])
            except (KeyError, ValueError):
                return
            self.tiled.setChecked(suggest_tiled([first]))

    def _reference_changed(self, *args) -> None:
        """The region's defaults follow the reference scan (set once per volume size)."""
        layer = self.reference.layer()
        if layer is not None and layer.ndim in (3, 4):
            volume = layer_volume(layer, 0 if layer.ndim == 4 else None)
            self.region.set_volume(volume.shape, volume)
            if layer.ndim == 3:  # a lazily backed or very large scan: out of core
                self.tiled.setChecked(suggest_tiled([volume]))

    def _mask(self, volume, layer=None):
        """The region's mask for the volumes of ``volume`` (None: the whole volume)."""
        if self.region.volume_shape != tuple(volume.shape):
            self.region.set_volume(volume.shape, volume)
        placement = layer_placement(layer) if layer is not None else None
        return self.region.mask(volume.shape, volume, placement)

    def _options(self) -> CorrectionOptions:
        """The panel's :class:`CorrectionOptions` (what it does not show keeps its default)."""
        return CorrectionOptions(
            frame=self.frame.currentData(),
            update=self.update_rule.currentData(),
            max_passes=self.max_passes.value(),
            noise_fit=self.noise_fit.isChecked(),
        )

    def prepare(self):
        self._follow_field()  # never the pair of the field this name had before
        choices = self.choices()
        source = self.field.currentText()
        if source not in choices:
            raise ValueError("no field to correct: run Correlate first (or open a field file)")
        chosen = choices[source]
        if isinstance(chosen, list):  # a series: each state against state 0, its own volumes
            pairs = [
                (
                    named_volume(self.viewer.layers, f.metadata.get("reference_layer", "")),
                    named_volume(self.viewer.layers, f.metadata.get("deformed_layer", "")),
                )
                for f in chosen
            ]
            tiled = self.tiled.isChecked()
            memory = check_tiled("pair", None, self.max_memory.text()) if tiled else None
            self.table.setRowCount(0)
            self._series_source = source
            return model.run_series_correction(
                pairs,
                chosen,
                mask=self._mask(pairs[0][0]),
                tiled=tiled,
                max_memory=memory,
                options=self._options(),
            )
        reference, deformed = self.reference.layer(), self.deformed.layer()
        if reference is None or deformed is None:
            raise ValueError("choose the reference and deformed Image layers of this field")
        if reference.name == deformed.name:
            raise ValueError("the reference and deformed volumes are the same layer")
        g, f = layer_volume(reference), layer_volume(deformed)
        if g.ndim != 3 or g.shape != f.shape:
            raise ValueError(
                f"'{reference.name}' {g.shape} and '{deformed.name}' {f.shape} must be two 3-D "
                "volumes of the same shape"
            )
        mask = self._mask(g, reference)
        self._source = source
        tiled = self.tiled.isChecked()
        memory = check_tiled("pair", None, self.max_memory.text()) if tiled else None
        self.table.setRowCount(0)
        return model.run_correction(
            g, f, chosen, options=self._options(), mask=mask, tiled=tiled, max_memory=memory
        )

    def settings(self) -> dict:
        """The panel's options, JSON-friendly (for a session file)."""
        return {
            **self._options().as_dict(),
            "region": self.region.settings(),
            "tiled": self.tiled.isChecked(),
            "max_memory": self.max_memory.text(),
        }

    def restore(self, settings: dict) -> None:
        for combo, key in ((self.frame, "frame"), (self.update_rule, "update")):
            index = combo.findData(settings.get(key))
            if index >= 0:
                combo.setCurrentIndex(index)
        self.max_passes.setValue(int(settings.get("max_passes", self.max_passes.value())))
        self.noise_fit.setChecked(bool(settings.get("noise_fit", self.noise_fit.isChecked())))
        self.tiled.setChecked(bool(settings.get("tiled", self.tiled.isChecked())))
        self.max_memory.setText(str(settings.get("max_memory", "")))
        if "region" in settings:
            self.region.restore(settings["region"])

    def _fill_table(self, headers, rows) -> None:
        self.table.setColumnCount(len(headers))
        self.table.setHorizontalHeaderLabels(headers)
        self.table.setRowCount(len(rows))
        for r, row in enumerate(rows):
            for c, text in enumerate(row):
                self.table.setItem(r, c, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()

    def _series_result(self, result: model.SeriesCorrection) -> None:
        source = self._series_source
        corrected = model.corrected_source(source)
        first = result.results[0]
        placement = {"voxel_size": first.voxel_size, "offset": first.offset}
        yield from V.show_field_steps(
            self.viewer, L.field_layers(result.series, corrected, **placement)
        )
        rows = model.series_rows(result.results)
        self._fill_table(model.SERIES_HEADERS, rows)
        methods = model.series_method_message(result.results)
        self.show_message(
            "Self-corrected every state: "
            + "; ".join(f"{r[0]} {r[1]}" for r in rows)
            + "."
            + (f" {methods}" if methods else "")
        )

    def on_result(self, result) -> None:
        if isinstance(result, model.SeriesCorrection):
            yield from self._series_result(result)
            return
        yield from V.show_field_steps(
            self.viewer,
            L.field_layers(
                result.field,
                model.corrected_source(self._source),
                voxel_size=result.voxel_size,
                offset=result.offset,
            ),
        )
        self._fill_table(model.PASS_HEADERS, model.pass_rows(result.field))
        self.show_message(model.summary_message(result.field))


def _same(a, b) -> bool:
    """The same field object, or a series of the same field objects."""
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(x is y for x, y in zip(a, b))
    return a is b
