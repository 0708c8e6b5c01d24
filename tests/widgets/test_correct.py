"""The Self-correct dock end to end: corrected layers, the per-pass table, cancel, bad choices."""

from __future__ import annotations

import numpy as np

from napari_dvc_correct._sample_data import true_field
from napari_dvc_correct.engine.fields.field import Provenance
from napari_dvc_correct.layers import field_of
from napari_dvc_correct.widgets.correct import CorrectWidget


def _dock(viewer):
    widget = CorrectWidget(viewer)
    viewer.window.add_dock_widget(widget)
    return widget


def test_self_correct_adds_corrected_layers_and_reports_passes(
    correlated, run_panel, pair48, placement
):
    viewer = correlated.viewer
    widget = _dock(viewer)
    assert widget.field.currentText() == "uncorrected"
    assert widget.reference.currentText() == "reference"
    assert widget.deformed.currentText() == "deformed"
    widget.max_passes.setValue(2)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    for quantity in ("displacement", "|u|"):
        assert f"{quantity} (corrected)" in viewer.layers
    corrected = field_of(viewer.layers["|u| (corrected)"])
    uncorrected = field_of(viewer.layers["|u| (uncorrected)"])
    assert corrected is not uncorrected
    scale, translate = placement(corrected)
    for name in ("|u| (corrected)", "displacement (corrected)"):
        np.testing.assert_allclose(viewer.layers[name].scale, scale)
        np.testing.assert_allclose(viewer.layers[name].translate, translate)
    # the table lists the cleaned input and at least one pass, residual never rises
    columns = widget.table.columnCount()
    headers = [widget.table.horizontalHeaderItem(c).text() for c in range(columns)]
    assert headers[:3] == ["pass", "order", "subvolume"]
    rows = [
        [widget.table.item(r, c).text() for c in range(columns)]
        for r in range(widget.table.rowCount())
    ]
    assert rows[0][0] == "0 (input)" and len(rows) >= 2
    passes = corrected.metadata["correction_passes"]
    # every pass says the order and subvolume its correcting matches used, and the message why
    for row, record in zip(rows[1:], passes[1:]):
        assert row[1] == {1: "first", 2: "second"}[record["order"]]
        assert row[2] == f"{record['subvolume']}³"
    assert "Correcting matches" in widget.message.text()
    assert corrected.metadata["correction"]["pass_method"] in widget.message.text()
    applied = [p["mean_gray_residual"] for p in passes if p["accepted"]]
    assert applied == sorted(applied, reverse=True)
    assert "→" in widget.message.text()
    reason = corrected.metadata["correction"]["stop_reason"]
    assert reason and f"Stopped: {reason}." in widget.message.text()  # why the loop ended
    # against the known shear band, the correction does not make the field worse
    truth = true_field(pair48[2], corrected.origin, corrected.step, corrected.shape)
    before = np.linalg.norm(uncorrected.u - truth.u, axis=-1)[uncorrected.valid].mean()
    after = np.linalg.norm(corrected.u - truth.u, axis=-1)[uncorrected.valid].mean()
    assert after <= before + 0.02
    if corrected.metadata["correction"]["passes_applied"]:
        assert (corrected.provenance == Provenance.CORRECTED).any()
    # the corrected field is not offered for correcting again
    assert widget.field.findText("corrected") < 0


def test_cancel_keeps_the_uncorrected_layers(correlated, qtbot):
    viewer = correlated.viewer
    before = [layer.name for layer in viewer.layers]
    widget = _dock(viewer)
    worker = widget.run(start=False)
    worker.yielded.connect(lambda value: widget.cancel())
    with qtbot.waitSignal(worker.finished, timeout=120_000):
        worker.start()
    assert [layer.name for layer in viewer.layers] == before
    assert "Cancelled" in widget.message.text()


def test_without_a_field_a_message(viewer_pair):
    widget = _dock(viewer_pair)
    assert widget.run() is None
    assert "run Correlate first" in widget.message.text()


def test_same_layer_twice_a_message(correlated):
    widget = _dock(correlated.viewer)
    widget.deformed.set_layer("reference")
    assert widget.run() is None
    assert "same layer" in widget.message.text()


def test_a_region_limits_the_correction(correlated, run_panel, small):
    """Outside the region no correction is measured: those nodes are never corrected (an update
    read more than a step beyond the measured ones is refused: the node keeps its value; a nearer
    one is interpolated, provenance replaced); inside it is measured (provenance corrected)."""
    from napari_dvc_correct.engine.fields.field import Provenance as P

    viewer = correlated.viewer
    widget = _dock(viewer)
    widget.region.set_kind("box")
    widget.region.x_from.setValue(0)
    widget.region.x_to.setValue(26)  # the left half only
    widget.max_passes.setValue(1)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    corrected = field_of(viewer.layers["|u| (corrected)"])
    x = corrected.axis_coordinates()[2]
    outside = x > 25.5 + small.subvolume / 2
    assert outside.any()
    kept = corrected.provenance[:, :, outside] == P.MEASURED
    assert np.all(kept | (corrected.provenance[:, :, outside] == P.REPLACED))
    uncorrected = field_of(viewer.layers["|u| (uncorrected)"])
    np.testing.assert_array_equal(
        corrected.u[:, :, outside][kept], uncorrected.u[:, :, outside][kept]
    )
    inside = x < 25.5 - small.subvolume / 2
    assert np.any(corrected.provenance[:, :, inside] == P.CORRECTED)
    assert not np.any(corrected.provenance[:, :, inside] == P.REPLACED)


