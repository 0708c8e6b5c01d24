"""The weighted sandwich uncertainty predicts the scatter of weighted matches over noise."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation import icgn_weighted, icgn_weighted_uncertainty
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.correlation.pyramid import PyramidLevel

N = 36
HALF = 7
CENTERS = np.array(
    [[z, y, x] for z in (12, 18, 23) for y in (12, 18, 23) for x in (12, 18, 23)], np.int64
)
SHIFT = (0.4, -0.3, 0.2)


def _scatter_and_prediction(order, noise, sensitive, window, realisations=24):
    """Empirical and predicted variance of the translations over noise realisations (pooled
    over POIs and axes), the prediction from the judge's statistics pass."""
    pattern = lambda s: synthetic.textured_volume(s, 2.5, seed=5)  # noqa: E731
    clean_ref, clean_def = synthetic.make_pair(pattern, (N,) * 3, synthetic.translation(SHIFT))
    sigma_n = noise * float(np.std(clean_ref))
    nb = 4 if order == 1 else 10
    params = CorrelationParams(subvolume=2 * HALF + 1, order=order, window=window)
    weights = params.subvolume_weights()  # truncated at WINDOW_TRUNCATE std, as the passes'
    params = params.replace(window=None)
    found, predicted = [], []
    for r in range(realisations):
        reference = np.float32(synthetic.add_noise(clean_ref, sigma_n, seed=100 + r))
        deformed = np.float32(synthetic.add_noise(clean_def, sigma_n, seed=500 + r))
        level = PyramidLevel.build(1, reference, deformed, None, HALF, 0.05, weights=weights)
        warps = np.zeros((len(CENTERS), 3 * nb))
        warps[:, [0, nb, 2 * nb]] = SHIFT
        zncc, status, _ = level.match(CENTERS, warps, order, params)
        assert np.all(status == 0)
        stats = (None, None, np.empty((len(CENTERS), 3)))
        flags = np.full(len(CENTERS), sensitive)
        level.statistics(CENTERS, warps, zncc, order, flags, stats, slice(None))
        found.append(warps[:, [0, nb, 2 * nb]])
        predicted.append(stats[2])
    found = np.array(found)
    empirical = np.mean(np.var(found, axis=0, ddof=1))
    return empirical, np.mean(np.array(predicted) ** 2)


@pytest.mark.parametrize(
    "order, noise, sensitive, window",
    [(1, 0.3, True, 3.5), (2, 0.15, True, 3.5), (1, 0.05, False, 3.5), (2, 0.05, False, 3.5),
     (2, 0.05, False, 3.0)],
)  # fmt: skip
def test_the_weighted_uncertainty_predicts_the_scatter(order, noise, sensitive, window):
    """Over 24 noise realisations of 27 POIs (the Gaussian window of std 3.5 on 15³, truncated
    at 3 std as :meth:`.CorrelationParams.subvolume_weights` builds it; and std 3.0, the
    correcting passes' window on the 100³ shear band, which the truncation cuts most: 19 % of
    the voxels), the predicted standard deviation is within 20 % of the scatter of the
    estimates: with the sensitivity pass under noise 0.3 (first order) or 0.15 (second order)
    × the texture's std on both scans, without it under 0.05. (At 0.3 the second-order
    sandwich over-reads the scatter 1.5× unweighted on 15³ as well: the sensitivity matrix of
    30 parameters is itself noisy.)"""
    empirical, predicted = _scatter_and_prediction(order, noise, sensitive, window)
    ratio = np.sqrt(predicted / empirical)
    assert 0.8 < ratio < 1.2, ratio


def test_the_window_lowers_the_scatter_it_predicts():
    """A narrower window holds less of the subvolume: its matches scatter more, and the
    estimate says so."""
    wide = _scatter_and_prediction(2, 0.15, True, 6.0, realisations=12)
    narrow = _scatter_and_prediction(2, 0.15, True, 3.0, realisations=12)
    assert narrow[0] > 1.5 * wide[0] and narrow[1] > 1.5 * wide[1]


@pytest.mark.parametrize("sensitive", [False, True])
def test_the_sandwich_does_not_depend_on_the_weights_scale(sensitive):
    """Weights times 3 (``H₁``, ``H₂``, ``W``, ``W₂`` all rescaled) give the same uncertainty to
    rounding: the estimate reads the weights' shape, not their unit."""
    pattern = lambda s: synthetic.textured_volume(s, 2.5, seed=5)  # noqa: E731
    reference, deformed = synthetic.make_pair(pattern, (N,) * 3, synthetic.translation(SHIFT))
    reference = np.float32(synthetic.add_noise(reference, 0.1 * np.std(reference), seed=1))
    level = PyramidLevel.build(1, reference, np.float32(deformed), None, HALF, 0.05)
    window = icgn_weighted.check_weights(icgn_weighted.gaussian_window(HALF, 3.5), HALF)
    p = np.zeros(30)
    p[[0, 10, 20]] = SHIFT
    out = []
    for scale in (1.0, 3.0):
        n = (2 * HALF + 1) ** 3
        g, w = np.empty(n, np.float32), np.empty(n)
        grad, xi = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        count, _, _ = icgn_weighted._gather(
            level.reference, level.gradient, level.mask, False, scale * window, 18, 18, 18, HALF,
            g, grad, xi, w,
        )  # fmt: skip
        mean_g, delta_g, ok, _, sum_j, sum_jg, total, second = icgn_weighted.weighted_terms(
            g, grad, xi, w, count, 10
        )
        assert ok
        sigma = np.empty(3)
        icgn_weighted_uncertainty.weighted_sigma_at(
            level.coef_deformed, g, grad, xi, w, count, 10, mean_g, delta_g, second, sum_j,
            sum_jg, total, 0.98, p, 18, 18, 18, sensitive, sigma,
        )  # fmt: skip
        out.append(sigma)
    assert np.all(np.isfinite(out[0])) and np.all(out[0] > 0)
    np.testing.assert_allclose(out[1], out[0], rtol=1e-9)
