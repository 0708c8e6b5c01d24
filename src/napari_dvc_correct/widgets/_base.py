"""What every panel shares: running an engine generator in a thread worker, layer pickers, messages.

:class:`EngineWidget` is the one generic base: a panel builds its form, implements
:meth:`EngineWidget.prepare` (validate the choices and return the engine generator to run) and
:meth:`EngineWidget.on_result` (turn the result into layers). The base makes the worker unstarted,
connects ``yielded``/``returned``/``errored``/``aborted``/``finished`` to bound methods, then starts
it; it drives the progress bar, the Run/Cancel buttons and the message line. Layers are touched only
in the main-thread slots, so a cancelled run leaves every earlier layer as it was. An ``on_result``
that is a generator shows the result in steps, one turn of the event loop each
(:mod:`._showing`); :attr:`EngineWidget.shown` says when the result is on view.

Errors never show a traceback: bad choices (:class:`ValueError` from ``prepare`` or the engine) go
to the message line and to ``napari.utils.notifications.show_error``; unexpected errors are
logged with their traceback and shown as one line.
"""

from __future__ import annotations

import atexit
import logging
from collections.abc import Callable, Generator

from napari.utils.notifications import show_error
from qtpy.QtCore import Qt, Signal
from qtpy.QtWidgets import (
    QAbstractButton,
    QAbstractSpinBox,
    QCheckBox,
    QComboBox,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QProgressBar,
    QPushButton,
    QSizePolicy,
    QVBoxLayout,
    QWidget,
)
from superqt.utils import GeneratorWorker, WorkerBase, create_worker

from ..engine.progress import Progress
from . import _layer_kinds as K
from ._showing import Steps, finish_all

log = logging.getLogger(__name__)


class EngineError(Exception):
    """An error raised inside a worker (re-raised under this type so the worker reports it).

    superqt's worker treats a :class:`RuntimeError` from the generator as "the worker was
    deleted" and swallows it; wrapping keeps every failure visible.
    """


#: How long the end of the process waits for runs still going (their generators stop at the
#: next progress report: a batch of matches, about a second).
EXIT_WAIT_MS = 60_000


