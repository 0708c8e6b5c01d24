"""A node's departure from the leave-one-out quadratic fit of its neighbours, in voxels."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import spearmanr

from napari_dvc_correct.engine.evaluation.node_roughness import (
    leave_one_out_weights,
    node_roughness,
)

INTERIOR = sum(1 << i for i in range(27) if i != 13)


def _grid(shape=(9, 10, 11)):
    return np.indices(shape, dtype=np.float64)


def test_the_interior_fit_reproduces_quadratics_and_its_noise_gain_is_known():
    """Inside the grid the weights reproduce every quadratic at the node, and an independent
    error's deviation has variance ``(1 + Σ a²) σ²`` with ``Σ a² = 0.35``."""
    weights = leave_one_out_weights(INTERIOR)
    offsets = np.array(np.unravel_index(np.arange(27), (3, 3, 3))).T - 1
    z, y, x = offsets.T
    for values in (np.ones(27), z, y * x, x * x + 2 * z * z - y * z):
        assert weights @ values == pytest.approx(values[13], abs=1e-12)
    assert weights[13] == 0.0
    assert np.sum(weights**2) == pytest.approx(0.35, abs=1e-12)


def test_smooth_fields_read_zero_everywhere_even_at_the_edges():
    """Affine and quadratic fields, and a band whose profile varies along one grid axis (a
    missed shear band's error), hold nothing at the node scale: 0 at every node."""
    z, y, x = _grid()
    affine = np.stack([0.01 * z - 0.02 * x + 1.3, 0.004 * y, 0.3 + 0 * x], -1)
    quadratic = np.stack([0.002 * x * x, 0.001 * z * y, 0.003 * z * z - 0.002 * x * y], -1)
    band = np.exp(-0.5 * ((x - 5.0) / 1.2) ** 2)[..., None] * np.array([0.3, 0.8, -0.5])
    for values in (affine, quadratic, band):
        assert np.all(node_roughness(values) == 0.0)


def test_a_single_wrong_node_stands_out_and_its_neighbours_take_their_share():
    """One node off by 0.4 voxel on an affine field: it reads ``0.4 / √1.35``, each neighbour
    ``|a_j| 0.4 / √1.35``, nodes further away 0."""
    z, y, x = _grid()
    values = np.stack([0.01 * z, -0.02 * y, 0.005 * x], -1)
    values[4, 5, 5] += np.array([0.0, 0.24, 0.32])  # 0.4 voxel
    rough = node_roughness(values)
    weights = leave_one_out_weights(INTERIOR)
    scale = 0.4 / np.sqrt(1.0 + np.sum(weights**2))
    assert rough[4, 5, 5] == pytest.approx(scale, rel=1e-9)
    # neighbour at offset (0, 0, +1) sees the wrong node at its offset (0, 0, -1): index 12
    assert rough[4, 5, 6] == pytest.approx(abs(weights[12]) * scale, rel=1e-9)
    far = np.ones(rough.shape, bool)
    far[3:6, 4:7, 4:7] = False
    assert np.all(rough[far] == 0.0)


def test_independent_node_errors_are_read_at_their_size():
    """Random node errors (0.1 voxel rms, independent): the median reads the truth's within
    10 % (1.005 measured) and ranks it (Spearman 0.67: the neighbours' errors enter the fit)."""
    rng = np.random.default_rng(3)
    z, y, x = _grid((20, 20, 20))
    errors = rng.normal(0.0, 0.1 / np.sqrt(3), (20, 20, 20, 3))
    values = np.stack([0.01 * z, 0.02 * y, -0.01 * x], -1) + errors
    truth = np.linalg.norm(errors, axis=-1)
    rough = node_roughness(values)
    assert np.median(rough) / np.median(truth) == pytest.approx(1.0, abs=0.1)
    assert spearmanr(rough.ravel(), truth.ravel()).statistic > 0.6


def test_small_grids_invalid_nodes_and_bad_input():
    """A grid too small for the fit reads 0; an invalid node is NaN and its neighbours fit
    without it; shapes are checked."""
    assert np.all(node_roughness(np.zeros((1, 1, 1, 3))) == 0.0)
    assert np.all(node_roughness(np.zeros((2, 2, 2, 3))) == 0.0)
    rng = np.random.default_rng(1)
    values = rng.normal(0.0, 0.1, (6, 6, 6, 3))
    values[2, 3, 3] = np.nan
    rough = node_roughness(values)
    assert np.isnan(rough[2, 3, 3]) and np.isfinite(np.delete(rough.ravel(), 2 * 36 + 21)).all()
    valid = np.ones((6, 6, 6), bool)
    valid[0, 0, 0] = False
    assert np.isnan(node_roughness(np.nan_to_num(values), valid)[0, 0, 0])
    with pytest.raises(ValueError, match="nz, ny, nx, 3"):
        node_roughness(np.zeros((4, 4, 4)))
    with pytest.raises(ValueError, match="not on the grid"):
        node_roughness(np.zeros((4, 4, 4, 3)), np.ones((3, 4, 4), bool))


def test_the_deviation_vectors_are_what_the_roughness_measures():
    """node_deviation's vectors: their norms are node_roughness (0 under the floor, NaN at
    invalid nodes), and a lone node error reads along its own direction."""
    from napari_dvc_correct.engine.evaluation.node_roughness import node_deviation

    rng = np.random.default_rng(9)
    values = rng.normal(0.0, 0.1, (6, 7, 5, 3))
    values[2, 3, 1] = np.nan
    deviation = node_deviation(values)
    expected = node_roughness(values)
    norms = np.linalg.norm(deviation, axis=-1)
    np.testing.assert_allclose(np.where(norms < 1e-4, 0.0, norms), expected, equal_nan=True)
    lone = np.zeros((5, 5, 5, 3))
    lone[2, 2, 2] = (0.0, 0.3, 0.4)
    d = node_deviation(lone)[2, 2, 2]
    np.testing.assert_allclose(d / np.linalg.norm(d), [0.0, 0.6, 0.8], atol=1e-12)
