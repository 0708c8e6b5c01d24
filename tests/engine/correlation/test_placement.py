"""Where the points go (engine/correlation/placement.py): boxes, cylinders, origins."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.placement import (
    Box,
    Cylinder,
    grid_for_region,
    restrict_to_region,
)
from napari_dvc_correct.engine.fields.field import (
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)


def nodes(grid):
    return DisplacementField.zeros(*grid).points


def test_without_a_region_the_grid_is_the_default_one():
    assert grid_for_region((60, 50, 40), 11, 6) == grid_for_volume((60, 50, 40), 11, 6)


def test_a_box_limits_the_grid_to_the_region():
    box = Box((10, 20, 5), (30, 41, 25))
    grid = grid_for_region((60, 60, 60), 11, 4, box)
    points = nodes(grid)
    assert np.all(box.contains(points))
    # the grid fills the box: one more step along any axis would leave it
    hi = points.max(axis=0) + np.array(grid[1])
    lo = points.min(axis=0) - np.array(grid[1])
    assert np.all((hi >= box.hi) | (lo < box.lo))
    assert grid[2] == (5, 6, 5)


def test_the_box_is_clipped_to_where_subvolumes_fit():
    grid = grid_for_region((40, 40, 40), 11, 5, Box((-100, 0, 0), (100, 40, 40)))
    points = nodes(grid)
    assert points.min() >= 5 + 2 and points.max() <= 39 - 5 - 2


def test_an_origin_places_the_first_node():
    grid = grid_for_region((40, 40, 40), 11, 5, origin=(9, 10, 11))
    assert grid[0] == (9.0, 10.0, 11.0)
    assert nodes(grid).max(axis=0).tolist() == [29.0, 30.0, 31.0]
    with pytest.raises(ValueError, match="whole voxels"):
        grid_for_region((40, 40, 40), 11, 5, origin=(9.5, 10, 11))
    with pytest.raises(ValueError, match="outside"):
        grid_for_region((40, 40, 40), 11, 5, origin=(1, 10, 11))


def test_a_region_outside_the_volume_says_so():
    with pytest.raises(ValueError, match="no node fits along axis z"):
        grid_for_region((40, 40, 40), 11, 5, Box((50, 0, 0), (60, 40, 40)))


def test_a_cylinder_keeps_nodes_within_its_radius_and_z_range():
    cylinder = Cylinder(center=(30, 28), radius=12, z_range=(10, 40))
    grid = grid_for_region((64, 64, 64), 9, 4, cylinder)
    field = DisplacementField.zeros(*grid)
    field.u[:] = 1.0
    kept = restrict_to_region(field, cylinder)
    points = kept.points
    radial = np.hypot(points[:, 1] - 30, points[:, 2] - 28)
    inside = kept.status.reshape(-1) != Status.NOT_COMPUTED
    assert inside.sum() > 0 and (~inside).sum() > 0  # the box corners are dropped
    assert np.all(radial[inside] <= 12 + 1e-9) and np.all(radial[~inside] > 12)
    assert np.all((points[:, 0] >= 10) & (points[:, 0] < 40))
    assert np.all(kept.provenance.reshape(-1)[~inside] == Provenance.NOT_COMPUTED)
    assert np.all(np.isnan(kept.u.reshape(-1, 3)[~inside]))


def test_regions_validate_their_bounds():
    with pytest.raises(ValueError, match="lo < hi"):
        Box((0, 0, 0), (10, 0, 10))
    with pytest.raises(ValueError, match="radius"):
        Cylinder((0, 0), 0)
