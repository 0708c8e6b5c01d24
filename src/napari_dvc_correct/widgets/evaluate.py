"""The Evaluate dock: phases by gray thresholds, background residual, accuracy index, curves."""

from __future__ import annotations

import atexit

import numpy as np
from qtpy.QtCore import Qt
from qtpy.QtWidgets import (
    QComboBox,
    QFrame,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QListWidget,
    QListWidgetItem,
    QPushButton,
    QScrollArea,
    QSpinBox,
)
from superqt import QDoubleRangeSlider
from superqt.utils import GeneratorWorker

from .. import layers as L
from .. import viewer_layers as V
from ..engine.evaluation.options import MAX_PHASES, EvaluationOptions
from . import evaluate_model as model
from ._base import EngineWidget, LayerCombo, follow_layers, one_line, pair_in_order
from ._layer_kinds import is_scan
from ._plots import CurvesCanvas, HistogramCanvas, SeriesCanvas
from ._workers import Debouncer, LatestWorker
from .correlate_model import (
    check_tiled,
    layer_placement,
    layer_volume,
    named_volume,
    suggest_tiled,
)
from .regions import RegionBox

#: Key of a residual layer's plugin metadata: the temporary folder it reads lazily.
TEMPORARY_KEY = "temporary_folder"

MODES = {
    "reference": "reference frame: |map(F)(X + u) − G(X)|",
    "loaded": "loaded state: |map(F) − G'| (paper)",
}


