"""The error estimate in voxels per node against known errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.evaluation.accuracy_blocks import gradient_components
from napari_dvc_correct.engine.evaluation.error_estimate import (
    attach_estimate,
    bounded_text,
    error_estimate,
    error_summary,
    estimate_of,
    probability_above,
    residual_error,
    resolution_of,
)
from napari_dvc_correct.engine.evaluation.error_moments import MOMENTS, ErrorMoments, moment_volumes
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


def _texture(shape, size, seed):
    rng = np.random.default_rng(seed)
    texture = ndimage.gaussian_filter(rng.standard_normal(shape), size, mode="wrap")
    return 100.0 * texture / texture.std()


def _window_moments(shift, gain=1.0, offset=0.0, sigma=2.0, seed=0, size=2.0, half=10):
    """Moments of one window of a pair whose moved scan is the reference shifted by ``shift``
    (cubic interpolation of scipy, not ours), times ``gain`` plus ``offset``, noise ``sigma`` on
    both; and the pair's r0 for that noise."""
    big = _texture((48, 48, 48), size, seed)
    grid = np.indices(big.shape, dtype=np.float64)
    moved = ndimage.map_coordinates(big, grid + np.reshape(shift, (3, 1, 1, 1)), order=3)
    rng = np.random.default_rng(seed + 100)
    reference = big + rng.normal(0.0, sigma, big.shape)
    moved = gain * (moved + rng.normal(0.0, sigma, big.shape)) + offset
    window = tuple(slice(24 - half, 24 + half + 1) for _ in range(3))
    volumes = list(
        moment_volumes(
            (moved - reference)[window],
            reference[window],
            gradient_components(reference)[:, *window],
        )
    )
    sums = np.array([np.nansum(v) for v in volumes]).reshape(len(MOMENTS), 1, 1, 1)
    count = np.full((1, 1, 1), np.isfinite(volumes[0]).sum())
    r0 = 2.0 * sigma / np.sqrt(np.pi)
    return ErrorMoments.from_sums(sums, count), r0


@pytest.mark.parametrize("gain, offset", [(1.0, 0.0), (0.8, 15.0)])
def test_the_step_gives_back_a_known_shift_whatever_the_gray_gain(gain, offset):
    """A shift of (0.3, -0.2, 0.1) voxel, made by another interpolator than ours, with noise
    and a gray gain and offset the residual still holds: the step gives it back to 0.03 voxel
    (its noise is ``resolution / √3`` ≈ 0.005 per component; central differences under-read a
    texture this fine by a few percent, which the step returns as a slightly larger shift)."""
    e = np.array([0.3, -0.2, 0.1])
    moments, r0 = _window_moments(e, gain, offset, sigma=10.0)
    result = residual_error(moments, r0)
    resolution = float(result.resolution[0, 0, 0])
    assert 0.003 < resolution < 0.03
    np.testing.assert_allclose(result.shift[0, 0, 0], e, atol=0.03)
    assert result.resolved[0, 0, 0] == pytest.approx(np.linalg.norm(e), abs=0.03)
    assert not result.unexplained.any()


def test_the_resolution_is_the_noise_of_the_step():
    """Over noise realisations of an exact pair, the step's spread per component is
    ``resolution / √3`` within 35 %, and the resolved error is mostly 0 and never twice the
    resolution (the error is below what the residual can see: the estimate is a bound)."""
    steps, resolutions, resolved = [], [], []
    for seed in range(12):
        moments, r0 = _window_moments((0.0, 0.0, 0.0), sigma=20.0, seed=seed, half=6)
        result = residual_error(moments, r0)
        steps.append(result.shift[0, 0, 0])
        resolutions.append(result.resolution[0, 0, 0])
        resolved.append(result.resolved[0, 0, 0])
    spread = float(np.sqrt(np.mean(np.square(steps))))
    expected = float(np.mean(resolutions)) / np.sqrt(3.0)
    assert 0.65 < spread / expected < 1.35
    resolved, resolutions = np.array(resolved), np.array(resolutions)
    assert np.mean(resolved == 0) >= 0.5 and np.all(resolved < 2 * resolutions)