def test_the_panel_says_when_the_correction_changed_the_method(
    make_napari_viewer, changed_method_field
):
    """The paper promises the same DVC parameters: where the correcting matches used another
    order or subvolume than the user's, the table shows them and the message says why."""
    from napari_dvc_correct.viewer_layers import finish
    from napari_dvc_correct.widgets.correct_model import CorrectionResult

    field, method = changed_method_field
    widget = _dock(make_napari_viewer())
    finish(widget.on_result(CorrectionResult(field, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))))
    rows = [
        [widget.table.item(r, c).text() for c in range(widget.table.columnCount())]
        for r in range(widget.table.rowCount())
    ]
    assert [row[:3] for row in rows] == [
        ["0 (input)", "—", "—"],
        ["1", "second", "15³"],
        ["2", "second", "15³"],
    ]
    message = widget.message.text()
    assert "changed from your first order, 21³" in message
    assert f"passes 1–2: {method}" in message
    # the gray-level map the residuals were judged with, and the flags by kind
    assert "G ≈ 2.3·F − 23 (local, 32-voxel cells)" in message
    assert "3 nodes whose residual no small error explains" in message
    assert "11 along a discontinuity" in message and "6 nodes near it kept" in message


def _opened_field(viewer, value: float, stem: str) -> None:
    """What napari does with our reader's tuples: Layer.create and add, no show_layers."""
    from napari.layers import Layer

    from napari_dvc_correct.engine.fields.field import DisplacementField
    from napari_dvc_correct.layers import field_layers

    field = DisplacementField.zeros((7, 7, 7), (4, 4, 4), (2, 3, 4))
    field.u[...] = value
    for data, kwargs, layer_type in field_layers(field, stem):
        viewer.add_layer(Layer.create(data, kwargs, layer_type))


def test_two_fields_with_one_name_can_both_be_chosen(viewer_pair):
    """aldvc.npz then aldvc.mat: both in Self-correct's and Evaluate's lists (user audit, 1)."""
    from napari_dvc_correct.widgets.evaluate import EvaluateWidget

    widget = _dock(viewer_pair)
    evaluate = EvaluateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(evaluate)
    _opened_field(viewer_pair, 0.5, "aldvc")
    _opened_field(viewer_pair, 1.0, "aldvc")
    assert [widget.field.itemText(i) for i in range(widget.field.count())] == [
        "aldvc",
        "aldvc [1]",
    ]
    assert [evaluate.fields.item(i).text() for i in range(evaluate.fields.count())] == [
        "aldvc",
        "aldvc [1]",
    ]
    chosen = widget.choices()
    assert float(chosen["aldvc"].u[0, 0, 0, 0]) == 0.5
    assert float(chosen["aldvc [1]"].u[0, 0, 0, 0]) == 1.0


def test_correcting_an_opened_field_keeps_its_name_and_the_other_s_layers(correlated, run_panel):
    """A field from a file ('aldvc') corrects into '(aldvc, corrected)' layers; correcting the
    panel's own field afterwards leaves them alone (user audit, item 2)."""
    from napari.layers import Layer

    from napari_dvc_correct.layers import field_layers, plugin_metadata

    viewer = correlated.viewer
    opened = field_of(viewer.layers["|u| (uncorrected)"]).copy()  # as if saved and opened
    for data, kwargs, layer_type in field_layers(opened, "aldvc"):
        viewer.add_layer(Layer.create(data, kwargs, layer_type))
    widget = _dock(viewer)
    widget.max_passes.setValue(1)
    widget.field.setCurrentText("aldvc")
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    assert "|u| (aldvc, corrected)" in viewer.layers
    assert "|u| (corrected)" not in viewer.layers
    from_file = field_of(viewer.layers["|u| (aldvc, corrected)"])
    widget.field.setCurrentText("uncorrected")
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    sources = [(plugin_metadata(x) or {}).get("source") for x in viewer.layers]
    assert sources.count("aldvc, corrected") == 2 and sources.count("corrected") == 2
    assert field_of(viewer.layers["|u| (aldvc, corrected)"]) is from_file
    assert [widget.field.itemText(i) for i in range(widget.field.count())] == [
        "uncorrected",
        "aldvc",
    ]


def test_a_new_field_under_the_same_name_brings_its_own_pair(make_napari_viewer):
    # Correlate on (a, b), then again on (a, c): the new 'uncorrected' field replaced the first
    # under the same name, but the panel kept b as the deformed scan and corrected the a → c
    # field against b without a word
    from napari_dvc_correct.engine.fields.field import DisplacementField
    from napari_dvc_correct.layers import field_layers
    from napari_dvc_correct.viewer_layers import show_field

    viewer = make_napari_viewer()
    for name in ("a", "b", "c"):
        viewer.add_image(np.zeros((16, 16, 16), np.float32), name=name)
    widget = _dock(viewer)

    def correlated(deformed):
        field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (2, 2, 2))
        field.metadata.update(reference_layer="a", deformed_layer=deformed)
        show_field(viewer, field_layers(field, "uncorrected"))

    correlated("b")
    assert (widget.reference.currentText(), widget.deformed.currentText()) == ("a", "b")
    correlated("c")  # its layers updated in place: no layer-list event
    from qtpy.QtGui import QShowEvent

    widget.showEvent(QShowEvent())  # the panel brought to the front shows the new field's pair
    assert (widget.reference.currentText(), widget.deformed.currentText()) == ("a", "c")
    widget.deformed.set_layer("b")
    correlated("c")
    assert widget.run(start=False) is not None, widget.message.text()
    assert (widget.reference.currentText(), widget.deformed.currentText()) == ("a", "c")
    widget.deformed.set_layer("b")  # a choice made for this very field stays
    widget.worker = None
    assert widget.run(start=False) is not None
    assert widget.deformed.currentText() == "b"
