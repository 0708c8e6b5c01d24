"""The uncertainty estimate's noise-stage kernel against the full pass."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation import icgn_uncertainty
from napari_dvc_correct.engine.correlation.interpolation import prefilter


@pytest.mark.parametrize("order", [1, 2])
def test_subvolume_moments_equal_the_full_statistics(order):
    """The noise stage's plain sums give the variance and gradient power of the full pass."""
    from napari_dvc_correct.engine.correlation import icgn_reference, shape_function

    rng = np.random.default_rng(2)
    reference = (100.0 + 10.0 * rng.standard_normal((20, 20, 20))).astype(np.float32)
    gradient = icgn_reference.gradient_volume(prefilter(reference))
    mask = rng.random(reference.shape) > 0.2  # masked voxels left out of both
    mask[:, :, :7] = False  # a POI with too few voxels: NaN in both
    nb = shape_function.n_monomials(order)
    half = 3
    centers = np.array([[10, 10, 10], [5, 14, 12], [14, 5, 8], [10, 10, 3]], np.int64)
    n = len(centers)
    variance, power = np.empty(n), np.empty(n)
    icgn_uncertainty.subvolume_moments(
        reference, gradient, mask, True, centers, half, nb, variance, power
    )
    full = (np.empty(n), np.empty(n), np.empty((n, 3)))
    icgn_uncertainty.subvolume_statistics(
        reference,
        gradient,
        prefilter(reference),
        mask,
        True,
        centers,
        half,
        nb,
        np.zeros((n, 3 * nb)),
        np.full(n, 0.9),
        np.zeros(n, bool),
        *full,
    )
    assert np.all(np.isnan(variance[3:])) and np.all(np.isnan(full[0][3:]))
    assert np.all(np.isnan(power[3:]))
    # the same sums up to float64 rounding (first order: summed by rows there)
    np.testing.assert_allclose(variance[:3], full[0][:3], rtol=1e-12)
    np.testing.assert_allclose(power[:3], full[1][:3], rtol=1e-12)  # there: diag of L Lᵀ
    window = reference[
        5 - half : 5 + half + 1, 14 - half : 14 + half + 1, 12 - half : 12 + half + 1
    ]
    inside = mask[5 - half : 5 + half + 1, 14 - half : 14 + half + 1, 12 - half : 12 + half + 1]
    np.testing.assert_allclose(variance[1], np.var(window[inside].astype(np.float64)), rtol=1e-12)


