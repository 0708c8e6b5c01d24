"""DVC at an explicit list of points (engine/correlate_points.py)."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlate_points import correlate_points
from napari_dvc_correct.engine.field import Status
from napari_dvc_correct.engine.params import CorrelationParams

SIZE = 48
GRADIENT = np.array([[0.01, 0.0, 0.0], [0.0, -0.008, 0.004], [0.0, 0.0, 0.012]])
CENTER = np.full(3, SIZE / 2)
FIELD = synthetic.affine(GRADIENT, CENTER, shift=(1.3, -0.6, 2.2))
PARAMS = CorrelationParams(subvolume=15, step=6)


@pytest.fixture(scope="module")
def pair():
    return synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=3), (SIZE,) * 3, FIELD
    )


def test_results_come_at_exactly_the_given_irregular_points(pair):
    reference, deformed = pair
    rng = np.random.default_rng(5)
    points = rng.uniform(12.0, SIZE - 13.0, size=(25, 3))  # fractional, no common spacing
    points = np.vstack([points, [[2.0, 20.0, 20.0]]])  # its subvolume leaves the volume
    result = correlate_points(reference, deformed, points, PARAMS)
    np.testing.assert_array_equal(result.points, points)
    assert result.status[-1] == Status.OUT_OF_BOUNDS and np.all(np.isnan(result.u[-1]))
    good = result.valid
    assert good[:-1].all()
    error = np.linalg.norm(result.u[:-1] - FIELD(points[:-1]), axis=1)
    assert error.max() < 0.05, error.max()
    np.testing.assert_allclose(
        result.gradient[:-1], np.broadcast_to(GRADIENT, (25, 3, 3)), atol=5e-3
    )


def test_points_that_all_leave_the_volume_are_refused(pair):
    reference, deformed = pair
    with pytest.raises(ValueError, match="border"):
        correlate_points(reference, deformed, [[1.0, 1.0, 1.0]], PARAMS)