def test_an_error_beyond_the_linear_range_is_not_missed():
    """A 4-voxel error on a fine texture (correlation length about 2 voxels): the texture no
    longer matches, one linear step cannot say how far, and the residual's excess does: the
    estimate is above 1.5 voxels (a lower bound: a texture that no longer matches at all reads
    about twice its correlation length), where the plain step falls far short (about a voxel)."""
    moments, r0 = _window_moments((4.0, 0.0, 0.0), size=1.0)
    result = residual_error(moments, r0)
    assert result.unexplained[0, 0, 0]
    assert np.linalg.norm(result.shift[0, 0, 0]) < 2.0
    assert result.resolved[0, 0, 0] > 1.5


def test_error_summary_counts_bounds_and_undefined_nodes():
    summary = error_summary(np.array([0.1, 0.2, 0.7, np.nan]), resolution=[0.15, 0.1, 0.1, 0.1])
    assert summary["median"] == pytest.approx(0.45) and summary["likely_bad"] == 0.5
    assert summary["below_resolution"] == 0.25 and summary["resolution"] == pytest.approx(0.1)
    assert np.isnan(error_summary(np.array([0.1]))["below_resolution"])


def test_the_probability_of_an_error_above_the_limit_uses_the_estimate_s_noise():
    """σ = resolution / √3: at the limit P = ½, one σ above 0.841, one σ below 0.159; without a
    finite resolution the estimate decides alone; an undefined node counts as bad."""
    resolution = np.sqrt(3.0) * 0.1  # σ = 0.1
    estimate = np.array([0.5, 0.6, 0.4, 0.2, np.nan, 0.7, 0.3])
    limits = np.array([resolution] * 5 + [np.inf, np.nan])
    p = probability_above(estimate, limits, 0.5)
    np.testing.assert_allclose(p[:4], [0.5, 0.841345, 0.158655, 0.001350], atol=1e-6)
    assert p[4] == 1.0 and p[5] == 1.0 and p[6] == 0.0
    np.testing.assert_array_equal(probability_above([0.4, 0.6]), [0.0, 1.0])


def test_the_summary_says_likely_possibly_and_where_its_numbers_are_bounds():
    """Likely: P ≥ ½ (the estimate above 0.5); possibly: P ≥ 16 % (the estimate plus σ above
    0.5). Median and 95th percentile are bounds when half (95 %) of the nodes are below the
    resolution, the bound being the median of max(estimate, resolution)."""
    sigma = 0.05
    resolution = np.full(6, np.sqrt(3.0) * sigma)  # 0.0866
    estimate = np.array([0.0, 0.0, 0.0, 0.44, 0.46, 0.52])
    summary = error_summary(estimate, resolution=resolution)
    assert summary["likely_bad"] == pytest.approx(1 / 6)  # 0.52
    assert summary["possibly_bad"] == pytest.approx(2 / 6)  # 0.46 + 0.05 > 0.5, 0.44 not
    assert summary["below_resolution"] == 0.5 and summary["median_is_bound"]
    assert not summary["p95_is_bound"]
    assert summary["median_bound"] == pytest.approx((0.0866 + 0.44) / 2, abs=1e-4)
    assert bounded_text(summary, "median") == f"< {summary['median_bound']:.3f}"
    assert bounded_text(summary, "p95") == "0.520"
    quiet = error_summary(np.zeros(20), resolution=np.full(20, 0.12))
    assert bounded_text(quiet, "median") == "< 0.120" == bounded_text(quiet, "p95")
    assert quiet["likely_bad"] == quiet["possibly_bad"] == 0.0


def test_the_estimate_and_its_resolution_ride_on_the_field():
    field = DisplacementField.zeros((0, 0, 0), (5, 5, 5), (1, 2, 2))
    estimate = np.array([[[0.1, np.nan], [0.3, 0.4]]])
    resolution = np.array([[[0.05, 0.2], [np.inf, 0.1]]])
    assert estimate_of(field) is None and resolution_of(field) is None
    attach_estimate(field, estimate, resolution, background_residual=2.0)
    np.testing.assert_allclose(estimate_of(field), estimate, equal_nan=True)
    expected = np.where(np.isfinite(resolution), resolution, np.nan)  # no texture: undefined
    np.testing.assert_allclose(resolution_of(field), expected, equal_nan=True)
    import json

    json.dumps(field.metadata, allow_nan=False)  # JSON-ready as it is
    with pytest.raises(ValueError, match="resolution .* is not on the field's grid"):
        attach_estimate(field, estimate, resolution[..., :1])


