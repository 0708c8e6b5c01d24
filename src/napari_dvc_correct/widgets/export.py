"""The Export dock: a field to NPZ/HDF5/VTK/TIFF/CSV, strain and residual to TIFF, the report;
a result at points of interest to CSV/NPZ/VTU and the other tools' point formats."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPushButton,
)

from .. import layers as L
from .. import point_layers as P
from . import export_model as model
from ._base import EngineWidget, follow_layers


def default_folder(viewer) -> Path:
    """Where exports go unless the user says otherwise: the folder of the first opened scan."""
    for layer in viewer.layers:
        path = getattr(getattr(layer, "source", None), "path", None)
        if path:
            folder = Path(path)
            folder = folder if folder.is_dir() else folder.parent
            if folder.is_dir():
                return folder
    return Path.cwd()


class ExportWidget(EngineWidget):
    """Write the latest field (the corrected one once there is one) and what came from it.

    The Field choice follows each new result; the line under it says which field the export
    writes (corrected or not, passes, residuals) and the file name follows the field until the
    user edits it. Results at points of interest are listed too; for them the Format choice
    offers the point formats only (:data:`.export_model.POINT_FORMATS`) and the extras that need
    a grid are off.
    """

    run_text = "Export"

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(napari_viewer, parent)
        self.field = QComboBox()
        self.form.addRow("Field", self.field)
        self.writes = QLabel("")
        self.writes.setWordWrap(True)
        self.form.addRow("Writes", self.writes)
        self.format = QComboBox()
        self._formats = model.FORMATS
        for label, suffix in self._formats.items():
            self.format.addItem(label, suffix)
        self.form.addRow("Format", self.format)
        self.path = QLineEdit("")
        self._proposed = ""
        browse = QPushButton("Browse…")
        row = QHBoxLayout()
        row.addWidget(self.path)
        row.addWidget(browse)
        self.form.addRow("File", row)
        self.with_strain = QCheckBox("equivalent strain with the field")
        self.with_strain.setChecked(True)
        self.strain_tiff = QCheckBox("equivalent strain as a TIFF stack")
        self.residual_tiff = QCheckBox("gray residual volume as a TIFF stack")
        self.report = QCheckBox("evaluation report (folder, .json)")
        self.report.setToolTip(
            "NAME_report/: report.md with its plots and CSV tables, as evaluate --out-dir "
            "writes it; NAME_report.json: the numbers"
        )
        for box in (self.with_strain, self.strain_tiff, self.residual_tiff, self.report):
            self.form.addRow(box)
        sessions = QHBoxLayout()
        self.save_session_button = QPushButton("Save session…")
        self.open_session_button = QPushButton("Open session…")
        self.save_session_button.setToolTip(
            "The scans' paths, every panel's parameters and thresholds, and the fields"
        )
        sessions.addWidget(self.save_session_button)
        sessions.addWidget(self.open_session_button)
        self.form.addRow("Session", sessions)
        self.save_session_button.clicked.connect(lambda checked=False: self._session_dialog(True))
        self.open_session_button.clicked.connect(lambda checked=False: self._session_dialog(False))
        browse.clicked.connect(self.browse)
        self.format.currentIndexChanged.connect(self._format_changed)
        self.field.currentIndexChanged.connect(self._field_changed)
        for signal in (self.path.textEdited, self.format.currentIndexChanged):
            signal.connect(lambda *args: self.clear_message())
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()

    def fields(self) -> dict:
        """What the panel can export, by name: the grid fields, then the results at points."""
        fields = L.fields_in(self.viewer.layers)
        for source, points in P.points_in(self.viewer.layers).items():
            fields.setdefault(source, points)
        return fields

    def _layers_changed(self, event=None) -> None:
        """Keep the list of fields; a new field (the latest result) becomes the choice."""
        current = self.field.currentText()
        fields = self.fields()
        names = list(fields)
        inserted = getattr(event, "value", None) if event is not None else None
        latest = None
        if inserted is not None and L.field_of(inserted) is not None:
            source = L.plugin_metadata(inserted)["source"]
            series = L.series_of(inserted)
            latest = L.state_source(source, len(series) - 1) if series else source
        elif inserted is not None and (L.plugin_metadata(inserted) or {}).get("kind") == "points":
            latest = L.plugin_metadata(inserted)["source"]
        elif current not in names:
            corrected = [n for n in names if "corrected" in n and "uncorrected" not in n]
            latest = corrected[-1] if corrected else (names[-1] if names else None)
        self.field.blockSignals(True)
        self.field.clear()
        self.field.addItems(names)
        self.field.setCurrentText(latest if latest in names else current)
        self.field.blockSignals(False)
        self._field_changed()

    def _field_changed(self, *args) -> None:
        source = self.field.currentText()
        field = self.fields().get(source)
        self.writes.setText(model.describe(field, source) if field is not None else "no field yet")
        self._offer_formats(model.formats_for(field))
        grid = not model.is_points(field)
        for box in (self.strain_tiff, self.residual_tiff, self.report):
            box.setEnabled(grid)  # a result at points has no grid, residual or report
        # the file name follows the field until the user types their own
        text = self.path.text().strip()
        if field is not None and (not text or text == self._proposed):
            folder = Path(text).parent if text else default_folder(self.viewer)
            self._proposed = str(folder / model.default_name(source, self.format.currentData()))
            self.path.setText(self._proposed)

    def _offer_formats(self, formats: dict) -> None:
        """Offer ``formats`` (label -> suffix) in the Format choice, keeping the chosen suffix
        when it is among them (else the first: CSV for points, NPZ for grids)."""
        if formats is self._formats:
            return
        suffix = self.format.currentData()
        self._formats = formats
        self.format.blockSignals(True)
        self.format.clear()
        for label, value in formats.items():
            self.format.addItem(label, value)
        self.format.setCurrentIndex(max(0, self.format.findData(suffix)))
        self.format.blockSignals(False)
        if self.format.currentData() != suffix:
            self._format_changed()

    def _format_changed(self, *args) -> None:
        text = self.path.text().strip()
        if text:
            proposed = text == self._proposed
            self.path.setText(str(Path(text).with_suffix(self.format.currentData())))
            if proposed:
                self._proposed = self.path.text()

    def set_format(self, suffix: str) -> None:
        """Choose the format by file suffix (``".vti"``, ``".csv"``...)."""
        model.check_format(self.fields().get(self.field.currentText()), suffix)
        self.format.setCurrentIndex(self.format.findData(suffix))

    def browse(self, checked: bool = False) -> None:
        path, _ = QFileDialog.getSaveFileName(
            self, "Export the field", self.path.text(), f"*{self.format.currentData()}"
        )
        if path:
            self.path.setText(path)
            self._proposed = ""

    def panels(self) -> dict:
        """The plugin's other panels docked in the same window, by name (for sessions)."""
        from .correct import CorrectWidget
        from .correlate import CorrelateWidget
        from .evaluate import EvaluateWidget

        found = {}
        for name, cls in (
            ("Correlate", CorrelateWidget),
            ("Self-correct", CorrectWidget),
            ("Evaluate", EvaluateWidget),
        ):
            widgets = self.window().findChildren(cls)
            if widgets:
                found[name] = widgets[0]
        return found

    def _session_dialog(self, save: bool) -> None:
        from .session_model import SUFFIX

        folder = str(default_folder(self.viewer))
        if save:
            path, _ = QFileDialog.getSaveFileName(self, "Save the session", folder, f"*{SUFFIX}")
        else:
            path, _ = QFileDialog.getOpenFileName(self, "Open a session", folder, f"*{SUFFIX}")
        if path:
            self.session(path, save=save)

    def session(self, path, save: bool = True):
        """Save the session to ``path`` (or open it); the message line says what happened."""
        from . import session
        from ._showing import finish_all

        finish_all()  # the results still being shown, whole in the session
        self.clear_message()
        try:
            if save:
                written = session.save_session(self.viewer, path, self.panels())
                self.show_message(f"Session saved to {written}.")
                return written
            content = session.open_session(self.viewer, path, self.panels())
            self.show_message(
                f"Session opened: {len(content['scans'])} scans, {len(content['fields'])} fields."
            )
            return content
        except (ValueError, KeyError, TypeError, AttributeError, OSError) as error:
            # a hand-edited session's settings may not fit a panel: one line, never a raise
            self.show_message(str(error) or type(error).__name__, error=True)
            return None

    def _layer_of(self, source: str, kind: str):
        for layer in self.viewer.layers:
            entry = L.plugin_metadata(layer)
            if entry and entry.get("source") == source and entry.get("kind") == kind:
                return layer
        return None

    def prepare(self):
        source = self.field.currentText()
        fields = self.fields()
        if source not in fields:
            raise ValueError("no field to export: run Correlate first (or open a field file)")
        field = fields[source]
        path = model.check_path(self.path.text(), self.format.currentData())
        model.check_not_open(
            path, [getattr(getattr(x, "source", None), "path", None) for x in self.viewer.layers]
        )
        if model.is_points(field):  # (no grid: the grid's extras are off in the panel)
            return model.run_export(
                model.ExportRequest(
                    field=field,
                    path=path,
                    source=source,
                    strain_with_field=self.with_strain.isChecked(),
                    voxel_size=tuple(field.metadata.get("voxel_size", (1.0, 1.0, 1.0))),
                    offset=tuple(field.metadata.get("offset", (0.0, 0.0, 0.0))),
                )
            )
        strain = None
        if self.with_strain.isChecked() or self.strain_tiff.isChecked():
            from ..engine.evaluation.strain import equivalent_strain_field

            strain = equivalent_strain_field(field)
        residual = report = evaluation = None
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
                evaluation = L.plugin_metadata(residual_layer).get("evaluation")
        return model.run_export(
            model.ExportRequest(
                field=field,
                path=path,
                source=source,
                equivalent_strain=strain,
                strain_with_field=self.with_strain.isChecked(),
                strain_tiff=self.strain_tiff.isChecked(),
                residual=residual,
                report=report,
                evaluation=evaluation,
                voxel_size=tuple(field.metadata.get("voxel_size", (1.0, 1.0, 1.0))),
                offset=tuple(field.metadata.get("offset", (0.0, 0.0, 0.0))),
            )
        )

    def on_result(self, written) -> None:
        self.written = written
        names = ", ".join(p.name for p in written[:8])
        more = f" and {len(written) - 8} more" if len(written) > 8 else ""
        self.show_message(f"Wrote {names}{more} in {written[0].parent}.")
