"""IC-GN on weighted subvolumes: unit weights are the unweighted match, known fields are found,
bad weights are refused."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation import icgn_weighted, shape_function
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.correlation.pyramid import PyramidLevel

N = 40
CENTER = (N - 1) / 2.0
CENTERS = np.array(
    [[z, y, x] for z in (14, 20, 25) for y in (14, 20, 25) for x in (14, 20, 25)], np.int64
)


def _pair(truth, seed=3, noise=0.0):
    pattern = lambda s: synthetic.textured_volume(s, 2.5, seed=seed)  # noqa: E731
    reference, deformed = synthetic.make_pair(pattern, (N,) * 3, truth, margin=12)
    if noise:
        sigma = noise * float(np.std(reference))
        reference = synthetic.add_noise(reference, sigma, seed=seed + 10)
        deformed = synthetic.add_noise(deformed, sigma, seed=seed + 20)
    return np.float32(reference), np.float32(deformed)


def _match(reference, deformed, order, half, weights, start=None, **stop):
    level = PyramidLevel.build(1, reference, deformed, None, half, 0.05, weights=weights)
    nb = shape_function.n_monomials(order)
    warps = np.zeros((len(CENTERS), 3 * nb)) if start is None else start.copy()
    sigma = np.zeros((len(CENTERS), 4))
    params = CorrelationParams(subvolume=2 * half + 1, order=order, **stop)
    zncc, status, _ = level.match(CENTERS, warps, order, params, sigma=sigma)
    return warps.reshape(len(CENTERS), 3, nb), zncc, status, sigma, level


AFFINE = synthetic.affine(
    np.array([[0.02, 0.01, 0.0], [0.0, -0.015, 0.01], [0.01, 0.0, 0.02]]), (CENTER,) * 3,
    (0.7, -0.4, 0.3),
)  # fmt: skip


@pytest.mark.parametrize("order", [1, 2])
def test_unit_weights_give_the_unweighted_match(order):
    """Weights all 1: the same displacement, ZNCC, status and uncertainty as the unweighted
    kernels, in IC-GN and in the judge's statistics pass with and without the sensitivity pass.
    The weighted step takes the projected Gauss-Newton Hessian ``H₁⊥`` (the unweighted one steps
    with ``H₁``), so the two walk to the same solution by different steps: both are run to
    convergence (no noise stop, a tolerance of 1e-6 voxel), where they agree to rounding."""
    reference, deformed = _pair(AFFINE, noise=0.2)
    stop = dict(tolerance=1e-6, noise_tolerance=0.0, max_iterations=200)
    plain = _match(reference, deformed, order, 6, None, **stop)
    ones = _match(reference, deformed, order, 6, np.ones((13, 13, 13)), **stop)
    np.testing.assert_array_equal(ones[2], plain[2])
    # two corner POIs of the second-order match stall in both at ~1e-6 (float32 samples)
    done = plain[2] == 0
    assert done.sum() >= len(CENTERS) - 2
    np.testing.assert_allclose(ones[0][done, :, 0], plain[0][done, :, 0], rtol=0, atol=2e-6)
    np.testing.assert_allclose(ones[0][done], plain[0][done], rtol=0, atol=2e-6)
    np.testing.assert_allclose(ones[1][done], plain[1][done], rtol=0, atol=1e-7)
    np.testing.assert_array_equal(ones[3][:, 3], plain[3][:, 3])
    np.testing.assert_allclose(ones[3][done, :3], plain[3][done, :3], rtol=1e-5)
    warps = plain[0].reshape(len(CENTERS), -1)
    for sensitive in (False, True):
        flags = np.full(len(CENTERS), sensitive)
        out = {}
        for name, level in (("plain", plain[4]), ("ones", ones[4])):
            stats = (np.empty(len(CENTERS)), np.empty(len(CENTERS)), np.empty((len(CENTERS), 3)))
            level.statistics(CENTERS, warps, plain[1], order, flags, stats, slice(None))
            moments = (np.empty(len(CENTERS)), np.empty(len(CENTERS)))
            level.moments(CENTERS, order, moments, slice(None))
            out[name] = stats + moments
        for a, b in zip(out["ones"], out["plain"]):
            np.testing.assert_allclose(a, b, rtol=1e-5)


def test_a_weighted_match_finds_known_fields_on_noiseless_texture():
    """A Gaussian window (std 3.5 on 15³) finds an affine field with first order and a quadratic
    one with second order to a few 1e-4 voxel (RMS; the unweighted match: 0.9e-4 and 2.7e-4 on
    this texture), within 3× the unweighted match's error (the window holds fewer effective
    voxels to average the interpolation error over)."""

    def quadratic(points):
        d = np.asarray(points, np.float64) - CENTER
        bend = np.stack([d[:, 1] ** 2, d[:, 0] * d[:, 2], d[:, 2] ** 2 - d[:, 0] ** 2], axis=1)
        return np.array([0.3, -0.2, 0.5]) + 2e-3 * bend

    window = icgn_weighted.gaussian_window(7, 3.5)
    for order, truth in ((1, AFFINE), (2, quadratic)):
        reference, deformed = _pair(truth)
        expected = truth(CENTERS.astype(np.float64))
        weighted = _match(reference, deformed, order, 7, window)
        plain = _match(reference, deformed, order, 7, None)
        assert np.all(weighted[2] == 0)
        error = np.sqrt(np.mean((weighted[0][:, :, 0] - expected) ** 2))
        plain_error = np.sqrt(np.mean((plain[0][:, :, 0] - expected) ** 2))
        assert error < 4e-4 and error < 3.0 * plain_error + 1e-5, (order, error, plain_error)
        assert np.all(weighted[3][:, 3] == 1.0) and np.all(np.isfinite(weighted[3][:, :3]))


def test_a_narrow_window_converges_as_fast_as_the_box():
    """A second-order match under a narrow window (std 3 on 15³) of a noiseless translation
    from a zero start takes about the iterations of the uniform box (the step's Hessian is the
    projected ``H₁⊥``: with ``H₁`` the window took 18.0 iterations on average here where the
    box takes 10.8; 4.0 now) and finds the shift to 1.5e-3 voxel."""
    shift = (0.3, 0.2, -0.4)
    reference, deformed = _pair(synthetic.translation(shift), seed=5)
    counts = {}
    for name, weights in (("box", None), ("window", icgn_weighted.gaussian_window(7, 3.0))):
        level = PyramidLevel.build(1, reference, deformed, None, 7, 0.05, weights=weights)
        warps = np.zeros((len(CENTERS), 30))
        params = CorrelationParams(subvolume=15, order=2)
        _, status, iterations = level.match(CENTERS, warps, 2, params)
        assert np.all(status == 0), name
        error = warps.reshape(len(CENTERS), 3, 10)[:, :, 0] - np.array(shift)
        assert np.max(np.abs(error)) < 1.5e-3, (name, np.max(np.abs(error)))
        counts[name] = float(np.mean(iterations))
    assert counts["window"] <= 1.25 * counts["box"] + 0.25, counts


def test_correlate_with_a_window_and_without():
    """``CorrelationParams.window`` runs the whole correlation weighted (initial guess, repair,
    judge); None is the unweighted run."""
    reference, deformed = _pair(AFFINE)
    params = CorrelationParams(subvolume=15, step=8)
    plain = correlate(reference, deformed, params)
    weighted = correlate(reference, deformed, params.replace(window=4.0))
    truth = AFFINE(plain.points)
    assert weighted.params["window"] == 4.0 and plain.params["window"] is None
    for field in (plain, weighted):
        assert np.all(field.valid)
        assert np.max(np.abs(field.displacement - truth)) < 2e-3
    assert np.all(np.isfinite(weighted.uncertainty))


@pytest.mark.parametrize(
    "weights, message",
    [
        (np.ones((5, 5, 5)), "shape"),
        (-np.ones((7, 7, 7)), ">= 0"),
        (np.zeros((7, 7, 7)), "all zero"),
        (np.full((7, 7, 7), np.nan), "finite"),
    ],
)
def test_bad_weights_are_refused(weights, message):
    with pytest.raises(ValueError, match=message):
        icgn_weighted.check_weights(weights, 3)
    reference = np.zeros((20, 20, 20), np.float32)
    with pytest.raises(ValueError, match=message):
        PyramidLevel.build(1, reference, reference, None, 3, 0.05, weights=weights)


@pytest.mark.parametrize("window", [0.0, -2.0, np.nan, "wide"])
def test_a_bad_window_is_refused(window):
    with pytest.raises(ValueError, match="window"):
        CorrelationParams(window=window)
    with pytest.raises(ValueError, match="standard deviation"):
        icgn_weighted.gaussian_window(3, -1.0)


def _former_weighted_moments(reference, gradient, mask, use_mask, weights, center, half, nb):
    """The judge's moments as the kernel computed them from the gathered copies (float32
    values, float64 sums in the gather's order): the reference for the bit-for-bit test."""
    cz, cy, cx = center
    w, g, grad = [], [], []
    n = 0
    for z in range(cz - half, cz + half + 1):
        for y in range(cy - half, cy + half + 1):
            for x in range(cx - half, cx + half + 1):
                weight = float(weights[n])
                n += 1
                if weight == 0.0 or (use_mask and not mask[z, y, x]):
                    continue
                w.append(weight)
                g.append(float(np.float32(reference[z, y, x])))
                grad.append([float(np.float32(gradient[k, z, y, x])) for k in range(3)])
    if len(w) < 3 * nb + 3:
        return np.nan, np.nan
    total = mean_g = power = 0.0
    for weight, value, gk in zip(w, g, grad):
        total += weight
        mean_g += weight * value
        for k in range(3):
            power += weight * (gk[k] * gk[k])
    mean_g /= total
    ss_g = 0.0
    for weight, value in zip(w, g):
        ss_g += weight * ((value - mean_g) * (value - mean_g))
    return ss_g / total, power / total


