"""Points of interest from a napari Points layer, without Qt: world to voxels, and the checks."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.widgets import points_model


def test_points_in_voxels_undoes_both_layers_placement():
    voxels = np.array([[10.0, 12.0, 20.0], [30.5, 8.0, 15.25]])
    image = _layer(scale=(2.0, 1.5, 1.5), translate=(10.0, -4.0, 0.0))
    world = voxels * np.array(image.scale) + np.array(image.translate)
    # points added with viewer.add_points: data in world coordinates
    np.testing.assert_allclose(points_model.points_in_voxels(_layer(world), image), voxels)
    # a Points layer with its own scale and translate (and a leading state axis)
    own_scale, own_translate = np.array([0.5, 3.0, 1.0]), np.array([1.0, 2.0, -3.0])
    data = (world - own_translate) / own_scale
    data4 = np.concatenate([np.full((2, 1), 2.0), data], axis=1)
    points = _layer(data4, scale=(1.0, *own_scale), translate=(0.0, *own_translate))
    np.testing.assert_allclose(points_model.points_in_voxels(points, image), voxels)
    with pytest.raises(ValueError, match="2-D points"):
        points_model.points_in_voxels(_layer(np.zeros((3, 2))), image)
    with pytest.raises(ValueError, match="holds no point"):
        points_model.points_in_voxels(_layer(np.zeros((0, 3))), image)


def test_check_points_says_which_points_do_not_fit_and_why():
    shape, subvolume = (40, 50, 60), 15  # M = 7: centres 7..32, 7..42, 7..52
    points_model.check_points(np.array([[7.0, 7.0, 7.0], [32.4, 42.0, 52.0]]), shape, subvolume)
    with pytest.raises(ValueError) as outside:
        points_model.check_points(
            np.array([[20.0, 20.0, 20.0], [20.0, 20.0, 60.0]]), shape, 15, "p"
        )
    text = str(outside.value)
    assert "1 outside the volume (40, 50, 60)" in text and "#1 at (z, y, x)" in text
    assert "z 7–32, y 7–42, x 7–52" in text
    with pytest.raises(ValueError, match="1 closer than 7 voxels to its border"):
        points_model.check_points(np.array([[6.4, 20.0, 20.0], [20.0, 20.0, 20.0]]), shape, 15)
    with pytest.raises(ValueError, match="non-finite"):
        points_model.check_points(np.array([[np.nan, 1.0, 1.0]]), shape, 15)


def test_job_points_refuses_a_series_and_a_missing_layer():
    params = CorrelationParams(subvolume=15, step=8)
    image = _layer()
    with pytest.raises(ValueError, match="work on a pair"):
        points_model.job_points(_layer(np.full((1, 3), 20.0)), image, "total", (48,) * 3, params)
    with pytest.raises(ValueError, match="choose the Points layer"):
        points_model.job_points(None, image, "pair", (48,) * 3, params)
    points = points_model.job_points(
        _layer(np.full((1, 3), 20.0)), image, "pair", (48,) * 3, params
    )
    np.testing.assert_array_equal(points, [[20.0, 20.0, 20.0]])


# -- points of interest from a Points layer ---------------------------------------------------
def _layer(data=None, scale=(1.0, 1.0, 1.0), translate=(0.0, 0.0, 0.0), name="pois"):
    from types import SimpleNamespace

    return SimpleNamespace(data=data, scale=scale, translate=translate, name=name)
