"""The Export dock: a field to NPZ/HDF5/VTK/TIFF/CSV, strain and residual to TIFF, the report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from qtpy.QtWidgets import QCheckBox, QComboBox, QFileDialog, QHBoxLayout, QLineEdit, QPushButton

from .. import layers as L
from . import export_model as model
from ._base import EngineWidget, follow_layers


class ExportWidget(EngineWidget):
    """Write the current field (uncorrected or corrected) and what was computed from it."""

    run_text = "Export"

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(napari_viewer, parent)
        self.field = QComboBox()
        self.form.addRow("Field", self.field)
        self.format = QComboBox()
        for label, suffix in model.FORMATS.items():
            self.format.addItem(label, suffix)
        self.form.addRow("Format", self.format)
        self.path = QLineEdit(str(Path.home() / "dvc_field.npz"))
        browse = QPushButton("Browse…")
        row = QHBoxLayout()
        row.addWidget(self.path)
        row.addWidget(browse)
        self.form.addRow("File", row)
        self.with_strain = QCheckBox("equivalent strain with the field")
        self.with_strain.setChecked(True)
        self.strain_tiff = QCheckBox("equivalent strain as a TIFF stack")
        self.residual_tiff = QCheckBox("gray residual volume as a TIFF stack")
        self.report = QCheckBox("evaluation report (.md and .json)")
        for box in (self.with_strain, self.strain_tiff, self.residual_tiff, self.report):
            self.form.addRow(box)
        browse.clicked.connect(self.browse)
        self.format.currentIndexChanged.connect(self._format_changed)
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()

    def _layers_changed(self, event=None) -> None:
        current = self.field.currentText()
        self.field.clear()
        names = list(L.fields_in(self.viewer.layers))
        self.field.addItems(names)
        if current in names:
            self.field.setCurrentText(current)
        elif "corrected" in names:
            self.field.setCurrentText("corrected")

    def _format_changed(self, *args) -> None:
        text = self.path.text().strip()
        if text:
            self.path.setText(str(Path(text).with_suffix(self.format.currentData())))

    def set_format(self, suffix: str) -> None:
        """Choose the format by file suffix (``".vti"``, ``".csv"``...)."""
        index = self.format.findData(suffix)
        if index < 0:
            raise ValueError(f"unknown export format {suffix!r}")
        self.format.setCurrentIndex(index)

    def browse(self, checked: bool = False) -> None:
        path, _ = QFileDialog.getSaveFileName(
            self, "Export the field", self.path.text(), f"*{self.format.currentData()}"
        )
        if path:
            self.path.setText(path)

    def _layer_of(self, source: str, kind: str):
        for layer in self.viewer.layers:
            entry = L.plugin_metadata(layer)
            if entry and entry.get("source") == source and entry.get("kind") == kind:
                return layer
        return None

    def prepare(self):
        source = self.field.currentText()
        fields = L.fields_in(self.viewer.layers)
        if source not in fields:
            raise ValueError("no field to export: run Correlate first (or open a field file)")
        field = fields[source]
        path = model.check_path(self.path.text(), self.format.currentData())
        strain_layer = self._layer_of(source, "equivalent strain")
        strain = None
        if self.with_strain.isChecked() or self.strain_tiff.isChecked():
            if strain_layer is not None:
                strain = np.asarray(strain_layer.data)
            else:
                from ..engine.strain import equivalent_strain_field

                strain = equivalent_strain_field(field)
        residual = report = None
        if self.residual_tiff.isChecked() or self.report.isChecked():
            residual_layer = self._layer_of(source, "residual")
            if residual_layer is None:
                raise ValueError(
                    f"no residual for the '{source}' field yet: run Evaluate first, or untick "
                    "the residual and report"
                )
            if self.residual_tiff.isChecked():
                residual = np.asarray(residual_layer.data)
            if self.report.isChecked():
                report = L.plugin_metadata(residual_layer).get("report")
        return model.run_export(
            model.ExportRequest(
                field=field,
                path=path,
                equivalent_strain=strain,
                strain_with_field=self.with_strain.isChecked(),
                strain_tiff=self.strain_tiff.isChecked(),
                residual=residual,
                report=report,
                voxel_size=tuple(field.metadata.get("voxel_size", (1.0, 1.0, 1.0))),
                offset=tuple(field.metadata.get("offset", (0.0, 0.0, 0.0))),
            )
        )

    def on_result(self, written) -> None:
        self.written = written
        names = ", ".join(p.name for p in written[:8])
        more = f" and {len(written) - 8} more" if len(written) > 8 else ""
        self.show_message(f"Wrote {names}{more} in {written[0].parent}.")
