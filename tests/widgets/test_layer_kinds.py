"""Which layers the panels offer: the user's scans, regions and points, never our results."""

from __future__ import annotations

import numpy as np
from napari.layers import Image, Labels, Points, Shapes

from napari_dvc_correct.layers import MARKER
from napari_dvc_correct.widgets import _layer_kinds as K


def _ours(kind: str, **extra) -> dict:
    return {MARKER: {"kind": kind, "source": "uncorrected", **extra}}


def test_scans_are_the_user_s_gray_volumes():
    scan = Image(np.zeros((4, 4, 4)))
    sample = Image(np.zeros((4, 4, 4)), metadata={MARKER: {"role": "reference"}})
    result = Image(np.zeros((4, 4, 4)), metadata=_ours("quantity"))
    rgb = Image(np.zeros((4, 4, 3)), rgb=True)
    assert [K.is_scan(layer) for layer in (scan, sample, result, rgb)] == [True, True, False, False]
    assert not K.is_scan(Labels(np.zeros((4, 4, 4), np.uint8)))
    # the sample data says which scan it is; a result has no role
    assert [K.layer_role(layer) for layer in (scan, sample, result)] == [None, "reference", None]
    assert [K.made_by_us(layer) for layer in (scan, sample, result)] == [False, False, True]


def test_regions_and_points_are_the_user_s():
    assert K.is_mask(Labels(np.zeros((4, 4, 4), np.uint8)))
    assert K.is_mask(Shapes())
    assert not K.is_mask(Labels(np.zeros((4, 4, 4), np.uint8), metadata=_ours("phases")))
    assert not K.is_mask(Image(np.zeros((4, 4, 4))))
    assert K.is_user_points(Points(np.zeros((2, 3))))
    assert not K.is_user_points(Points(np.zeros((2, 3)), metadata=_ours("preview")))
    assert not K.is_user_points(Shapes())


def _field_layers(value: float, source: str) -> list:
    from napari.layers import Layer

    from napari_dvc_correct.engine.fields.field import DisplacementField
    from napari_dvc_correct.layers import field_layers

    field = DisplacementField.zeros((7, 7, 7), (4, 4, 4), (2, 3, 4))
    field.u[...] = value
    return [Layer.create(*t) for t in field_layers(field, source)]


def test_a_second_field_with_the_same_name_gets_its_own():
    """Two files with one stem (aldvc.npz, aldvc.mat): the second field becomes 'aldvc [1]', its
    arrows follow it, and a third becomes 'aldvc [2]' (user audit, item 1)."""
    from napari_dvc_correct.layers import plugin_metadata

    layers = _field_layers(0.5, "aldvc")
    assert [K.distinct_source(layers, x) for x in layers] == [None, None]  # the first keeps it
    for value, expected in ((1.0, "aldvc [1]"), (2.0, "aldvc [2]")):
        for layer in _field_layers(value, "aldvc"):
            layers.append(layer)
            K.distinct_source(layers, layer)
            assert plugin_metadata(layer)["source"] == expected
            assert layer.name.endswith(f"({expected})")
            # found again under this name where show_layers keyed it
            assert plugin_metadata(layer).get("name", layer.name) == layer.name
    sources = [plugin_metadata(x)["source"] for x in layers]
    assert sources == ["aldvc"] * 2 + ["aldvc [1]"] * 2 + ["aldvc [2]"] * 2


def test_a_new_result_replacing_the_old_keeps_its_name():
    """show_layers removes the old 'corrected' layer before it inserts the new one."""
    from napari_dvc_correct.layers import plugin_metadata

    layers = _field_layers(0.5, "corrected")
    new = _field_layers(1.0, "corrected")
    layers[0] = new[0]  # the quantity replaced, the old arrows not yet
    assert K.distinct_source(layers, new[0]) is None
    assert plugin_metadata(new[0])["source"] == "corrected"
