"""The error estimate in voxels per node against known errors (issue 26)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.evaluation.error_estimate import error_summary, residual_error
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    concrete_ct_volume,
    ct_noise_sigma,
    make_pair,
    sample_displacement,
    translation,
)

SHAPE = (56, 56, 56)


def test_residual_error_inverts_the_gaussian_model():
    """R = sqrt(2/pi) sqrt(sigma^2 + e^2 g^2 / 3) with r0 = sqrt(2/pi) sigma gives back e."""
    sigma, g, e = 4.0, 30.0, np.array([0.0, 0.1, 0.5, 1.0])
    r0 = np.sqrt(2 / np.pi) * sigma
    # g is the texture's gradient: add the noise's 1.5 sigma_G^2 (sigma_G = r0 sqrt(pi) / 2)
    measured = np.sqrt(g**2 + 1.5 * (r0 * np.sqrt(np.pi) / 2) ** 2)
    local = np.sqrt(2 / np.pi) * np.sqrt(sigma**2 + e**2 * g**2 / 3)
    np.testing.assert_allclose(residual_error(local, measured, r0), e, atol=1e-9)
    summary = error_summary(np.array([0.1, 0.2, 0.7, np.nan]))
    assert summary["median"] == pytest.approx(0.45) and summary["likely_bad"] == 0.5


@pytest.fixture(scope="module")
def ct_pair():
    truth = translation((1.3, -0.7, 2.2))
    reference, deformed = make_pair(lambda s: concrete_ct_volume(s, seed=3), SHAPE, truth, 12)
    sigma = ct_noise_sigma(reference, 0.03)
    reference, deformed = add_noise(reference, sigma, seed=1), add_noise(deformed, sigma, seed=2)
    origin, step, shape = grid_for_volume(SHAPE, 15, 5)
    base = DisplacementField.zeros(origin, step, shape, params={"subvolume": 15})
    exact = sample_displacement(truth, base.points)
    return reference, deformed, base, exact


def test_the_estimate_follows_imposed_errors_on_ct_texture(ct_pair):
    """A 1-voxel error in a 12-voxel band and a uniform 0.3-voxel error, on faint CT texture
    with 3 % noise: the band's nodes are flagged, the exact field's are not, and the medians
    are within a factor 2 of the truth (benchmarks/bench_error_estimate.py measures more)."""
    from scipy.stats import spearmanr

    reference, deformed, base, exact = ct_pair
    points = base.points
    d = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
    band = np.exp(-0.5 * ((points[:, 2] - 28.0) / (12.0 / 2.355)) ** 2)[:, None] * d
    errors = {
        "exact": np.zeros_like(exact),
        "band": band,
        "uniform": np.tile([0.3, 0, 0], (len(points), 1)),
    }
    fields = {k: base.replace(u=(exact + e).reshape((*base.shape, 3))) for k, e in errors.items()}
    result = evaluate_fields(reference, deformed, fields, keep_volumes=False)
    r = np.hypot(points[:, 1] - 27.5, points[:, 2] - 27.5).reshape(base.shape)
    inside = r < 0.46 * SHAPE[1] - 5  # the specimen (a cylinder in air)
    truth = {k: np.linalg.norm(e, axis=1).reshape(base.shape)[inside] for k, e in errors.items()}
    estimate = {item.name: item.error_estimate[inside] for item in result.fields}
    assert np.mean(estimate["exact"] > 0.5) < 0.05
    bad = truth["band"] > 0.5
    assert bad.sum() > 20 and np.mean(estimate["band"][bad] > 0.5) >= 0.8
    assert spearmanr(estimate["band"], truth["band"]).statistic >= 0.6
    assert 0.5 < np.median(estimate["uniform"]) / 0.3 < 2.0
    assert np.median(estimate["exact"]) < 0.15
