"""Layer builders: placement in world units, vectors, names, metadata, replacing old layers."""

from __future__ import annotations

import numpy as np
import pytest
from napari.components import ViewerModel
from napari.layers import Layer

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


def test_grid_layers_sit_on_the_nodes_in_world_units(field):
    data, kwargs, kind = L.quantity_layer(
        field, "uncorrected", "|u|", voxel_size=(2, 1, 0.5), offset=(10, 0, -1)
    )
    layer = Layer.create(data, kwargs, kind)
    world = layer.data_to_world((1, 2, 3))
    node = np.asarray(field.origin) + np.array([1, 2, 3]) * np.asarray(field.step)
    np.testing.assert_allclose(world, np.array([10, 0, -1]) + node * [2, 1, 0.5])
    assert kwargs["name"] == "|u| (uncorrected)"
    assert np.isnan(data[1, 2, 3]) and np.isfinite(data[0, 0, 0])


def test_vectors_start_on_nodes_and_have_their_true_length(field):
    data, kwargs, kind = L.vectors_layer(
        field, "corrected", voxel_size=(2, 1, 0.5), exaggerate=False
    )
    layer = Layer.create(data, kwargs, kind)
    assert kind == "vectors" and layer.name == "displacement (corrected)"
    assert len(data) == field.n_points - 1  # the diverged node is left out
    for start, vector in data[:5]:
        i, j, k = start.astype(int)
        tip = np.asarray(layer.data_to_world(start + vector))
        base = np.asarray(layer.data_to_world(start))
        np.testing.assert_allclose(tip - base, field.u[i, j, k] * [2, 1, 0.5])
    np.testing.assert_allclose(
        layer.features["magnitude"], np.linalg.norm(data[:, 1] * field.step, axis=1)
    )


def test_vectors_are_subsampled(field):
    data, kwargs, _ = L.vectors_layer(field, "x", max_vectors=20)
    assert len(data) <= 20
    assert kwargs["metadata"]["dvc_correct"]["stride"] == L.vector_stride(field.shape, 20) > 1


def test_show_quantity_switches_in_place_and_series_are_4d(field):
    viewer = ViewerModel()
    (layer, _) = V.show_layers(viewer, L.field_layers(field, "uncorrected"))
    L.show_quantity(layer, "status")
    assert layer.name == "status (uncorrected)" and layer.data[1, 2, 3] == Status.DIVERGED
    assert L.find_layer(viewer, L.field_key("uncorrected")) is layer
    with pytest.raises(ValueError, match="run Evaluate first"):
        L.show_quantity(layer, "residual")
    L.show_quantity(layer, "residual", residual=np.ones((20, 20, 20)))
    assert layer.scale[0] == 1.0 and layer.data.shape == (20, 20, 20)
    series = L.series_fields([field, field.copy()])
    tuples = L.field_layers(series, "series (total)")
    (image, image_kwargs, _), (arrows, arrow_kwargs, _) = tuples
    assert image.shape == (3, *field.shape) and image_kwargs["scale"][0] == 1.0
    assert arrows.shape[2] == 4 and set(arrows[:, 0, 0]) == {0.0, 1.0, 2.0}
    np.testing.assert_array_equal(image[0][field.valid], 0.0)  # state 0 does not move
    viewer = ViewerModel()
    V.show_layers(viewer, tuples)
    assert list(L.fields_in(viewer.layers)) == ["state 1 (total)", "state 2 (total)"]
    assert viewer.dims.axis_labels == ("state", "z", "y", "x")


def test_dense_layers_use_the_voxel_size(field):
    residual = np.ones((8, 8, 8), np.float32)
    data, kwargs, kind = L.residual_layer(
        residual, "corrected", voxel_size=(2, 2, 2), offset=(1, 1, 1)
    )
    assert kwargs["scale"] == (2.0, 2.0, 2.0) and kwargs["translate"] == (1.0, 1.0, 1.0)
    assert kwargs["name"] == "residual volume (corrected)" and kind == "image"
    labels, kwargs, kind = L.phase_layer(np.zeros((8, 8, 8), np.uint8), voxel_size=(2, 2, 2))
    assert kind == "labels" and kwargs["name"] == "phases"


def test_the_error_estimate_s_caption_gives_its_resolution_and_bounds(field):
    """After Evaluate the field offers its error estimate and the residual's resolution; the
    caption of either says the resolution, the share of nodes below it and how many are likely
    and possibly above 0.5 voxel."""
    from napari_dvc_correct.engine.evaluation.error_estimate import attach_estimate

    estimate = np.full(field.shape, 0.05)  # 120 nodes, resolution 0.1 (σ 0.058)
    estimate[0] = 0.48  # 30 nodes possibly > 0.5, not likely
    estimate[1, 0] = 0.7  # 6 nodes likely
    attach_estimate(field, estimate, np.full(field.shape, 0.1))
    assert {"error estimate", "error resolution"} <= set(L.available_quantities(field))
    layer = Layer.create(*L.quantity_layer(field, "f", "error resolution"))
    np.testing.assert_allclose(layer.data[field.valid], 0.1, rtol=1e-6)
    L.show_quantity(layer, "error estimate")
    text = L.caption(layer)
    assert text.startswith("error estimate [vx]") and "a bound, not a rank" in text
    assert "Resolution 0.100 voxel (median); 70 % of nodes below it" in text
    assert "5 % of nodes likely > 0.5 voxel (P ≥ ½), 30 % possibly (P ≥ 16 %" in text