def test_the_noise_of_the_match_sets_the_level_below_the_resolution():
    """An exact field measured by a match with noise uncertainty 0.04 voxel per component: the
    residual resolves nothing, the estimate is the match's noise error (0.04 √3)."""
    moments, r0 = _window_moments((0.0, 0.0, 0.0))
    field = DisplacementField.zeros((0, 0, 0), (5, 5, 5), (1, 1, 1))
    field = field.replace(uncertainty=np.full((1, 1, 1, 3), 0.04))
    estimate, resolution = error_estimate(field, moments, r0)
    assert estimate[0, 0, 0] == pytest.approx(0.04 * np.sqrt(3), rel=0.25)
    assert resolution[0, 0, 0] > 0


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
    with 3 % noise: the band's nodes are flagged and ranked, no node of the exact field and
    almost none truly under 0.25 voxel is, the uniform error is measured within 30 %, and the
    estimate does not depend on the gray-level map (fitted or not)
    (benchmarks/bench_error_estimate.py measures more)."""
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
    raw = evaluate_fields(reference, deformed, fields, keep_volumes=False, gray_levels=False)
    r = np.hypot(points[:, 1] - 27.5, points[:, 2] - 27.5).reshape(base.shape)
    inside = r < 0.46 * SHAPE[1] - 5  # the specimen (a cylinder in air)
    truth = {k: np.linalg.norm(e, axis=1).reshape(base.shape)[inside] for k, e in errors.items()}
    estimate = {item.name: item.error_estimate[inside] for item in result.fields}
    assert np.all(estimate["exact"] < 0.5)
    assert np.median(estimate["exact"]) < 0.05
    bad = truth["band"] > 0.5
    assert bad.sum() > 20 and np.mean(estimate["band"][bad] > 0.5) >= 0.8
    assert np.mean(estimate["band"][truth["band"] < 0.25] > 0.5) <= 0.02
    assert spearmanr(estimate["band"], truth["band"]).statistic >= 0.8
    assert 0.7 < np.median(estimate["uniform"]) / 0.3 < 1.3
    # nodes far from the band (truly under 0.05 voxel): mostly below the resolution (a bound)
    far = truth["band"] < 0.05
    resolution = result["band"].error_resolution[inside]
    assert far.sum() > 20 and np.mean(~(estimate["band"][far] > resolution[far])) > 0.5
    plain = raw["uniform"].error_estimate[inside]
    assert np.median(plain) == pytest.approx(np.median(estimate["uniform"]), rel=0.1)


def test_independent_node_errors_are_read_at_the_node_not_through_the_window(ct_pair):
    """Random node errors (0.6 voxel rms, independent from node to node): the densified field
    between nodes averages them, so a window of one grid step holds about a third of each
    node's error (the residual's part follows that window mean within 25 %). The estimate reads
    the node's own error through the node's departure from its neighbourhood: its median
    within 0.8-1.4 of the truth's and ranked (measured: 1.04, Spearman 0.65)."""
    from scipy.stats import spearmanr

    from napari_dvc_correct.engine.evaluation.error_estimate import error_region_half
    from napari_dvc_correct.engine.fields.field_spline import densify

    reference, deformed, base, exact = ct_pair
    errors = np.random.default_rng(4).normal(0.0, 0.6 / np.sqrt(3), exact.shape)
    field = base.replace(u=(exact + errors).reshape((*base.shape, 3)))
    item = evaluate_fields(reference, deformed, {"random": field}, keep_volumes=False)["random"]
    half = error_region_half(base)
    dense = densify(base.replace(u=errors.reshape((*base.shape, 3))), shape=SHAPE, dtype=float)
    window = np.stack(
        [ndimage.uniform_filter(dense[..., c], 2 * half + 1, mode="nearest") for c in range(3)],
        axis=-1,
    )
    nodes = np.round(base.points).astype(int)
    windowed = np.linalg.norm(window[nodes[:, 0], nodes[:, 1], nodes[:, 2]], axis=1)
    r = np.hypot(base.points[:, 1] - 27.5, base.points[:, 2] - 27.5)
    inside = r < 0.46 * SHAPE[1] - 5
    truth = np.linalg.norm(errors, axis=1)[inside]
    windowed, estimate = windowed[inside], item.error_estimate.reshape(-1)[inside]
    assert 0.25 < np.median(windowed) / np.median(truth) < 0.42  # what the window holds: 0.33
    resolved = np.sqrt(np.maximum(estimate**2 - _roughness(field)[inside] ** 2, 0.0))
    assert np.median(resolved) == pytest.approx(np.median(windowed), rel=0.25)
    assert 0.8 < np.median(estimate) / np.median(truth) < 1.4
    assert spearmanr(estimate, truth).statistic >= 0.6


