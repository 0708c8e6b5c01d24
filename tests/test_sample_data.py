"""Sample data: deterministic, the right shapes, and the stored answer really is the deformation."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from napari_dvc_correct._sample_data import (
    NOISE_SIGMA,
    make_scan_series,
    make_soil_shear_band,
    scan_series,
    soil_pair,
)
from napari_dvc_correct.engine.synthetic import sample_displacement, shear_band


def _mismatch(reference, deformed, truth=None):
    """RMS of F(X + u(X)) - G(X) over interior voxels (u = 0 without ``truth``)."""
    points = np.stack(
        np.meshgrid(*[np.arange(10, n - 10, 2.0) for n in reference.shape], indexing="ij"), -1
    ).reshape(-1, 3)
    moved = points if truth is None else points + sample_displacement(shear_band(**truth), points)
    values = ndimage.map_coordinates(deformed.astype(np.float64), moved.T, order=3)
    expected = reference[tuple(points.astype(int).T)]
    return float(np.sqrt(np.mean((values - expected) ** 2)))


def test_soil_pair_is_deterministic_and_matches_its_known_deformation():
    reference, deformed, truth = soil_pair((40, 40, 40), slip=4.0)
    again, _, _ = soil_pair((40, 40, 40), slip=4.0)
    np.testing.assert_array_equal(reference, again)
    assert reference.dtype == np.float32 and reference.shape == (40, 40, 40)
    # poor texture: two phases around 100 and 170 gray levels
    assert 100 < np.mean(reference) < 170
    # undoing the known motion brings F back onto G up to the two noises (sqrt 2 sigma + interp.)
    undone = _mismatch(reference, deformed, truth)
    assert undone < 2.0 * NOISE_SIGMA
    assert _mismatch(reference, deformed) > 1.5 * undone


def test_scan_series_grows_step_by_step():
    series, truths = scan_series((32, 32, 32), slips=(0.0, 2.0, 4.0, 6.0))
    assert series.shape == (4, 32, 32, 32)
    assert [t["slip"] for t in truths] == [0.0, 2.0, 4.0, 6.0]
    point = np.array([[16.0, 16.0, 24.0]])
    motion = [np.linalg.norm(sample_displacement(shear_band(**t), point)) for t in truths]
    assert motion[0] == 0.0 and motion == sorted(motion)
    for k in range(1, 4):
        assert _mismatch(series[0], series[k], truths[k]) < 2.0 * NOISE_SIGMA


def test_npe2_commands_return_layer_tuples():
    layers = make_soil_shear_band()
    assert [kwargs["name"] for _, kwargs, _ in layers] == ["reference", "deformed"]
    assert all(data.shape == (96, 96, 96) for data, _, _ in layers)
    assert layers[1][1]["metadata"]["dvc_correct"]["truth"]["slip"] > 0
    ((series, kwargs, layer_type),) = make_scan_series()
    assert series.shape == (4, 64, 64, 64) and layer_type == "image"
    assert len(kwargs["metadata"]["dvc_correct"]["truths"]) == 4


def test_napari_lists_and_opens_the_samples(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.open_sample("napari-dvc-correct", "soil_shear_band")
    assert [layer.name for layer in viewer.layers] == ["reference", "deformed"]
