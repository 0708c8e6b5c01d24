"""DVC at an explicit list of points (engine/correlation/correlate_points.py)."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate_points import correlate_points
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import DisplacementField, Status

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


# --- the noise-aware ZNCC threshold, as on a grid -----------------------------------------------
NOISY_SHIFT = np.array([0.3, -0.4, 0.6])


@pytest.fixture(scope="module")
def noisy_pair():
    """Noise 1.25x the texture's gray deviation: a right match reaches a ZNCC of about 0.44,
    below the fixed 0.5. Beyond x = 36 the deformed scan holds another texture (no match)."""
    clean = synthetic.textured_volume((SIZE,) * 3, 2.0, seed=3)
    deformed = synthetic.deform_volume(clean, synthetic.translation(NOISY_SHIFT))
    deformed[:, :, 36:] = synthetic.textured_volume((SIZE,) * 3, 2.0, seed=4)[:, :, 36:]
    sigma = 1.25 * float(clean.std())
    reference = synthetic.add_noise(clean, sigma, seed=1).astype(np.float32)
    deformed = synthetic.add_noise(deformed, sigma, seed=2).astype(np.float32)
    rng = np.random.default_rng(1)
    points = np.vstack([rng.uniform(11.0, 26.0, size=(36, 3)), [[24.0, 24.0, 40.2]]])
    return reference, deformed, points, sigma


NOISY_PARAMS = CorrelationParams(subvolume=21, step=6)


def test_noisy_points_are_judged_by_the_noise_aware_threshold(noisy_pair):
    reference, deformed, points, sigma = noisy_pair
    result = correlate_points(reference, deformed, points, NOISY_PARAMS)
    noise = result.metadata["noise"]
    assert noise["source"] == "points" and noise["estimates"] == 36
    assert abs(noise["sigma"] - sigma) < 0.15 * sigma  # estimated from the matches alone
    assert 0.15 < noise["zncc_threshold_median"] < 0.3  # 0.5 x (1 - sigma² / s²)
    right = result.zncc[:36]
    assert (right < NOISY_PARAMS.min_zncc).all()  # the fixed threshold would reject them all ...
    assert np.all(np.isin(result.status[:36], [Status.CONVERGED, Status.MAX_ITERATIONS]))
    error = np.linalg.norm(result.u[:36] - NOISY_SHIFT, axis=1)
    assert error.max() < 0.6 and np.sqrt(np.mean(error**2)) < 0.35  # ... yet they are right
    # the point on the other texture still fails
    assert result.status[36] not in (Status.CONVERGED, Status.MAX_ITERATIONS)
    assert np.all(np.isnan(result.u[36]))


def test_few_points_take_the_guide_noise_or_the_fixed_threshold(noisy_pair):
    reference, deformed, points, sigma = noisy_pair
    few = points[:3]
    result = correlate_points(reference, deformed, few, NOISY_PARAMS)
    noise = result.metadata["noise"]
    assert noise["source"] == "guide" and noise["estimates"] >= 30  # the guide's grid
    assert abs(noise["sigma"] - sigma) < 0.15 * sigma
    assert np.all(result.status == Status.CONVERGED)
    # a given guide without a noise estimate (say from another tool): the fixed min_zncc,
    # which rejects these right matches
    guide = DisplacementField((0, 0, 0), (8, 8, 8), np.broadcast_to(NOISY_SHIFT, (7, 7, 7, 3)))
    result = correlate_points(reference, deformed, few, NOISY_PARAMS, guide=guide)
    assert result.metadata["noise"]["source"] == "fixed"
    assert result.metadata["noise"]["zncc_threshold_median"] == NOISY_PARAMS.min_zncc
    assert np.all(result.status == Status.LOW_ZNCC)