def _roughness(field):
    from napari_dvc_correct.engine.evaluation.node_roughness import node_roughness

    return node_roughness(field.u).reshape(-1)


def _inside(base):
    r = np.hypot(base.points[:, 1] - 27.5, base.points[:, 2] - 27.5).reshape(base.shape)
    return r < 0.46 * SHAPE[1] - 5  # the specimen (a cylinder in air)


def test_exact_and_uniform_errors_read_their_known_answers(ct_pair):
    """The exact field reads about 0, within its stated resolution; fields off by a uniform
    0.3 and 1.0 voxel read 0.3 and 1.0 within 20 % (median over the specimen's nodes)."""
    reference, deformed, base, exact = ct_pair
    n = len(base.points)
    errors = {
        "exact": np.zeros((n, 3)),
        "0.3": np.tile([0.3, 0.0, 0.0], (n, 1)),
        "1.0": np.tile([0.0, 0.6, 0.8], (n, 1)),
    }
    fields = {k: base.replace(u=(exact + e).reshape((*base.shape, 3))) for k, e in errors.items()}
    result = evaluate_fields(reference, deformed, fields, keep_volumes=False)
    inside = _inside(base)
    zero = result["exact"]
    below = ~(zero.error_estimate[inside] > zero.error_resolution[inside])
    assert np.mean(below) >= 0.8 and np.median(zero.error_estimate[inside]) == 0.0
    ratio = zero.error_estimate[inside] / zero.error_resolution[inside]
    ratio = zero.error_estimate[inside] / zero.error_resolution[inside]
    assert np.mean(ratio <= 1.5) >= 0.95 and np.all(ratio < 2.5)  # 1.7 % above 1.5, max 2.1
    assert 0.05 < np.median(zero.error_resolution[inside]) < 0.2  # 3 % noise, 11³ windows
    for name, value in (("0.3", 0.3), ("1.0", 1.0)):
        assert np.median(result[name].error_estimate[inside]) == pytest.approx(value, rel=0.2)


def test_a_held_out_band_on_trilinear_warped_ct_is_ranked_and_caught():
    """Held out from the choice of the estimator: another CT texture and seed, 4 % noise, the
    deformed scan made by trilinear interpolation (not our B-spline), a 1-voxel band plus
    0.05-voxel random node errors. The issue's lines: rank correlation ≥ 0.6, ≥ 80 % of the
    nodes truly > 0.5 voxel likely above it, the median within a factor 2 of the truth's; and
    almost no node truly under 0.25 voxel flagged likely (measured: 98 % caught, 2 of 163 nodes
    under 0.25 flagged, Spearman 0.85, median ratio 1.01). And random 0.2-voxel node errors
    on the same pair, read at the node (measured: median ratio 1.19, Spearman 0.55)."""
    from scipy.stats import spearmanr

    from napari_dvc_correct.engine.evaluation.error_estimate import LIKELY, probability_above

    shift = np.array([1.3, -0.7, 2.2])
    margin = 6
    big = concrete_ct_volume(tuple(n + 2 * margin for n in SHAPE), aggregate_fraction=0.3, seed=17)
    grid = np.indices(big.shape, dtype=np.float64) - shift.reshape(3, 1, 1, 1)
    moved = ndimage.map_coordinates(big.astype(np.float64), grid, order=1, mode="mirror")
    crop = tuple(slice(margin, margin + n) for n in SHAPE)
    reference = np.ascontiguousarray(big[crop], np.float32)
    deformed = np.ascontiguousarray(moved[crop], np.float32)
    sigma = ct_noise_sigma(reference, 0.04)
    reference, deformed = add_noise(reference, sigma, seed=3), add_noise(deformed, sigma, seed=4)
    origin, step, shape = grid_for_volume(SHAPE, 15, 5)
    base = DisplacementField.zeros(origin, step, shape, params={"subvolume": 15})
    points = base.points
    d = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
    error = np.exp(-0.5 * ((points[:, 2] - 28.0) / (12.0 / 2.355)) ** 2)[:, None] * d
    error += np.random.default_rng(6).normal(0.0, 0.05 / np.sqrt(3), error.shape)
    field = base.replace(u=(shift + error).reshape((*shape, 3)))
    random = np.random.default_rng(7).normal(0.0, 0.2 / np.sqrt(3), error.shape)
    noisy = base.replace(u=(shift + random).reshape((*shape, 3)))
    result = evaluate_fields(
        reference, deformed, {"band": field, "random": noisy}, keep_volumes=False
    )
    item = result["band"]
    inside = _inside(base)
    truth = np.linalg.norm(error, axis=1).reshape(shape)[inside]
    estimate, resolution = item.error_estimate[inside], item.error_resolution[inside]
    likely = probability_above(estimate, resolution) >= LIKELY
    bad = truth > 0.5
    assert bad.sum() > 20 and np.mean(likely[bad]) >= 0.8
    assert (truth < 0.25).sum() > 100 and np.mean(likely[truth < 0.25]) <= 0.03
    assert spearmanr(estimate, truth).statistic >= 0.6
    assert 0.5 < np.median(estimate) / np.median(truth) < 2.0
    # 0.2-voxel errors independent from node to node, below the window's resolution: read at
    # the node from the field's shape (before: 0.00 of the truth at the median)
    truth = np.linalg.norm(random, axis=1).reshape(shape)[inside]
    estimate = result["random"].error_estimate[inside]
    assert 0.8 < np.median(estimate) / np.median(truth) < 1.5
    assert spearmanr(estimate, truth).statistic >= 0.45
    assert np.mean(probability_above(estimate, resolution) >= LIKELY) <= 0.02