class EvaluateWidget(EngineWidget):
    """Accuracy of the fields without ground truth (paper section 2.2, eqs. 1–3, Figs. 10–11)."""

    run_text = "Evaluate"

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(napari_viewer, parent)
        # out-of-core residuals: removed when no layer reads them any more, the rest at exit
        self._temporary = model.TemporaryFolders()
        self._writing = None  # the folder of the run in progress
        atexit.register(self._temporary.remove_all)
        self.viewer.layers.events.removed.connect(self._release_temporary)
        self.reference = LayerCombo(self.viewer, is_scan)
        self.deformed = LayerCombo(self.viewer, is_scan)
        self.form.addRow("Reference (G)", self.reference)
        self.form.addRow("Deformed (F)", self.deformed)
        self.fields = QListWidget()
        self.fields.setMaximumHeight(70)
        self.form.addRow("Fields", self.fields)
        self.mode = QComboBox()
        for key, text in MODES.items():
            self.mode.addItem(text, key)
        self.mode.setCurrentIndex(self.mode.findData(EvaluationOptions.mode))
        self.form.addRow("Residual", self.mode)
        self.add_out_of_core_row(
            "Reads the scans block by block and writes each residual to a temporary Zarr "
            "array (shown lazily), for scans larger than memory or opened lazily (then ticked "
            "by itself). Same numbers as in memory. A pair (its residual kept on disk) or every "
            "state of a series (the numbers only)."
        )

        # the specimen: phases, r0 and the residual statistics use only its voxels
        self.region = RegionBox(self.viewer)
        self.controls.addWidget(self.region)

        self.n_phases = QSpinBox()
        self.n_phases.setRange(2, MAX_PHASES)
        self.n_phases.setValue(EvaluationOptions.n_phases)
        self.auto_button = QPushButton("Auto (multi-Otsu)")
        row = QHBoxLayout()
        row.addWidget(self.n_phases)
        row.addWidget(self.auto_button)
        self.form.addRow("Phases", row)
        self.histogram = HistogramCanvas()
        self.controls.addWidget(self.histogram)
        self.slider = QDoubleRangeSlider(Qt.Orientation.Horizontal)
        self.controls.addWidget(self.slider)
        self.threshold_label = QLabel("")
        self.controls.addWidget(self.threshold_label)
        self.phase_label = QLabel("")
        self.phase_label.setWordWrap(True)
        self.controls.addWidget(self.phase_label)
        self.summary = QLabel("")
        self.summary.setWordWrap(True)
        self.summary.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.curves = CurvesCanvas()
        # a series' summary has a block per state: scrolled, so the plots stay on screen
        self.summary_box = QScrollArea()
        self.summary_box.setWidget(self.summary)
        self.summary_box.setWidgetResizable(True)
        self.summary_box.setFrameShape(QFrame.Shape.NoFrame)
        self.summary_box.setMaximumHeight(190)
        self.summary_box.setMinimumHeight(120)  # about seven lines: both fields of a pair
        self.body.addWidget(self.summary_box)
        self.body.addWidget(self.curves)
        # a series: residual, p and error estimate against the load state (hidden for a pair)
        self.loads = QLineEdit()
        self.loads.setPlaceholderText("load per deformed state, e.g. 0.5, 1, 1.5 (empty: state)")
        self.loads.setToolTip(
            "The load of each evaluated state, in order, for the x axis of the series plot; "
            "empty: the states in order. Every state stays ticked."
        )
        self.series_label = QLabel("Load values")
        self.series_plot = SeriesCanvas()
        row = QHBoxLayout()
        row.addWidget(self.series_label)
        row.addWidget(self.loads)
        self.body.addLayout(row)
        self.body.addWidget(self.series_plot)
        for widget in (self.series_label, self.loads, self.series_plot):
            widget.setVisible(False)
        self.loads.editingFinished.connect(self.plot_series)

        self.evaluation = None
        self._volume_key = None
        # the phases layer appears once the user works with the thresholds (or evaluates), not
        # when the panel opens with automatic thresholds
        self.show_phases = False
        self._live = Debouncer(self.update_phases, 150, self)
        self._phases_worker = LatestWorker(self.phase_label.setText)
        self.slider.valueChanged.connect(self._thresholds_moved)
        self.slider.sliderPressed.connect(self._enable_phases)
        self.n_phases.valueChanged.connect(self.auto_thresholds)
        self.auto_button.clicked.connect(lambda checked=False: self.auto_thresholds())
        self.reference.currentIndexChanged.connect(self._reference_changed)
        follow_layers(self.viewer, self, self._layers_changed)
        self._layers_changed()
        self._reference_changed()

    # -- inputs -------------------------------------------------------------------------------
    def _layers_changed(self, event=None) -> None:
        checked = self.checked_fields()
        known = {self.fields.item(i).text() for i in range(self.fields.count())}
        self.fields.clear()
        fields = L.fields_in(self.viewer.layers)
        for name in fields:
            item = QListWidgetItem(name)
            item.setFlags(item.flags() | Qt.ItemFlag.ItemIsUserCheckable)
            keep = name in checked or name not in known
            item.setCheckState(Qt.CheckState.Checked if keep else Qt.CheckState.Unchecked)
            self.fields.addItem(item)
        inserted = getattr(event, "value", None)
        new_field = L.field_of(inserted) if inserted is not None else None
        first = next(iter(fields.values()), None)
        if new_field is not None or (event is None and first is not None):
            # default to the volumes the (newest) field was measured on
            source = new_field if new_field is not None else first
            self.reference.set_layer(source.metadata.get("reference_layer", ""))
            self.deformed.set_layer(source.metadata.get("deformed_layer", ""))
        pair_in_order(self.reference, self.deformed, event)

    def checked_fields(self) -> list[str]:
        return [
            self.fields.item(i).text()
            for i in range(self.fields.count())
            if self.fields.item(i).checkState() == Qt.CheckState.Checked
        ]

    def _volume(self, combo, name: str) -> np.ndarray:
        layer = combo.layer()
        if layer is None:
            raise ValueError(f"choose the {name} Image layer")
        volume = layer_volume(layer)
        if volume.ndim == 4 and name == "reference":  # a series: its first state
            volume = volume[0]
        if volume.ndim != 3:
            raise ValueError(f"'{layer.name}' is not a 3-D volume (shape {volume.shape})")
        return volume

    def _reference_changed(self, *args) -> None:
        layer = self.reference.layer()
        if layer is None or layer.ndim not in (3, 4):
            return
        key = (layer.name, id(layer.data))
        if key == self._volume_key:
            return
        self._volume_key = key
        volume = self._volume(self.reference, "reference")
        self.region.set_volume(volume.shape, volume)
        self.tiled.setChecked(suggest_tiled([volume]))
        counts, edges = model.gray_histogram(volume)
        self.histogram.set_histogram(counts, edges)
        self.slider.blockSignals(True)
        self.slider.setRange(float(edges[0]), float(edges[-1]))
        self.slider.blockSignals(False)
        self.auto_thresholds(show=False)

    # -- sessions -------------------------------------------------------------------------------
    def settings(self) -> dict:
        """Thresholds, number of phases, residual mode and a series' load values, JSON-friendly
        (for a session file)."""
        return {
            "region": self.region.settings(),
            "n_phases": self.n_phases.value(),
            "thresholds": self.thresholds(),
            "mode": self.mode.currentData(),
            "tiled": self.tiled.isChecked(),
            "max_memory": self.max_memory.text(),
            "evaluated": self.evaluated_fields(),
            "loads": self.loads.text(),
        }

    def evaluated_fields(self) -> list[str]:
        """Names of the fields of the evaluation on show ([] if none)."""
        evaluation = getattr(self, "evaluation", None)
        if evaluation is None:
            return []
        return [item.name for item in evaluation.fields]

    def evaluate_again(self, names) -> GeneratorWorker | None:
        """Evaluate the fields ``names`` again (a reopened session: the residual layers and the
        summary come back), with the panel's thresholds; the worker, or None (message)."""
        for i in range(self.fields.count()):
            item = self.fields.item(i)
            checked = item.text() in names
            item.setCheckState(Qt.CheckState.Checked if checked else Qt.CheckState.Unchecked)
        if not self.checked_fields():
            return None
        return self.run()

    def restore(self, settings: dict) -> None:
        index = self.mode.findData(settings.get("mode"))
        if index >= 0:
            self.mode.setCurrentIndex(index)
        self.max_memory.setText(str(settings.get("max_memory", "")))
        self.n_phases.blockSignals(True)  # no automatic thresholds over the saved ones
        self.n_phases.setValue(int(settings.get("n_phases", self.n_phases.value())))
        self.n_phases.blockSignals(False)
        self._reference_changed()
        if "region" in settings:
            self.region.restore(settings["region"])
        if settings.get("thresholds"):
            self.set_thresholds(settings["thresholds"], show=False)
        self.tiled.setChecked(bool(settings.get("tiled", self.tiled.isChecked())))
        self.loads.setText(str(settings.get("loads", "")))

    # -- thresholds and live phases -----------------------------------------------------------
    def thresholds(self) -> list[float]:
        return [float(v) for v in self.slider.value()]

    def set_thresholds(self, values, show: bool = True) -> None:
        """Move the slider handles (one per threshold, increasing); ``show`` the phases layer."""
        if show:
            self._enable_phases()
        self.slider.setValue(tuple(float(v) for v in values))

    def auto_thresholds(self, *args, show: bool = True) -> None:
        """Multi-Otsu thresholds for the chosen number of phases."""
        try:
            volume = self._volume(self.reference, "reference")
            values = model.automatic_thresholds(volume, self.n_phases.value())
        except ValueError as error:
            self.show_message(one_line(error), error=True)
            return
        self.set_thresholds(values, show=show)

    def _enable_phases(self) -> None:
        if not self.show_phases:
            self.show_phases = True
            self._live.trigger()

    def _thresholds_moved(self, *args) -> None:
        values = self.thresholds()
        self.threshold_label.setText("thresholds: " + ", ".join(f"{v:.1f}" for v in values))
        self.histogram.set_thresholds(values)
        self._live.trigger()

    def update_phases(self):
        """Recompute the phase labels and per-phase mean gray (debounced from the slider).

        The labels of the whole volume are computed in a worker (returned; None when the
        choice is bad); a newer threshold supersedes it, and the layer follows the latest.
        """
        try:
            layer = self.reference.layer()
            volume = self._volume(self.reference, "reference")
            thresholds = self.thresholds()
            model.check_thresholds(thresholds)
        except ValueError as error:
            self._phases_worker.cancel()
            self.phase_label.setText(one_line(error))
            return None
        placement = layer_placement(layer)
        return self._phases_worker.start(
            _phase_preview,
            volume,
            thresholds,
            on_returned=lambda preview: self._show_phases(preview, placement),
        )

    @property
    def phases_busy(self) -> bool:
        """True while the phase labels of the latest thresholds are computed."""
        return self._phases_worker.busy

    def _show_phases(self, preview, placement) -> None:
        self.phase_label.setText(preview.text())
        if not self.show_phases:
            return
        voxel_size, offset = placement
        existing = L.find_layer(self.viewer, "phases")
        if existing is not None:
            existing.data = preview.labels
            existing.scale, existing.translate = voxel_size, offset
        else:
            V.show_layers(
                self.viewer, [L.phase_layer(preview.labels, voxel_size=voxel_size, offset=offset)]
            )

    # -- running ------------------------------------------------------------------------------
    def prepare(self):
        self.show_phases = True
        self._live.trigger()
        self._live.flush()
        self._volume(self.reference, "reference")  # a 2-D image is refused first
        fields = L.fields_in(self.viewer.layers)
        chosen = {name: fields[name] for name in self.checked_fields() if name in fields}
        if not chosen:
            raise ValueError("no field to evaluate: run Correlate (and Self-correct) first")
        self._placement = (
            layer_placement(self.reference.layer()) if self.reference.layer() else None
        )
        self._chosen = dict(chosen)  # the layers' fields: the estimates go onto them
        groups = self._groups(chosen)
        reference = self._volume(self.reference, "reference")
        region = self.region.mask(reference.shape, reference, self._placement)
        if len(groups) > 1:  # a series: each state against its own pair of volumes
            tiled = self.tiled.isChecked()
            memory = check_tiled("pair", None, self.max_memory.text()) if tiled else None
            return model.run_groups(
                groups, self.thresholds(), self.mode.currentData(), memory, tiled, region
            )
        _, reference, deformed, chosen, known = groups[0]
        self._outputs, memory, self._writing = None, None, None
        self._release_temporary()  # folders of earlier runs no layer reads any more
        if self.tiled.isChecked():
            memory = check_tiled("pair", None, self.max_memory.text())
            self._outputs = self._temporary.new(chosen)
            self._writing = str(next(iter(self._outputs.values())).parent)
        run = model.run_evaluation(
            reference,
            deformed,
            chosen,
            self.thresholds(),
            self.mode.currentData(),
            outputs=self._outputs,
            max_memory=memory,
            background_fields=known,
            region=region,
        )
        return model.with_residual_layers(run, self._placement, self._outputs, TEMPORARY_KEY)

    def _panel_pair(self):
        reference = self._volume(self.reference, "reference")
        deformed = self._volume(self.deformed, "deformed")
        if self.reference.currentText() == self.deformed.currentText():
            raise ValueError("the reference and deformed volumes are the same layer")
        if reference.shape != deformed.shape:
            raise ValueError(
                f"reference {reference.shape} and deformed {deformed.shape} differ in shape"
            )
        return reference, deformed

    def _groups(self, chosen: dict) -> list:
        """Chosen fields grouped by the pair of volumes they were measured on.

        A field whose metadata names volumes open in the viewer — the states of a series
        (``"scan[2]"``) or separate layers — is evaluated on them; the others on the panel's
        reference and deformed volumes. Each entry is ``(label, reference, deformed, chosen,
        known)``, ``known`` every field of the viewer on that pair, ticked or not: the pair's
        gray-level map and ``r0`` are measured with the best of them.
        """
        panel = (self.reference.currentText(), self.deformed.currentText())

        def key_of(field):
            pair = (field.metadata.get("reference_layer"), field.metadata.get("deformed_layer"))
            if not all(pair) or pair == panel:
                return None
            try:
                volumes = tuple(named_volume(self.viewer.layers, n) for n in pair)
            except ValueError:  # not open any more: the panel's pair
                return None
            return pair if volumes[0].shape == volumes[1].shape else None

        every = L.fields_in(self.viewer.layers)
        keys = {name: key_of(field) for name, field in every.items()}
        groups: dict = {}
        for name, field in chosen.items():
            pair = keys.get(name, key_of(field))
            if pair is None:  # the panel's pair, named as the others are
                label = f"{panel[0]} → {panel[1]}"
                volumes = groups[None][1:3] if None in groups else self._panel_pair()
            else:
                volumes = tuple(named_volume(self.viewer.layers, n) for n in pair)
                if "[" in str(pair[1]):
                    label = f"state {pair[1].rsplit('[', 1)[1].rstrip(']')}"
                else:
                    label = f"{pair[0]} → {pair[1]}"
            entry = groups.setdefault(pair, [label, *volumes, {}, {}])
            entry[3][name] = field
        for pair, entry in groups.items():
            entry[4].update({n: f for n, f in every.items() if keys.get(n) == pair})
            entry[4].update(entry[3])
        return [tuple(entry) for entry in groups.values()]

    def _release_temporary(self, event=None) -> None:
        """Remove the out-of-core residual folders that no layer of the viewer reads (nor the
        run that is writing one, until its layers are shown)."""
        in_use = [self._writing]
        for layer in self.viewer.layers:
            entry = layer.metadata.get(L.MARKER)
            if isinstance(entry, dict) and entry.get(TEMPORARY_KEY):
                in_use.append(entry[TEMPORARY_KEY])
        self._temporary.release(in_use)

    def _attach_estimates(self, evaluations) -> None:
        """Leave each field's error estimate on the field its layers carry (View shows it,
        exports write it)."""
        chosen = getattr(self, "_chosen", {})
        for _, evaluation in evaluations:
            for item in evaluation.fields:
                if item.name in chosen and item.error_estimate is not None:
                    model.attach_estimate(chosen[item.name], item, evaluation)

    def on_result(self, evaluation) -> None:
        tuples = None
        if isinstance(evaluation, model.ShownEvaluation):  # its layers made in the worker
            evaluation, tuples = evaluation.evaluation, evaluation.layers
        self._attach_estimates(evaluation if isinstance(evaluation, list) else [("", evaluation)])
        if isinstance(evaluation, list):  # a series: one evaluation per state
            self.evaluations = evaluation
            self.evaluation = evaluation[-1][1]
            self.summary.setText(model.groups_text(evaluation))
            self.curves.plot(self.evaluation)
            self.show_message(f"Evaluation done for {len(evaluation)} states.")
            self.plot_series()
            return
        if tuples is None:
            outputs = getattr(self, "_outputs", None)
            tuples = model.residual_layers(evaluation, self._placement, outputs, TEMPORARY_KEY)
        self.evaluations = [("", evaluation)]
        self.evaluation = evaluation
        # replacing layers (one per step): their folder is still _writing
        yield from V.show_layers_steps(self.viewer, tuples)
        self._writing = None
        self._release_temporary()
        self.summary.setText(model.summary_text(evaluation))
        self.curves.plot(evaluation)
        self.show_message("Evaluation done.")
        for widget in (self.series_label, self.loads, self.series_plot):
            widget.setVisible(False)

    def plot_series(self) -> None:
        """The series plot of the evaluations on show (states ticked, at the typed loads)."""
        evaluations = getattr(self, "evaluations", [])
        if len(evaluations) < 2:
            return
        try:
            rows = model.series_rows(
                evaluations, self.loads.text(), self.deformed.currentText() or None
            )
        except ValueError as error:
            self.show_message(one_line(error), error=True)
            return
        for widget in (self.series_label, self.loads, self.series_plot):
            widget.setVisible(True)
        self.series_plot.plot(rows)


def _phase_preview(volume, thresholds):
    """Worker: :func:`.evaluate_model.phase_preview` (a generator, so a newer threshold can
    stop it before it starts). Touches no layer."""
    yield None
    return model.phase_preview(volume, thresholds)