@pytest.mark.parametrize("order", [1, 2])
def test_the_matchs_own_sigma_equals_the_statistics_pass(order):
    """IC-GN's sigma from its own reference terms is the statistics kernel's, bit for bit;
    matches that dropped voxels (near the volume's edge) or failed are not measured there."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation import shape_function
    from napari_dvc_correct.engine.correlation.params import CorrelationParams
    from napari_dvc_correct.engine.correlation.pyramid import PyramidLevel

    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=3)
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.4, -0.3, 0.6)))
    params = CorrelationParams(subvolume=11, step=4, order=order)
    level = PyramidLevel.build(
        1, reference.astype(np.float32), deformed.astype(np.float32), None, params.half, 0.0,
        "cpu",
    )  # fmt: skip
    nb = shape_function.n_monomials(order)
    # inner POIs, one at the volume's edge pushed out by its guess (drops voxels), one flat
    centers = np.array([[12, 14, 20], [20, 20, 20], [26, 22, 15], [5, 20, 20]], np.int64)
    warps = np.zeros((len(centers), 3 * nb))
    warps[3, 0] = -3.0
    sigma = np.zeros((len(centers), 4))
    zncc, status, _ = level.match(centers, warps.copy(), order, params, sigma=sigma)
    matched = warps.copy()
    level.match(centers, matched, order, params)  # the same matches without sigma
    measured = sigma[:, 3] == 1.0
    assert measured[:3].all() and not measured[3]
    expected = np.empty((len(centers), 3))
    icgn_uncertainty.subvolume_statistics(
        level.reference, level.gradient, level.coef_deformed, level.mask, False, centers,
        params.half, nb, matched, zncc, np.zeros(len(centers), bool), np.empty(len(centers)),
        np.empty(len(centers)), expected,
    )  # fmt: skip
    assert np.all(np.isfinite(expected[:3])) and np.all(expected[:3] > 0)
    np.testing.assert_array_equal(sigma[:3, :3], expected[:3])

    # POIs whose gradient power is below noise_power: the sensitivity pass, from the same terms
    noisy = synthetic.add_noise(deformed, 0.03, seed=2).astype(np.float32)
    level = PyramidLevel.build(
        1, reference.astype(np.float32), noisy, None, params.half, 0.0, "cpu"
    )  # fmt: skip
    for noise_power in (0.0, 1e30):
        sigma = np.zeros((len(centers), 4))
        matched = warps.copy()
        zncc, status, _ = level.match(
            centers, matched, order, params, sigma=sigma, noise_power=noise_power
        )
        kind = 1.0 if noise_power == 0.0 else 2.0
        assert np.all(sigma[:3, 3] == kind) and sigma[3, 3] == 0.0
        expected = np.empty((len(centers), 3))
        icgn_uncertainty.subvolume_statistics(
            level.reference, level.gradient, level.coef_deformed, level.mask, False, centers,
            params.half, nb, matched, zncc, np.full(len(centers), kind == 2.0),
            np.empty(len(centers)), np.empty(len(centers)), expected,
        )  # fmt: skip
        assert np.all(np.isfinite(expected[:3])) and np.all(expected[:3] > 0)
        np.testing.assert_array_equal(sigma[:3, :3], expected[:3])
        if kind == 1.0:
            plain = sigma[:3, :3].copy()
    assert np.abs(sigma[:3, :3] / plain - 1.0).max() > 1e-2  # the sensitivity pass counted


def test_a_field_is_the_same_whether_icgn_or_the_judge_measures_sigma(monkeypatch):
    """Letting IC-GN measure the noise-free sigma changes nothing in the field."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation import pyramid
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    truth = synthetic.shear_band((24.0,) * 3, width=6.0, slip=2.0, shift=(0.5, -0.7, 1.2))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=5), (48,) * 3, truth, margin=8
    )
    deformed = synthetic.add_noise(deformed, 2.0, seed=1)  # some POIs need the sensitivity
    params = CorrelationParams(subvolume=15, step=6)
    fast = correlate(reference, deformed, params)
    original = pyramid.PyramidLevel.match

    def without_sigma(self, centers, warps, order, params, sigma=None, noise_power=0.0):
        return original(self, centers, warps, order, params)

    monkeypatch.setattr(pyramid.PyramidLevel, "match", without_sigma)
    slow = correlate(reference, deformed, params)
    for name in ("u", "zncc", "status", "iterations", "uncertainty"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
    assert np.isfinite(fast.uncertainty).any()


def test_a_noise_hint_changes_no_number_right_or_wrong(monkeypatch):
    """The hint only moves the sensitivity pass into IC-GN's call: the field is the same with
    no hint, a right one, one that calls every POI noisy and one that calls none; with a right
    hint the judge's own pass measures fewer POIs."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation import pyramid
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    truth = synthetic.shear_band((24.0,) * 3, width=6.0, slip=2.0, shift=(0.5, -0.7, 1.2))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=5), (48,) * 3, truth, margin=8
    )
    reference = synthetic.add_noise(reference, 0.03, seed=2)
    deformed = synthetic.add_noise(deformed, 0.03, seed=1)
    measured = []
    original = pyramid.PyramidLevel.statistics

    def counting(self, centers, *args):
        measured.append(len(centers))
        return original(self, centers, *args)

    monkeypatch.setattr(pyramid.PyramidLevel, "statistics", counting)
    params = CorrelationParams(subvolume=15, step=6, order=2)
    plain = correlate(reference, deformed, params)
    variance = plain.metadata["noise"]["sigma"] ** 2
    assert variance > 0
    for hint in (variance, 1e9, 1e-9):
        field = correlate(reference, deformed, params, noise_hint=hint)
        for name in ("u", "zncc", "status", "iterations", "uncertainty"):
            np.testing.assert_array_equal(
                getattr(field, name), getattr(plain, name), err_msg=f"{name}, hint {hint}"
            )
    assert np.isfinite(plain.uncertainty).any()
    no_hint, right, everywhere, nowhere = measured
    assert no_hint > 0 and right < no_hint  # the hint moved the pass (here all of it)
    assert nowhere == no_hint and everywhere <= no_hint


@pytest.mark.parametrize("order", [1, 2])
def test_moments_and_statistics_from_gs_coefficients_equal_those_from_its_gradient(order):
    """Given ``G``'s coefficients (1, nz, ny, nx) instead of ``∇G``, both kernels compute each
    subvolume's gradient themselves: the same numbers to the last bit, masked voxels, the
    sensitivity pass and POIs at the volume's faces included."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation import icgn_reference, shape_function

    reference = synthetic.textured_volume((26, 24, 22), 2.0, seed=6).astype(np.float32)
    deformed = synthetic.add_noise(
        synthetic.deform_volume(reference, synthetic.translation((0.3, 0.2, -0.4))), 0.03, seed=1
    ).astype(np.float32)
    coefficients = prefilter(reference)
    mask = np.random.default_rng(4).random(reference.shape) > 0.1
    nb = shape_function.n_monomials(order)
    half = 4
    centers = np.array([[4, 4, 4], [13, 12, 11], [21, 19, 17], [8, 15, 6]], np.int64)
    n = len(centers)
    warps = np.zeros((n, 3 * nb))
    warps[:, 0], warps[:, nb], warps[:, 2 * nb] = 0.3, 0.2, -0.4
    results = []
    for gradient in (icgn_reference.gradient_volume(coefficients), coefficients[None]):
        moments = (np.empty(n), np.empty(n))
        icgn_uncertainty.subvolume_moments(
            reference, gradient, mask, True, centers, half, nb, *moments
        )
        full = (np.empty(n), np.empty(n), np.empty((n, 3)))
        icgn_uncertainty.subvolume_statistics(
            reference, gradient, prefilter(deformed), mask, True, centers, half, nb, warps,
            np.full(n, 0.9), np.array([True, False, True, False]), *full,
        )  # fmt: skip
        results.append((*moments, *full))
    for a, b in zip(*results):
        assert np.isfinite(a).all()
        np.testing.assert_array_equal(a, b)
