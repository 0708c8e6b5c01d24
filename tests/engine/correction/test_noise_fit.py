"""The regularised estimate where a neighbourhood holds only matching noise: known answers."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correction import noise_fit
from napari_dvc_correct.engine.correction.noise_fit import (
    fit_noise_regions,
    overlap_correlation,
    regularise,
)
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status

SHAPE, STEP, SUBVOLUME, SIGMA = (8, 8, 8), 6.0, 21, 0.1


def test_the_overlap_correlation_is_the_shared_fraction_of_the_subvolumes():
    assert overlap_correlation(np.zeros(3), 21, 21) == pytest.approx(1.0)
    assert overlap_correlation(np.array([6.0, 0, 0]), 21, 21) == pytest.approx(1 - 6 / 21)
    both = overlap_correlation(np.array([6.0, -6.0, 0]), 21, 21)
    assert both == pytest.approx((1 - 6 / 21) ** 2)
    assert overlap_correlation(np.array([21.0, 0, 0]), 21, 21) == 0.0
    # a 15³ box inside a 21³ one: the shared 15³ over the geometric mean of the volumes
    assert overlap_correlation(np.zeros(3), 21, 15) == pytest.approx((15 / 21) ** 1.5)


def _noise(seed, shape=SHAPE):
    """Matching noise with the model's covariance (each component independent)."""
    grid = np.stack(np.meshgrid(*[np.arange(n) * STEP for n in shape], indexing="ij"), -1)
    points = grid.reshape(-1, 3)
    correlation = overlap_correlation(points[:, None] - points[None], SUBVOLUME, SUBVOLUME)
    root = np.linalg.cholesky(correlation**noise_fit.CORRELATION_POWER + 1e-9 * np.eye(len(points)))
    white = np.random.default_rng(seed).standard_normal((len(points), 3))
    return (SIGMA * root @ white).reshape(*shape, 3)


def _field(truth, seed, status=None):
    field = DisplacementField.zeros((0.0, 0.0, 0.0), (STEP,) * 3, SHAPE)
    exact = truth(field.points).reshape(*SHAPE, 3)
    field.u = exact + _noise(seed)
    field.uncertainty = np.full((*SHAPE, 3), SIGMA)
    if status is not None:
        field.status[:] = status
    return field, exact


def _rmse(values, exact, where=None):
    error = np.linalg.norm(values - exact, axis=-1)
    return float(np.sqrt(np.mean(error[where] ** 2 if where is not None else error**2)))


def _translation(points):
    return np.broadcast_to(np.array([1.3, -0.7, 0.6]), points.shape)


def _affine(points):
    gradient = np.array([[0.02, 0.01, 0.0], [0.0, -0.015, 0.01], [0.01, 0.0, 0.02]])
    return points @ gradient.T + np.array([1.7, -0.8, 2.3])


@pytest.mark.parametrize("truth", [_translation, _affine], ids=["translation", "affine"])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_noisy_translation_or_affine_field_gets_closer_to_the_truth(truth, seed):
    field, exact = _field(truth, seed)
    fit = fit_noise_regions(field, SUBVOLUME)
    # measured: 1.7-2.0x lower RMSE over the fitted nodes (seeds 0, 1); most nodes fitted
    assert fit.fitted.mean() > 0.6
    before = _rmse(field.u, exact, fit.fitted)
    after = _rmse(fit.field.u, exact, fit.fitted)
    assert after < before / 1.4
    assert _rmse(fit.field.u, exact) < _rmse(field.u, exact) / 1.3
    # the recorded uncertainty is the fit's, and it says how far the fitted values are
    predicted = np.linalg.norm(fit.field.uncertainty[fit.fitted], axis=-1)
    assert np.all(predicted < np.sqrt(3) * SIGMA)
    assert 0.6 < after / float(np.sqrt(np.mean(predicted**2))) < 1.6
    # not fitted: values and uncertainties unchanged to the bit
    assert np.array_equal(fit.field.u[~fit.fitted], field.u[~fit.fitted])
    summary = fit.summary()
    assert summary["fitted_nodes"] == int(fit.fitted.sum())
    assert len(summary["fitted"]) == summary["fitted_nodes"]


def _band(points):
    """A shear band of half-width 4 (tanh) through the middle, slip 2.8, on a translation."""
    normal = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    direction = np.array([1.0, 0.0, -1.0]) / np.sqrt(2.0)
    distance = (points - 21.0) @ normal
    return 1.4 * np.tanh(distance / 4.0)[:, None] * direction + np.array([1.3, -0.7, 0.6])


