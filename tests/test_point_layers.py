"""Layer data of a field at scattered points, without a napari viewer."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct import point_layers as P


def test_point_layers_without_napari_viewer():
    """The builders: hollow points without a value, the status in its own colours."""
    from napari_dvc_correct.engine.fields.field import Status
    from napari_dvc_correct.engine.fields.scattered import ScatteredField

    field = ScatteredField(
        points=np.array([[10.0, 10.0, 10.0], [20.0, 20.0, 20.5]]),
        u=np.array([[0.5, 0.0, 0.0], [np.nan] * 3]),
        status=np.array([int(Status.CONVERGED), int(Status.DIVERGED)], np.uint8),
        gradient=np.zeros((2, 3, 3)),
        params={"subvolume": 15},
    )
    (points, kwargs, kind), (vectors, vkwargs, vkind) = P.points_layers(field, quantity="status")
    assert (kind, vkind) == ("points", "vectors")
    assert kwargs["face_color"] == ["white", "red"]
    assert kwargs["border_color"] == ["#202020", "red"]  # a red rim: no value here
    assert len(vectors) == 1  # no arrow where there is no displacement
    spacing = np.linalg.norm([10.0, 10.0, 10.5])  # the points' typical spacing
    assert vkwargs["length"] == pytest.approx(spacing / 0.5)  # exaggerated: it says how much
    assert np.isnan(kwargs["features"]["εeq"][1]) and kwargs["features"]["εeq"][0] == 0.0