@atexit.register
def _stop_runs_at_exit() -> None:
    """A run still going when the process ends (its viewer closed by a script, not by quitting
    napari, which waits itself) is asked to stop and waited for: a worker thread that outlives
    the interpreter's teardown emits through deleted Qt objects and aborts the process."""
    try:
        WorkerBase.await_workers(msecs=EXIT_WAIT_MS)
    except RuntimeError:  # a run that did not stop in time: nothing more can be done
        log.warning("a DVC run did not stop within %d s of the process end", EXIT_WAIT_MS // 1000)


def _guarded(generator: Generator) -> Generator:
    try:
        return (yield from generator)
    except RuntimeError as error:
        raise EngineError(str(error)) from error


#: Modules napari imports the first time it shows a plugin layer (a Vectors layer's features
#: are a pandas table: ``import pandas`` on the main thread at the first field of a session,
#: 0.2 s of CPU, 0.3-0.4 s of frozen window at load 4-8); imported in the worker before the
#: result is shown.
SHOWING_IMPORTS = ("pandas",)


def _import_ahead() -> None:
    """Import :data:`SHOWING_IMPORTS` (worker): what napari would import on the main thread."""
    import importlib
    import sys

    for name in SHOWING_IMPORTS:
        if name not in sys.modules:
            try:
                importlib.import_module(name)
            except ImportError:  # napari imports it when it needs it (and says so)
                pass


def _shown_ahead(generator: Generator, quantity: str | None) -> Generator:
    """Run ``generator``; then, still in the worker, compute ``quantity`` (what the View panel
    shows) of the fields it returns, so showing them on the main thread computes no strain,
    and import what napari needs to show them (:data:`SHOWING_IMPORTS`)."""
    result = yield from generator
    _import_ahead()
    if quantity and quantity not in ("|u|", "residual"):
        from ..quantities import compute_ahead

        for field in _result_fields(result):
            try:
                compute_ahead(field, quantity)
            except ValueError:  # e.g. no uncertainty: the layer keeps its default
                pass
    return result


def _result_fields(result) -> list:
    """The grid fields in a panel's result (a correlation, a correction, a list of them), each
    once; a series' ``series`` (the fields as its 4-D layers show them: a correlated or a
    self-corrected series) brings its state 0."""
    from ..engine.fields.field import DisplacementField

    items = result if isinstance(result, list) else [result]
    found = []
    for item in items:
        entries = [getattr(item, "field", None), *(getattr(item, "fields", None) or [])]
        for entry in entries + list(getattr(item, "series", None) or []):
            field = entry[1] if isinstance(entry, tuple) and len(entry) == 2 else entry
            if isinstance(field, DisplacementField) and not any(f is field for f in found):
                found.append(field)
    return found


def _visible_quantity(viewer) -> str | None:
    from ..layers import plugin_metadata, quantity_layers

    shown = next((x for x in quantity_layers(viewer) if x.visible), None)
    return plugin_metadata(shown).get("quantity") if shown is not None else None


def follow_layers(viewer, widget, callback: Callable, moves: bool = False) -> None:
    """Call ``callback`` when layers are added or removed (and moved), until ``widget`` is deleted.

    The connections are undone when the Qt object goes away, so a closed dock never receives
    events for a deleted widget.

    The panels list fields by source name, so a new field named like one already there (two
    files with one stem) is renamed first (:func:`._layer_kinds.distinct_source`).
    """
    events = viewer.layers.events
    layers = viewer.layers

    def distinct(event=None) -> None:
        inserted = getattr(event, "value", None)
        if inserted is not None:
            K.distinct_source(layers, inserted)

    events.inserted.connect(distinct)  # before the panel's callback, which then sees the name
    emitters = (events.inserted, events.removed) + ((events.moved,) if moves else ())
    for emitter in emitters:
        emitter.connect(callback)

    def disconnect(*args, emitters=emitters, callback=callback, distinct=distinct) -> None:
        events.inserted.disconnect(distinct)
        for emitter in emitters:
            emitter.disconnect(callback)

    widget.destroyed.connect(disconnect)


def one_line(error: BaseException) -> str:
    """A short, single-line message for ``error``."""
    text = " ".join(str(error).split())
    return text if text else type(error).__name__


#: Characters a panel's combo box shows at least (longer entries are elided, the list shows
#: them whole): panels stay narrow so the canvas keeps most of the window.
COMBO_CHARACTERS = 10


def compact(panel: QWidget) -> None:
    """Let ``panel``'s combo boxes shrink to :data:`COMBO_CHARACTERS` instead of their longest
    entry (the width the dock asks for, next to napari's own docks, comes from them)."""
    for combo in panel.findChildren(QComboBox):
        combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        combo.setMinimumContentsLength(COMBO_CHARACTERS)
        # (Qt keeps the minimum size hint it computed from the entries before: set it)
        combo.setMinimumWidth(combo.sizeHint().width())


class LayerCombo(QComboBox):
    """A combo box of the viewer's layers that pass ``accept``, kept in sync with the viewer.

    The first entry is ``"(none)"`` when ``optional``. The current choice survives list changes
    while the layer still exists.
    """

    def __init__(self, viewer, accept: Callable, optional: bool = False, parent=None) -> None:
        super().__init__(parent)
        self._viewer = viewer
        self._accept = accept
        self._optional = optional
        self.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.setMinimumContentsLength(12)
        follow_layers(viewer, self, self.refresh, moves=True)
        self.refresh()

    def layers(self) -> list:
        return [layer for layer in self._viewer.layers if self._accept(layer)]

    def refresh(self, event=None) -> None:
        """Rebuild the list; signal a change only if the chosen layer is not the same any more."""
        current = self.currentText()
        self.blockSignals(True)
        self.clear()
        if self._optional:
            self.addItem("(none)")
        for layer in self.layers():
            self.addItem(layer.name)
            layer.events.name.connect(self._renamed)
        index = self.findText(current)
        if index >= 0:
            self.setCurrentIndex(index)
        self.blockSignals(False)
        if self.currentText() != current:
            self.currentIndexChanged.emit(self.currentIndex())

    def _renamed(self, event=None) -> None:
        self.refresh()

    def layer(self):
        """The chosen layer, or None."""
        name = self.currentText()
        if name and name in self._viewer.layers:
            layer = self._viewer.layers[name]
            return layer if self._accept(layer) else None
        return None

    def set_layer(self, layer_or_name) -> bool:
        """Choose a layer by object or name; False if it is not in the list."""
        name = getattr(layer_or_name, "name", layer_or_name)
        index = self.findText(str(name))
        if index >= 0:
            self.setCurrentIndex(index)
        return index >= 0


def pair_in_order(reference: LayerCombo, deformed: LayerCombo, event=None, ndim: int = 3) -> None:
    """Two different scans: the first opened is the reference, the next one the deformed.

    Only fills a choice that is empty, not ``ndim``-D, or the same layer in both boxes; a choice
    the user made between two different scans stays. With a layer-list ``event`` it acts only
    when a scan (a layer the reference box lists) was added.
    """
    # compared by name: napari hands plugins a proxy of the viewer, whose layers are new proxy
    # objects on every access (``is`` never holds between two of them)
    inserted = getattr(event, "value", None) if event is not None else None
    names = [x.name for x in reference.layers()]
    if event is not None and getattr(inserted, "name", None) not in names:
        return
    scans = [x.name for x in reference.layers() if x.ndim == ndim]
    ref = reference.layer()
    if ref is None or ref.ndim != ndim:
        if not scans:
            return
        ref = reference.layer() if reference.set_layer(scans[0]) else None
    ref_name = getattr(ref, "name", None)
    current = deformed.layer()
    if current is None or current.name == ref_name or current.ndim != ndim:
        after = scans[scans.index(ref_name) + 1 :] if ref_name in scans else scans
        others = [x for x in after + scans if x != ref_name]
        if others:
            deformed.set_layer(others[0])


class EngineWidget(QWidget):
    """Base of the panels that run engine work: form, Run/Cancel, progress bar, message line.

    Subclasses add their controls to :attr:`form` (a ``QFormLayout``) or :attr:`body` (the
    vertical layout, for anything else), and implement :meth:`prepare` and :meth:`on_result`.
    The panel is :attr:`running` from Run until its result is on view (or the run failed or was
    cancelled).
    """

    run_text = "Run"
    #: Emitted when a run's result is on view (after the last step of :meth:`on_result`).
    shown = Signal()

    def __init__(self, napari_viewer, parent=None) -> None:
        super().__init__(parent)
        self.viewer = napari_viewer
        self.worker: GeneratorWorker | None = None
        self._steps = Steps(self._step_failed)
        self._stage = ""
        self.body = QVBoxLayout(self)
        self.form = QFormLayout()
        self.body.addLayout(self.form)
        self.controls = QVBoxLayout()
        self.body.addLayout(self.controls)
        buttons = QHBoxLayout()
        self.run_button = QPushButton(self.run_text)
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        buttons.addWidget(self.run_button)
        buttons.addWidget(self.cancel_button)
        self.body.addLayout(buttons)
        self.progress_bar = QProgressBar()
        self.progress_bar.setRange(0, 1000)
        self.progress_bar.setValue(0)
        self.progress_bar.setFormat("%p%")
        self.body.addWidget(self.progress_bar)
        self.stage_label = QLabel("")
        self.body.addWidget(self.stage_label)
        self.message = QLabel("")
        self.message.setWordWrap(True)
        self.message.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.body.addWidget(self.message)
        for label in (self.stage_label, self.message):  # no stretching to fill the dock
            label.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Maximum)
        self.run_button.clicked.connect(lambda checked=False: self.run())
        self.cancel_button.clicked.connect(lambda checked=False: self.cancel())
        self.last_error: str | None = None
        if napari_viewer is not None:  # (None: a plain Qt host, no napari around)
            follow_layers(self.viewer, self, self._label_axes)
            self._label_axes()

    def add_out_of_core_row(self, tooltip: str) -> None:
        """The "out of core (tiled)" check box and its memory limit, as ``self.tiled`` and
        ``self.max_memory`` (the limit is editable only while the box is ticked)."""
        self.tiled = QCheckBox("out of core (tiled)")
        self.tiled.setToolTip(tooltip)
        self.max_memory = QLineEdit()
        self.max_memory.setPlaceholderText("memory: auto")
        self.max_memory.setToolTip("Peak memory of the tiled run, e.g. 4GB or 800MB")
        self.max_memory.setEnabled(False)
        self.tiled.toggled.connect(self.max_memory.setEnabled)
        row = QHBoxLayout()
        row.addWidget(self.tiled)
        row.addWidget(self.max_memory)
        self.form.addRow(row)

    def _label_axes(self, event=None) -> None:
        from ..viewer_layers import label_axes

        label_axes(self.viewer)

    def showEvent(self, event) -> None:
        """Once the subclass has added its controls, keep them at the top of a tall dock."""
        if not getattr(self, "_stretched", False):
            self.body.addStretch(1)
            self._stretched = True
            self.watch_inputs()
            compact(self)
        super().showEvent(event)

    def watch_inputs(self) -> None:
        """Clear an error message as soon as any input of the form changes."""
        for widget in self.findChildren((QComboBox, QAbstractSpinBox, QAbstractButton, QLineEdit)):
            if widget in (self.run_button, self.cancel_button):
                continue
            for name in ("currentIndexChanged", "valueChanged", "toggled", "textEdited"):
                signal = getattr(widget, name, None)
                if signal is not None and not getattr(widget, "_dvc_watched", False):
                    signal.connect(self._input_changed)
            widget._dvc_watched = True

    def _input_changed(self, *args) -> None:
        if self.last_error is not None and not self.running:
            self.clear_message()

    # -- what subclasses implement ------------------------------------------------------------
    def prepare(self) -> Generator:
        """Validate the choices and return the engine generator to run (raise ValueError)."""
        raise NotImplementedError

    def on_result(self, result) -> Generator | None:
        """Turn the generator's return value into layers (main thread). May be a generator:
        each ``yield`` lets the event loop turn (one layer per step)."""
        raise NotImplementedError

    def on_partial(self, value) -> None:
        """Handle a yielded value that is not a :class:`Progress` (main thread)."""

    # -- messages -----------------------------------------------------------------------------
    def show_message(self, text: str, error: bool = False) -> None:
        """Show ``text`` in the dock's message line; errors (red) also as a notification."""
        self.message.setStyleSheet("color: #e05050;" if error else "")
        self.message.setText(text)
        if error:
            self.last_error = text
            show_error(text)

    def clear_message(self) -> None:
        self.message.setStyleSheet("")
        self.message.setText("")
        self.last_error = None

    # -- running ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """True from Run until the result is on view (the worker, then the showing steps)."""
        return self.worker is not None or self._steps.pending

    def run(self, start: bool = True) -> GeneratorWorker | None:
        """Validate the choices and run the engine generator in a worker.

        Returns the worker, or None when a choice is bad (the message line says why). With
        ``start=False`` the worker is returned wired but unstarted, so a caller can connect to
        its signals first (``worker.start()`` then runs it).
        """
        finish_all()  # the last results whole in the layers this run reads
        if self.running:
            return None
        self.clear_message()
        try:
            generator = self.prepare()
        except ValueError as error:
            self.show_message(one_line(error), error=True)
            return None
        except Exception as error:  # a bug: log the traceback, show one line
            log.error("preparing the run failed", exc_info=True)
            self.show_message(f"{type(error).__name__}: {one_line(error)}", error=True)
            return None
        return self.start(generator, start=start)

    def start(self, generator: Generator, start: bool = True) -> GeneratorWorker:
        """Run ``generator`` in a thread worker wired to this panel's slots."""
        # errored handled here: without it superqt re-raises the error on the main thread (a
        # traceback notification in napari, an abort in a plain Qt host)
        quantity = _visible_quantity(self.viewer) if self.viewer is not None else None
        generator = _shown_ahead(generator, quantity)
        worker = create_worker(
            _guarded, generator, _start_thread=False, _connect={"errored": self._on_errored}
        )
        worker.yielded.connect(self._on_yielded)
        worker.returned.connect(self._on_returned)
        worker.aborted.connect(self._on_aborted)
        worker.finished.connect(self._on_finished)
        self.destroyed.connect(worker.quit)  # a closed panel's run stops at its next report
        self.worker = worker
        self.run_button.setEnabled(False)
        self.cancel_button.setEnabled(True)
        self.progress_bar.setValue(0)
        self.stage_label.setText("starting…")
        if start:
            worker.start()
        return worker

    def cancel(self) -> None:
        """Ask the worker to stop at its next progress report; earlier layers stay."""
        if self.worker is not None:
            self.stage_label.setText("cancelling…")
            self.worker.quit()

    def _on_yielded(self, value) -> None:
        if isinstance(value, Progress):
            self.progress_bar.setValue(int(round(1000 * value.fraction)))
            text = value.stage if not value.message else f"{value.stage}: {value.message}"
            self.stage_label.setText(text)
        else:
            self.on_partial(value)

    def _on_returned(self, result) -> None:
        self.progress_bar.setValue(1000)
        try:
            steps = self.on_result(result)
        except Exception as error:
            self._step_failed(error)
            return
        if isinstance(steps, Generator):
            self._stage = self.stage_label.text()
            self.stage_label.setText("showing the result…")
            self._steps.start(steps, self, self._on_shown)
        else:
            self._on_shown()

    def _on_shown(self) -> None:
        try:
            if self.stage_label.text() == "showing the result…":
                self.stage_label.setText(self._stage)
            self._idle()
            self.shown.emit()
        except RuntimeError as error:  # the panel was closed while its result was shown
            if "deleted" not in str(error):
                raise

    def _step_failed(self, error: Exception) -> None:
        try:
            if isinstance(error, ValueError):
                self.show_message(one_line(error), error=True)
            else:  # a bug: log it, show one line, never abort the Qt host
                log.error(
                    "showing the result failed", exc_info=(type(error), error, error.__traceback__)
                )
                self.show_message(f"{type(error).__name__}: {one_line(error)}", error=True)
            self._idle()
        except RuntimeError as closed:  # the panel was closed while its result was shown
            if "deleted" not in str(closed):
                raise

    def _on_errored(self, error: Exception) -> None:
        if not isinstance(error, ValueError):
            log.error(
                "%s's run failed",
                type(self).__name__.removesuffix("Widget"),
                exc_info=(type(error), error, error.__traceback__),
            )
        self.stage_label.setText("failed")
        self.show_message(one_line(error), error=True)

    def _on_aborted(self) -> None:
        self.progress_bar.setValue(0)
        self.stage_label.setText("cancelled")
        self.show_message("Cancelled: the layers from earlier runs are unchanged.")

    def _on_finished(self) -> None:
        self.worker = None
        self.cancel_button.setEnabled(False)  # a returned result is shown whole
        self._idle()

    def _idle(self) -> None:
        """Run enabled again once the worker is done and the result on view."""
        if not self.running:
            self.run_button.setEnabled(True)
            self.cancel_button.setEnabled(False)
