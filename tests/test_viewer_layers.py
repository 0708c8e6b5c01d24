"""Layers put into a viewer: ours replaced or updated in place, the user's left alone."""

from __future__ import annotations

import numpy as np
import pytest
from napari.components import ViewerModel

from napari_dvc_correct import layers as L
from napari_dvc_correct import viewer_layers as V
from napari_dvc_correct.engine.fields.field import DisplacementField, Status


@pytest.fixture
def field() -> DisplacementField:
    shape = (4, 5, 6)
    rng = np.random.default_rng(3)
    u = rng.normal(0, 2.0, (*shape, 3))
    status = np.zeros(shape, np.uint8)
    status[1, 2, 3] = Status.DIVERGED
    return DisplacementField(origin=(5.0, 6.0, 7.0), step=(4.0, 3.0, 2.0), u=u, status=status)


def test_field_layers_carry_the_field_and_show_layers_replaces_only_its_own(field):
    viewer = ViewerModel()
    viewer.add_image(np.zeros((3, 3, 3)), name="|u| (uncorrected)")  # the user's own layer
    first = V.show_layers(viewer, L.field_layers(field, "uncorrected"))
    assert len(first) == 2  # one quantity layer and the arrows
    assert L.fields_in(viewer.layers) == {"uncorrected": field}
    # the user's layer stays; ours got napari's numbered name
    assert L.plugin_metadata(viewer.layers["|u| (uncorrected)"]) is None
    assert viewer.layers["|u| (uncorrected) [1]"] in first
    count = len(viewer.layers)
    other = field.copy()
    second = V.show_layers(viewer, L.field_layers(other, "uncorrected"))
    assert len(viewer.layers) == count
    assert all(layer in viewer.layers for layer in second)
    # updated in place (no new canvas visual, no garbage-collection pause), with the new field
    assert all(new is old for new, old in zip(second, first))
    assert L.fields_in(viewer.layers)["uncorrected"] is other
    assert L.plugin_metadata(viewer.layers["|u| (uncorrected)"]) is None  # the user's, as it was


def test_show_layers_keeps_layers_that_share_a_metadata_dict():
    viewer = ViewerModel()
    meta = {L.MARKER: {"kind": "preview", "source": "preview"}}
    points = (np.zeros((2, 3)), {"name": "a", "metadata": meta}, "points")
    image = (np.zeros((2, 2, 2)), {"name": "b", "metadata": meta}, "image")
    V.show_layers(viewer, [points])
    V.show_layers(viewer, [image])
    assert [layer.name for layer in viewer.layers] == ["a", "b"]
    assert L.find_layer(viewer, "a").name == "a" and L.find_layer(viewer, "b").name == "b"


def test_a_series_field_comes_on_view_at_its_last_state(field):
    """State 0 of a series does not move: a series shown at state 0 showed an empty field."""
    from napari_dvc_correct.layers import series_fields

    viewer = ViewerModel()
    viewer.add_image(np.zeros((3, 20, 20, 20)), name="scans")  # the series' 4-D scans
    viewer.dims.set_current_step(0, 0)
    states = [field, field.copy()]
    V.show_field(viewer, L.field_layers(series_fields(states), "series (total)"))
    assert viewer.dims.current_step[0] == 2  # states 0, 1, 2: the last
    viewer.dims.set_current_step(0, 1)  # the user's choice stays when a field comes again
    V.show_field(viewer, L.field_layers(series_fields(states), "series (total)"))
    assert viewer.dims.current_step[0] == 1


def test_a_field_comes_one_layer_per_step_the_other_fields_hidden_first(field):
    """Each step does one thing napari makes expensive on the main thread (a layer's visual,
    controls and colorbar; one turn of the event loop each); the end state is that of showing
    the field at once."""
    viewer = ViewerModel()
    V.show_field(viewer, L.field_layers(field, "uncorrected"))
    before = list(viewer.layers)
    steps = V.show_field_steps(viewer, L.field_layers(field.copy(), "corrected"))
    next(steps)  # the other field hidden, nothing added yet
    assert len(viewer.layers) == 2 and not any(x.visible for x in before)
    next(steps)  # the quantity layer is in, on view; its colorbar not yet
    quantity = viewer.layers[-1]
    assert L.plugin_metadata(quantity)["kind"] == "quantity" and quantity.visible
    assert not quantity.colorbar.visible
    next(steps)  # its colorbar; the arrows are not in yet
    assert quantity.colorbar.visible and len(viewer.layers) == 3
    added = V.finish(steps)
    assert added == list(viewer.layers)[2:] and added[0] is quantity
    assert [L.plugin_metadata(x)["kind"] for x in viewer.layers] == ["quantity", "vectors"] * 2
    assert [x.visible for x in viewer.layers] == [False, False, True, True]
    assert not any(x.colorbar.visible for x in before if hasattr(x, "colorbar"))
    assert viewer.layers.selection.active is added[1]
    assert V.text_overlay(viewer).text == L.colorbar_title(quantity)
    # again: updated in place (the colorbar already on), the same layers
    steps = V.show_field_steps(viewer, L.field_layers(field.copy(), "corrected"))
    assert sum(1 for _ in steps) == 2  # hide the others; the quantity; the arrows
    assert list(viewer.layers)[2:] == added
