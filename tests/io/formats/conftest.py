"""Known fields for the format tests: a translation and an affine field, in (z, y, x) voxels."""

from types import SimpleNamespace

import numpy as np
import pytest

SHIFT = np.array([1.5, -2.0, 0.25])  # (uz, uy, ux)
GRADIENT = np.array(  # du_i/dX_j, i, j in (z, y, x)
    [[0.010, 0.002, -0.004], [0.000, -0.012, 0.006], [0.003, 0.000, 0.008]]
)
CENTER = np.array([20.0, 22.0, 24.0])


def translation(points):
    return np.broadcast_to(SHIFT, np.shape(points)).copy()


def affine(points):
    return SHIFT + (np.asarray(points) - CENTER) @ GRADIENT.T


@pytest.fixture
def grid_points():
    """A 3 x 4 x 5 grid, C order (z slowest), step (6, 5, 4), origin (8, 9, 10)."""
    axes = [8.0 + 6.0 * np.arange(3), 9.0 + 5.0 * np.arange(4), 10.0 + 4.0 * np.arange(5)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


@pytest.fixture
def scattered_points():
    return np.random.default_rng(7).uniform(5.0, 40.0, size=(30, 3))


@pytest.fixture
def known():
    """The known fields and their parameters (tests use ``known.affine(points)``...)."""
    return SimpleNamespace(
        shift=SHIFT, gradient=GRADIENT, center=CENTER, affine=affine, translation=translation
    )
