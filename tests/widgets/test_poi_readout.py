"""The Correlate panel's read-out of a clicked POI: the nearest node's values, by click or call."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from napari_dvc_correct.layers import field_of
from napari_dvc_correct.widgets import poi_readout


def test_the_box_invites_a_click(qtbot):
    box, label = poi_readout.poi_readout_box()
    qtbot.addWidget(box)
    assert box.title() == "Clicked POI" and "Click a point" in label.text()


def test_clicked_poi_shows_its_values(correlated, placement):
    viewer = correlated.viewer
    field = field_of(viewer.layers["|u| (uncorrected)"])
    scale, translate = placement(field)
    world = np.asarray(translate) + np.array([2, 1, 3]) * np.asarray(scale)
    values = correlated.inspect(world + 0.2)
    assert values["index"] == (2, 1, 3)
    np.testing.assert_allclose(values["u"], field.u[2, 1, 3])
    text = correlated.poi_label.text()
    assert "POI (2, 1, 3)" in text and "ZNCC" in text and "status" in text
    assert "provenance" in text and "iterations" in text
    assert correlated.inspect(np.asarray(translate) - 100 * np.asarray(scale)) is None
    # a click on the canvas goes through the viewer's mouse callback
    assert correlated._on_click in viewer.mouse_drag_callbacks
    corner = np.asarray(translate) + np.array([0, 0, 1]) * np.asarray(scale)
    click = SimpleNamespace(type="mouse_press", button=1, position=corner)
    correlated._on_click(viewer, click)
    assert "POI (0, 0, 1)" in correlated.poi_label.text()
