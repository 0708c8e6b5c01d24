"""The error estimate's window moments and its instrument (engine/evaluation/error_moments.py)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.accuracy_blocks import gradient_components
from napari_dvc_correct.engine.evaluation.error_moments import (
    instrument_noise_pairing,
    smoothed_gradient,
)


def test_the_instrument_s_noise_pairing_is_what_white_noise_shows():
    """``c = E[h_i g_i] / σ²`` of white noise (the pairing the step takes out) against the mean
    over a noise volume, and 0 across components and with the noise itself."""
    noise = np.random.default_rng(5).normal(0.0, 3.0, (72, 72, 72))
    h, g = smoothed_gradient(noise), gradient_components(noise)
    inner = (slice(None), *(slice(4, -4),) * 3)
    h, g, n = h[inner].astype(np.float64), g[inner].astype(np.float64), noise[inner[1:]]
    c = instrument_noise_pairing()
    assert 0.02 < c < 0.06  # a Gaussian of 1 voxel keeps little of the noise's finest scale
    assert np.mean(h[0] * g[0]) / 9.0 == pytest.approx(c, rel=0.1)
    assert np.mean(h[0] * g[1]) / 9.0 == pytest.approx(0.0, abs=0.1 * c)
    assert np.mean(h[2] * n) / 9.0 == pytest.approx(0.0, abs=0.1 * c)
