"""The Self-correct dock: run the paper's self-correcting strategy on a field, pass by pass."""

from __future__ import annotations

from qtpy.QtWidgets import QCheckBox, QComboBox, QSpinBox, QTableWidget, QTableWidgetItem

from .. import layers as L
from . import correct_model as model
from ._base import EngineWidget, LayerCombo, follow_layers, pair_in_order
from .correlate import _is_image, _is_mask
from .correlate_model import layer_volume, mask_from_layer


class CorrectWidget(EngineWidget):
    """Self-correct the current field with the DVC parameters that produced it."""

    run_text = "Self-correct"

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(napari_viewer, parent)
        self.field = QComboBox()
        self.form.addRow("Field", self.field)
        self.reference = LayerCombo(self.viewer, _is_image)
        self.deformed = LayerCombo(self.viewer, _is_image)
        self.form.addRow("Reference (G)", self.reference)
        self.form.addRow("Deformed (F)", self.deformed)
        self.use_mask = QCheckBox("only inside a mask")
        self.mask = LayerCombo(self.viewer, _is_mask, optional=True)
        self.form.addRow(self.use_mask, self.mask)
        self.frame = QComboBox()
        for key, text in model.FRAMES.items():
            self.frame.addItem(text, key)
        self.update_rule = QComboBox()
        for key, text in model.UPDATES.items():
            self.update_rule.addItem(text, key)
        self.max_passes = QSpinBox()
        self.max_passes.setRange(1, 10)
        self.max_passes.setValue(3)
        self.form.addRow("Frame", self.frame)
        self.form.addRow("Update", self.update_rule)
        self.form.addRow("Passes (at most)", self.max_passes)
        self.table = QTableWidget(0, 4)
        self.table.setHorizontalHeaderLabels(["pass", "mean residual", "applied", "nodes moved"])
        self.table.verticalHeader().setVisible(False)
        self.table.setMaximumHeight(150)
        self.body.addWidget(self.table)
        self.field.currentIndexChanged.connect(self._field_changed)
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()

    def _layers_changed(self, event=None) -> None:
        current = self.field.currentText()
        names = [name for name in L.fields_in(self.viewer.layers) if name != "corrected"]
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
        pair_in_order(self.reference, self.deformed, event)

    def _field_changed(self, *args) -> None:
        field = L.fields_in(self.viewer.layers).get(self.field.currentText())
        if field is not None:
            self.reference.set_layer(field.metadata.get("reference_layer", ""))
            self.deformed.set_layer(field.metadata.get("deformed_layer", ""))

    def prepare(self):
        fields = L.fields_in(self.viewer.layers)
        source = self.field.currentText()
        if source not in fields:
            raise ValueError("no field to correct: run Correlate first (or open a field file)")
        reference, deformed = self.reference.layer(), self.deformed.layer()
        if reference is None or deformed is None:
            raise ValueError("choose the reference and deformed Image layers of this field")
        if reference is deformed:
            raise ValueError("the reference and deformed volumes are the same layer")
        g, f = layer_volume(reference), layer_volume(deformed)
        if g.ndim != 3 or g.shape != f.shape:
            raise ValueError(
                f"'{reference.name}' {g.shape} and '{deformed.name}' {f.shape} must be two 3-D "
                "volumes of the same shape"
            )
        mask = None
        if self.use_mask.isChecked():
            layer = self.mask.layer()
            if layer is None:
                raise ValueError("'only inside a mask' is ticked but no mask is chosen")
            mask = mask_from_layer(layer, g.shape)
        self.table.setRowCount(0)
        return model.run_correction(
            g,
            f,
            fields[source],
            frame=self.frame.currentData(),
            update=self.update_rule.currentData(),
            max_passes=self.max_passes.value(),
            mask=mask,
        )

    def on_result(self, result: model.CorrectionResult) -> None:
        L.show_field(
            self.viewer,
            L.field_layers(
                result.field, "corrected", voxel_size=result.voxel_size, offset=result.offset
            ),
        )
        rows = model.pass_rows(result.field)
        self.table.setRowCount(len(rows))
        for r, row in enumerate(rows):
            for c, text in enumerate(row):
                self.table.setItem(r, c, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        info = result.field.metadata.get("correction", {})
        self.show_message(
            f"Mean gray residual {info.get('mean_gray_residual_before', float('nan')):.3f} → "
            f"{info.get('mean_gray_residual_after', float('nan')):.3f} "
            f"({info.get('passes_applied', 0)} pass(es) applied)."
        )
