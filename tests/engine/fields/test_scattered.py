"""Scattered fields (engine/fields/scattered.py): exact grids, interpolation with provenance, sampling."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.engine.fields.scattered import (
    ScatteredField,
    default_grid,
    from_grid,
    regular_grid_of,
    sample_field,
    to_grid,
)

GRADIENT = np.array([[0.01, 0.0, -0.02], [0.005, -0.01, 0.0], [0.0, 0.02, 0.01]])
SHIFT = np.array([1.5, -2.0, 0.75])


def affine(points):
    return SHIFT + (np.asarray(points) - 20.0) @ GRADIENT.T


def grid_field():
    field = DisplacementField.zeros((4.0, 6.0, 8.0), (3.0, 4.0, 5.0), (4, 5, 6))
    field.u = affine(field.points).reshape(*field.shape, 3)
    field.zncc[:] = 0.9
    return field


def test_a_shuffled_grid_comes_back_exactly():
    field = grid_field()
    scattered = from_grid(field)
    order = np.random.default_rng(0).permutation(scattered.n_points)
    shuffled = ScatteredField(
        scattered.points[order], scattered.u[order], zncc=scattered.zncc[order]
    )
    back = to_grid(shuffled)
    assert back.same_grid(field)
    np.testing.assert_array_equal(back.u, field.u)
    assert np.all(back.provenance == Provenance.MEASURED)
    assert back.metadata["scattered"]["interpolated"] == 0


def test_regular_grid_of_rejects_a_grid_with_a_hole():
    points = from_grid(grid_field()).points
    assert regular_grid_of(points[1:]) is None
    assert regular_grid_of(points + [0.0, 0.0, 0.3]) is not None  # offset grids are grids


def test_scattered_points_are_interpolated_with_provenance():
    rng = np.random.default_rng(1)
    points = rng.uniform(5.0, 35.0, size=(400, 3))
    scattered = ScatteredField(points, affine(points), zncc=np.full(400, 0.8))
    field = to_grid(scattered, grid=((10.0, 10.0, 10.0), (5.0, 5.0, 5.0), (4, 4, 4)))
    inside = field.provenance == Provenance.INTERPOLATED
    assert inside.sum() == 64  # the grid lies inside the points' hull
    # piecewise-linear interpolation of an affine field is exact
    np.testing.assert_allclose(field.u, affine(field.points).reshape(field.u.shape), atol=1e-9)
    np.testing.assert_allclose(field.zncc, 0.8, atol=1e-6)
    assert field.valid.all()


def test_nodes_outside_the_hull_are_not_computed_and_nodes_on_points_are_measured():
    points = np.array([[0, 0, 0], [0, 0, 10], [0, 10, 0], [10, 0, 0], [10, 10, 10]], float)
    scattered = ScatteredField(points, affine(points))
    field = to_grid(scattered, grid=((0.0, 0.0, 0.0), (10.0, 10.0, 10.0), (2, 2, 2)))
    prov = field.provenance.reshape(-1)
    measured = [0, 1, 2, 4, 7]  # nodes on input points: (0,0,0) (0,0,1) (0,1,0) (1,0,0) (1,1,1)
    assert set(np.flatnonzero(prov == Provenance.MEASURED)) == set(measured)
    np.testing.assert_allclose(field.u.reshape(-1, 3)[measured], affine(points[[0, 1, 2, 3, 4]]))
    others = prov != Provenance.MEASURED
    assert np.all(np.isin(prov[others], [Provenance.INTERPOLATED, Provenance.NOT_COMPUTED]))
    assert np.all(np.isnan(field.u.reshape(-1, 3)[prov == Provenance.NOT_COMPUTED]))


def test_planar_points_raise_a_clear_error():
    points = np.column_stack([np.zeros(20), np.arange(20.0), np.arange(20.0) ** 1.5])
    with pytest.raises(ValueError, match="one plane"):
        to_grid(ScatteredField(points, affine(points)), grid=((0, 0, 0), (1, 1, 1), (1, 3, 3)))


def test_sample_field_is_exact_at_nodes_and_linear_between():
    field = grid_field()
    rng = np.random.default_rng(2)
    lo = np.array(field.origin)
    hi = lo + (np.array(field.shape) - 1) * np.array(field.step)
    points = np.vstack([rng.uniform(lo, hi, size=(50, 3)), field.points[:5], [[0.0, 0.0, 0.0]]])
    sampled = sample_field(field, points)
    np.testing.assert_allclose(sampled.u[:55], affine(points[:55]), atol=1e-9)
    assert np.all(np.isnan(sampled.u[55]))  # outside the grid
    assert sampled.status[55] != Status.CONVERGED
    assert np.all(sampled.provenance[50:55] == Provenance.MEASURED)
    assert np.all(sampled.provenance[:50] == Provenance.INTERPOLATED)


def test_sample_field_does_not_use_unusable_nodes():
    field = grid_field()
    field.status[1, 1, 1] = Status.DIVERGED
    node = field.points.reshape(*field.shape, 3)[1, 1, 1]
    sampled = sample_field(field, np.array([node + 0.5, node + [0, 0, 100]]))
    assert np.all(np.isnan(sampled.u))


def test_default_grid_uses_the_point_spacing():
    rng = np.random.default_rng(3)
    axes = [np.arange(0.0, 40.0, 8.0)] * 3
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    points = points + rng.uniform(-0.3, 0.3, points.shape)
    origin, step, shape = default_grid(points)
    assert step == (8.0, 8.0, 8.0)
    assert all(float(o).is_integer() for o in origin)


def test_scattered_field_validates_its_shapes():
    with pytest.raises(ValueError, match="points"):
        ScatteredField(np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="u must"):
        ScatteredField(np.zeros((3, 3)), np.zeros((2, 3)))


def test_match_uncertainties_go_through_points_and_back_to_a_grid():
    field = grid_field()
    field.uncertainty = np.random.default_rng(3).uniform(0.01, 0.1, size=(*field.shape, 3))
    scattered = from_grid(field)
    np.testing.assert_array_equal(scattered.uncertainty, field.uncertainty.reshape(-1, 3))
    order = np.random.default_rng(4).permutation(scattered.n_points)
    shuffled = ScatteredField(
        scattered.points[order], scattered.u[order], uncertainty=scattered.uncertainty[order]
    )
    np.testing.assert_array_equal(to_grid(shuffled).uncertainty, field.uncertainty)
    # on another grid: a node on a point keeps its match's uncertainty, an interpolated one has
    # none (it is no match)
    other = to_grid(scattered, grid=(field.origin, (1.5, 4.0, 5.0), (7, 5, 6)))
    on_point = other.provenance == Provenance.MEASURED
    assert on_point.sum() == 4 * 5 * 6 and (~on_point).sum() == 3 * 5 * 6
    np.testing.assert_array_equal(other.uncertainty[::2], field.uncertainty)
    assert np.all(np.isnan(other.uncertainty[~on_point]))
    # sampled at points: a point on a node keeps the node's, the others have none
    sampled = sample_field(field, np.vstack([field.points[:3], field.points[:3] + 0.5]))
    np.testing.assert_array_equal(sampled.uncertainty[:3], field.uncertainty.reshape(-1, 3)[:3])
    assert np.all(np.isnan(sampled.uncertainty[3:]))
    with pytest.raises(ValueError, match="uncertainty"):
        ScatteredField(scattered.points, scattered.u, uncertainty=np.zeros((2, 3)))
    assert ScatteredField(scattered.points, scattered.u).uncertainty is None
