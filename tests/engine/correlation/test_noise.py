"""The noise estimate and the ZNCC thresholds (engine/correlation/noise.py), on hand-made numbers."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.noise import (
    noise_aware_thresholds,
    noise_estimates,
    zncc_floor,
)
from napari_dvc_correct.engine.fields.field import Status

# s² (1 - ZNCC) = 1, 1, 2, 4 for the four matched POIs; the fifth diverged, the sixth unknown
VARIANCE = np.array([4.0, 2.0, 4.0, 8.0, 4.0, np.nan])
ZNCC = np.array([0.75, 0.5, 0.5, 0.5, 0.1, 0.9])
STATUS = np.array([Status.CONVERGED] * 4 + [Status.DIVERGED, Status.CONVERGED], np.int64)


def test_estimates_are_those_of_the_matched_pois():
    np.testing.assert_allclose(noise_estimates(VARIANCE, ZNCC, STATUS), [1.0, 1.0, 2.0, 4.0])


def test_the_median_or_a_given_noise_sets_each_threshold():
    noise, perfect, thresholds = noise_aware_thresholds(VARIANCE, ZNCC, STATUS, 0.5)
    assert noise == pytest.approx(1.5)  # median of 1, 1, 2, 4
    np.testing.assert_allclose(perfect[:4], 1 - 1.5 / VARIANCE[:4])
    np.testing.assert_allclose(thresholds[:4], 0.5 * (1 - 1.5 / VARIANCE[:4]))
    assert thresholds[5] == 0.5  # variance unknown: the plain threshold
    # a whole run's noise given (tiled batches): it replaces these POIs' median
    noise, _, thresholds = noise_aware_thresholds(VARIANCE, ZNCC, STATUS, 0.5, noise_variance=3.0)
    assert noise == 3.0
    np.testing.assert_allclose(thresholds[:4], 0.5 * np.clip(1 - 3.0 / VARIANCE[:4], 0, 1))
    # never below the floor
    floor = zncc_floor(1, 15)
    assert floor == pytest.approx(2.5 * np.sqrt(12 / 15**3))
    _, _, thresholds = noise_aware_thresholds(VARIANCE, ZNCC, STATUS, 0.5, floor, 3.0)
    assert thresholds[1] == pytest.approx(floor)  # 1 - 3/2 < 0, clipped to the floor
