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
