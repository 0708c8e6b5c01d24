"""Residual binned by the equivalent strain of the nearest grid node."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.binning import bin_residual_by_strain, strain_bin_edges
from napari_dvc_correct.engine.fields.field import DisplacementField


def test_binning_uses_the_nearest_node_cell():
    field = DisplacementField.zeros(origin=(2.0, 2.0, 3.0), step=(4.0, 4.0, 6.0), shape=(3, 2, 2))
    strain = np.arange(12, dtype=np.float64).reshape(3, 2, 2) / 100.0  # a different strain per node
    shape = (12, 8, 12)  # cells of 4 x 4 x 6 voxels tile the volume exactly
    # residual = 1000 * strain of the voxel's nearest node, so every bin's mean is known
    z, y, x = np.indices(shape)
    iz, iy, ix = (z - 2 + 2) // 4, (y - 2 + 2) // 4, (x - 3 + 3) // 6
    residual = (1000.0 * strain[iz, iy, ix]).astype(np.float32)
    edges = np.array([0.0, 0.035, 0.075, 0.2])
    bins = bin_residual_by_strain(residual, strain, field, edges)
    assert bins.voxels.tolist() == [4 * 96, 4 * 96, 4 * 96]
    assert bins.mean_residual == pytest.approx([15.0, 55.0, 95.0])
    # NaN strain nodes and NaN residual voxels are left out
    strain_nan = strain.copy()
    strain_nan[0, 0, 0] = np.nan
    residual[11, 7, 11] = np.nan
    bins = bin_residual_by_strain(residual, strain_nan, field, edges)
    assert bins.voxels.tolist() == [3 * 96, 4 * 96, 4 * 96 - 1]
    assert bins.mean_residual[0] == pytest.approx(20.0)
    assert bins.centers == pytest.approx([0.0175, 0.055, 0.1375])


def test_binning_leaves_out_voxels_outside_the_grid_hull():
    field = DisplacementField.zeros(
        origin=(10.0, 10.0, 10.0), step=(4.0, 4.0, 4.0), shape=(2, 2, 2)
    )
    residual = np.ones((30, 30, 30), np.float32)
    bins = bin_residual_by_strain(residual, np.zeros((2, 2, 2)), field, [0.0, 1.0])
    # the cells span 8..15 along each axis (half a step around nodes 10 and 14)
    assert bins.voxels.tolist() == [8**3]
    edges = strain_bin_edges([np.array([0.0, 0.1, np.nan]), np.array([0.2])], n_bins=4)
    assert edges[0] == 0.0 and edges[-1] == pytest.approx(0.2, rel=0.01) and edges.size == 5
    assert strain_bin_edges([np.zeros(3)], 2)[-1] > 0


def test_loaded_state_binning_maps_positions_back():
    field = DisplacementField.zeros(origin=(2.0, 2.0, 2.0), step=(4.0, 4.0, 4.0), shape=(2, 2, 2))
    strain = np.zeros((2, 2, 2))
    strain[1] = 0.5
    residual = np.zeros((8, 8, 16), np.float32)
    residual[:, :, 8:] = 7.0  # the material moved by +8 along x
    bins = bin_residual_by_strain(
        residual, strain, field, [0.0, 0.25, 1.0], lambda p: p - np.array([0.0, 0.0, 8.0])
    )
    assert bins.voxels.tolist() == [256, 256]
    assert bins.mean_residual == pytest.approx([7.0, 7.0])