def test_a_corrected_field_reads_its_true_error_as_the_plain_one_does():
    """Our DVC's field and the same field self-corrected, on faint CT texture with 3 % noise and
    an affine field (benchmarks/bench_error_estimate.py's first pair). A correcting match
    re-measures a node on the same images with the same subvolume: a corrected node's error is
    no larger than the plain match's, nor is the noise its record must carry (not √2 × it, as if
    the two matches' noises were independent). The estimate adds that record where the residual
    cannot resolve the error, so it reads the corrected field's median as it reads the plain
    one's (1.09 here; 1.48 with the quadrature record)."""
    from napari_dvc_correct.engine.correction.self_correction import correct
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams
    from napari_dvc_correct.engine.evaluation.error_estimate import noise_error
    from napari_dvc_correct.engine.synthetic import affine

    shape = (64, 64, 64)
    gradient = np.array([[-0.01, 0.004, 0.0], [0.0, 0.006, 0.003], [0.002, 0.0, 0.008]])
    truth = affine(gradient, center=np.array(shape) / 2.0, shift=(1.3, -0.7, 2.2))
    pattern = lambda s: concrete_ct_volume(s, aggregate_fraction=0.4, seed=3)  # noqa: E731
    reference, deformed = make_pair(pattern, shape, truth, 12)
    sigma = ct_noise_sigma(reference, 0.03)
    reference, deformed = add_noise(reference, sigma, seed=11), add_noise(deformed, sigma, seed=12)
    params = CorrelationParams(subvolume=15, step=5)
    plain = correlate(reference, deformed, params)
    # 5 % of the nodes 0.6 voxel off (refilled by the cleaning, then the pass re-measures): on
    # the plain field itself the one pass would raise the mean residual and is refused
    wrong = plain.copy()
    flat = wrong.u.reshape(-1, 3)
    flat[np.random.default_rng(5).choice(len(flat), len(flat) // 20, replace=False)] += (0, 0.6, 0)
    corrected = correct(reference, deformed, wrong, params)
    passes = corrected.metadata["correction_passes"]
    assert any(p["accepted_nodes"] > 0 for p in passes[1:])  # the case is met: a pass applied
    result = evaluate_fields(
        reference, deformed, {"plain": plain, "corrected": corrected}, keep_volumes=False
    )
    points = plain.points
    inside = np.hypot(points[:, 1] - 31.5, points[:, 2] - 31.5) < 0.46 * 64 - 5  # the specimen
    exact = sample_displacement(truth, points)
    true = {
        item.name: np.linalg.norm(item.field.displacement - exact, axis=1)[inside]
        for item in result.fields
    }
    sigma_u = {name: noise_error(result[name].field).reshape(-1)[inside] for name in true}
    assert np.median(true["corrected"]) < 1.1 * np.median(true["plain"])
    assert np.median(sigma_u["corrected"]) < 1.15 * np.median(sigma_u["plain"])
    for name in ("plain", "corrected"):
        estimate = result[name].error_estimate.reshape(-1)[inside]
        ratio = np.median(estimate) / np.median(true[name])
        assert 0.6 < ratio < 1.35, (name, ratio)