@pytest.mark.parametrize("seed", [0, 1])
def test_a_band_s_values_are_never_fitted(seed):
    field, exact = _field(_band, seed)
    fit = regularise(field, SUBVOLUME, SUBVOLUME)
    distance = np.abs((field.points - 21.0) @ (np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)))
    near = (distance < 15.0).reshape(SHAPE)
    assert not fit.fitted[near].any()
    assert np.array_equal(fit.field.u[near], field.u[near])
    assert np.array_equal(fit.field.uncertainty[near], field.uncertainty[near])


def test_a_fault_s_jump_is_never_smoothed():
    # two blocks moving 1 voxel apart along x: every neighbourhood across the jump fails
    def fault(points):
        return _translation(points) + np.where(points[:, 2:3] < 21.0, 0.0, 1.0) * [0, 0, 1.0]

    field, _ = _field(fault, 0)
    fit = fit_noise_regions(field, SUBVOLUME)
    across = np.zeros(SHAPE, bool)
    across[:, :, 3:5] = True  # nodes at x = 18 and 24: their neighbourhoods hold both sides
    assert not fit.fitted[across].any()
    assert np.array_equal(fit.field.u[across], field.u[across])
    assert fit.fitted[:, :, [0, 7]].any()  # the blocks themselves are noise around a translation


@pytest.mark.parametrize("status", [Status.DISCONTINUITY, Status.OUTLIER_REPLACED, Status.MASKED])
def test_a_crack_flagged_or_masked_node_stops_every_fit_around_it(status):
    field, _ = _field(_translation, 0)
    field.status[:, :, 4] = status  # a crack's plane of nodes (or a flagged / masked layer)
    fit = fit_noise_regions(field, SUBVOLUME)
    near = np.zeros(SHAPE, bool)
    near[:, :, 3:6] = True
    assert not fit.fitted[near].any()
    assert np.array_equal(fit.field.u[near], field.u[near])
    assert fit.fitted[:, :, [0, 1, 7]].any()


def test_a_failed_match_is_left_out_without_stopping_its_neighbours():
    field, _ = _field(_translation, 0)
    field.status[4, 4, 4] = Status.LOW_ZNCC
    field.u[4, 4, 4] += 3.0  # a wrong match
    fit = fit_noise_regions(field, SUBVOLUME)
    assert not fit.fitted[4, 4, 4]
    assert fit.fitted[3:6, 3:6, 3:6].sum() >= 13
    assert np.all(np.abs(fit.field.u[3:6, 3:6, 3:6] - field.u[3:6, 3:6, 3:6])[..., 0] < 1.0)


def test_nodes_that_are_not_usable_or_refilled_are_not_fitted():
    field, _ = _field(_translation, 0)
    field.provenance[2, 2, 2] = Provenance.REPLACED
    usable = np.ones(SHAPE, bool)
    usable[6, 6, 6] = False
    fit = fit_noise_regions(field, SUBVOLUME, usable)
    assert not fit.fitted[2, 2, 2]
    assert not fit.fitted[5:, 5:, 5:].any()


def test_bad_input_is_refused_with_a_message():
    field, _ = _field(_translation, 0)
    field.uncertainty = None
    with pytest.raises(ValueError, match="uncertainty"):
        fit_noise_regions(field, SUBVOLUME)
    field, _ = _field(_translation, 0)
    with pytest.raises(ValueError, match="subvolume"):
        fit_noise_regions(field, 0)


def test_masked_nodes_without_values_leave_the_interior_to_the_fit():
    # a specimen mask leaves the outer nodes MASKED and without a value; the bend is measured on
    # the field with them filled in (the correction's own filled field)
    field, exact = _field(_translation, 0)
    filled = field.copy()
    outer = np.ones(SHAPE, bool)
    outer[1:-1, 1:-1, 1:-1] = False
    field.u[outer] = np.nan
    field.status[outer] = Status.MASKED
    field.provenance[outer] = Provenance.MASKED
    fit = regularise(field, SUBVOLUME, SUBVOLUME, filled=filled)
    assert fit.fitted[2:-2, 2:-2, 2:-2].mean() > 0.5  # away from the masked shell
    assert not fit.fitted[outer].any() and not fit.fitted[1, :, :].any()
    assert np.isnan(fit.field.u[outer]).all()
    # without the filled field the bend is unknown everywhere: nothing is fitted
    assert not regularise(field, SUBVOLUME, SUBVOLUME).fitted.any()


def test_a_field_without_uncertainties_is_left_alone_and_says_why():
    field, _ = _field(_translation, 0)
    field.uncertainty = None
    fit = regularise(field, SUBVOLUME, SUBVOLUME)
    assert not fit.fitted.any() and np.array_equal(fit.field.u, field.u)
    assert fit.summary()["not_run"] == "the field carries no match uncertainty"