def test_the_judges_weighted_moments_are_those_of_the_gathered_subvolume():
    """Read from the volumes without copying each subvolume: the same bits as the sums over
    the gathered copies, with a mask and with weights that are zero at the window's corners."""
    rng = np.random.default_rng(5)
    shape = (24, 24, 24)
    reference = rng.normal(100.0, 20.0, shape).astype(np.float32)
    gradient = rng.normal(0.0, 5.0, (3, *shape)).astype(np.float32)
    mask = rng.random(shape) > 0.3
    half, nb = 4, 10
    r = np.arange(-half, half + 1, dtype=np.float64)
    z, y, x = np.meshgrid(r, r, r, indexing="ij")
    window = np.exp(-(z**2 + y**2 + x**2) / (2 * 2.5**2))
    window[z**2 + y**2 + x**2 > 20] = 0.0
    weights = icgn_weighted.check_weights(window, half)
    centers = np.array([[6, 6, 6], [12, 9, 15], [17, 17, 17], [8, 15, 10]], np.int64)
    for use_mask in (False, True):
        variance = np.empty(len(centers))
        power = np.empty(len(centers))
        icgn_weighted.weighted_moments(
            reference, gradient, mask, use_mask, weights, centers, half, nb, variance, power
        )
        former = np.array([
            _former_weighted_moments(reference, gradient, mask, use_mask, weights, c, half, nb)
            for c in centers
        ])  # fmt: skip
        assert np.array_equal(variance, former[:, 0])
        assert np.array_equal(power, former[:, 1])
