"""The decision rules of engine/correction/acceptance.py on small fields with known answers."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correction.acceptance import (
    MEASURED_REACH,
    NOISE_Z,
    Judge,
    mix_fields,
    unsupported_updates,
)
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status


def _delta(shape=(4, 5, 6), origin=(10.0, 10.0, 10.0), step=(5.0, 5.0, 5.0)):
    return DisplacementField.zeros(origin, step, shape)


def test_updates_read_within_one_step_of_the_measured_nodes_are_supported():
    delta = _delta()
    lo = np.array(delta.origin)
    hi = lo + (np.array(delta.shape) - 1) * np.array(delta.step)
    inside = np.array([lo, hi, (lo + hi) / 2])
    reach = MEASURED_REACH * 5.0
    # just inside the reach on each side, along one axis at a time
    edge = np.array(
        [lo - [reach - 0.01, 0, 0], hi + [0, reach - 0.01, 0], hi + [0, 0, reach - 0.01]]
    )
    beyond = np.array(
        [lo - [reach + 0.01, 0, 0], hi + [0, reach + 0.01, 0], lo - [0, 0, 2 * reach]]
    )
    refused = unsupported_updates(delta, np.concatenate([inside, edge, beyond]))
    assert refused.tolist() == [False] * 6 + [True] * 3


def test_the_reach_counts_from_the_good_measured_nodes_only():
    delta = _delta()
    hi_x = delta.origin[2] + (delta.shape[2] - 1) * delta.step[2]  # 35
    # the two outermost x-layers failed (cleaning refilled them): the measured box ends at x = 25
    delta.status[:, :, -2:] = Status.OUT_OF_BOUNDS
    delta.provenance[:, :, -1] = Provenance.REPLACED
    points = np.array([[15.0, 15.0, 25.0 + 4.9], [15.0, 15.0, 25.0 + 5.1], [15.0, 15.0, hi_x]])
    assert unsupported_updates(delta, points).tolist() == [False, True, True]
    # non-finite read points (a node sent nowhere) are refused; no good node: all refused
    assert unsupported_updates(delta, np.array([[np.nan, 15.0, 15.0]])).tolist() == [True]
    delta.status[:] = Status.DIVERGED
    assert unsupported_updates(delta, points).all()


def test_a_correction_is_applied_in_proportion_to_its_support_above_the_noise():
    from napari_dvc_correct.engine.correction.acceptance import SUPPORT_Z, shrink_to_support

    current = _delta(shape=(1, 1, 4))
    candidate = current.copy()
    candidate.u[0, 0, :, 0] = 0.3  # every node corrected by 0.3 voxel along z
    # its match's uncertainty: none known, tiny, comparable, larger than the correction
    sigma = np.array([[[np.nan, 0.003, 0.3 / SUPPORT_Z / 2.0, 0.3 / SUPPORT_Z * 1.5]]])
    shrunk, unsupported = shrink_to_support(current, candidate, sigma)
    applied = shrunk.u[0, 0, :, 0]
    assert applied[0] == 0.3  # unknown uncertainty: the correction whole
    assert applied[1] == np.float64(0.3) * (1 - (SUPPORT_Z * 0.003 / 0.3) ** 2)
    assert np.isclose(applied[2], 0.3 * 0.75)  # half its size: three quarters of it
    assert applied[3] == 0.0  # the noise explains it: not applied, and refused
    assert unsupported.reshape(-1).tolist() == [False, False, False, True]
    assert np.all(shrunk.u[..., 1:] == 0.0)


def test_the_residuals_pull_a_field_back_once_and_the_correction_is_unchanged(monkeypatch):
    """The last pull-back is kept (the gray-level fit's is handed over): the same field judged
    again costs no warp, a changed field is pulled back anew, and the corrected field is the
    one computed with a pull-back for every residual, bit for bit."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correction import acceptance
    from napari_dvc_correct.engine.correction.self_correction import correct
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams
    from napari_dvc_correct.engine.fields import warp

    truth = synthetic.shear_band((20.0,) * 3, width=6.0, slip=3.0, shift=(0.5, -0.7, 1.2))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.two_phase_volume(s, seed=2), (40,) * 3, truth, margin=8
    )
    field = correlate(reference, deformed, CorrelationParams(subvolume=15, step=5))
    calls = []
    pull_back = warp.pull_back
    monkeypatch.setattr(warp, "pull_back", lambda *a, **k: calls.append(1) or pull_back(*a, **k))
    kept = correct(reference, deformed, field, max_passes=2)
    n_kept = len(calls)

    residuals = acceptance.ReferenceResiduals(
        reference.astype(np.float32), deformed.astype(np.float32),
        prefilter_of(deformed),
    )  # fmt: skip
    calls.clear()
    first = residuals.moved(field)
    again = residuals.moved(field)
    np.testing.assert_array_equal(first, again)
    assert len(calls) == 1
    moved_field = field.copy()
    moved_field.u[0, 0, 0, 0] += 0.5
    residuals.moved(moved_field)
    assert len(calls) == 2

    def always(self, field):
        spline = acceptance.FieldSpline.from_field(field)
        return warp.pull_back(self.deformed, spline, coefficients=self.coefficients, cval=np.nan)

    monkeypatch.setattr(acceptance.ReferenceResiduals, "pulled_back", always)
    calls.clear()
    every = correct(reference, deformed, field, max_passes=2)
    assert n_kept < len(calls)
    for name in ("u", "zncc", "status", "provenance"):
        np.testing.assert_array_equal(getattr(kept, name), getattr(every, name), err_msg=name)
    for name in ("mean_gray_residual", "accepted_nodes", "improved_nodes", "noise_floor"):
        assert [p[name] for p in kept.metadata["correction_passes"]] == [
            p[name] for p in every.metadata["correction_passes"]
        ], name


def prefilter_of(volume):
    from napari_dvc_correct.engine.correlation.interpolation import prefilter

    return prefilter(np.asarray(volume, np.float32))


class _KnownResiduals:
    """A judge's volume access with known per-node numbers: cell residual means, the noise
    floor of eq. 1 and the mean gray gradient."""

    def __init__(self, local, floor, gradient):
        self.local, self.floor, self.gradient = local, floor, gradient

    def local_means(self, field, halves):
        return (self.local, self.local), self.floor

    def gradient_means(self, field, half):
        return np.full(self.local.shape, self.gradient)


def _judged(floor, excess, gradient=4.0):
    """Judge a 3 x 3 x 3 grid (step 6: 7³ cells) whose centre node's residual exceeds the floor
    by ``excess`` gray levels; the others sit on the floor. Returns (flagged centre, tolerance)."""
    field = DisplacementField.zeros((10.0,) * 3, (6.0,) * 3, (3, 3, 3))
    local = np.full(field.shape, floor)
    local[1, 1, 1] += excess
    judge = Judge(
        None, None, None, field.step, 10, residuals=_KnownResiduals(local, floor, gradient)
    )
    local = judge.local(field)
    return bool(judge.unexplained(field, local)[1, 1, 1]), judge.tolerance


def test_a_flag_needs_an_excess_above_both_a_voxel_s_error_and_the_noise_scatter():
    # a 7³ cell holds 343 / 8 independent noise samples: noise alone scatters its mean residual
    # by sqrt(2) sqrt(pi/2 - 1) / sqrt(343 / 8) = 0.163 of the floor; NOISE_Z = 2 of that
    spread = np.sqrt(2.0) * np.sqrt(np.pi / 2 - 1) / np.sqrt(343 / 8)
    # heavy noise (floor 30 gray levels): a 1-voxel error explains 0.5 x 4 = 2 gray levels, the
    # noise scatters the cell mean by up to 2 x 0.163 x 30 = 9.8
    flagged, tolerance = _judged(floor=30.0, excess=5.0)
    assert tolerance == pytest.approx(NOISE_Z * spread * 30.0, rel=1e-9)
    assert not flagged  # within the noise's scatter: no more wrong than the others
    assert _judged(floor=30.0, excess=2.0 + tolerance + 0.1)[0]
    assert not _judged(floor=30.0, excess=2.0 + tolerance - 0.1)[0]
    # clean scans (floor 1): the noise term is 0.33 and the voxel's error decides, as before
    assert _judged(floor=1.0, excess=2.5)[0]
    assert not _judged(floor=1.0, excess=1.9)[0]


def test_flags_count_from_the_cells_lower_quartile_where_eq_1_reads_below_it():
    # eq. 1 reads 5.1 gray levels while a right field leaves 7.4-8.6 in every cell (noise large
    # against the phases' contrast, docs/heldout.md): with a voxel's error worth 0.9 gray
    # levels, a cell at 7.9 stood 2.8 above the floor and was flagged; over the lower quartile
    # (7.7 here) it stands 0.2 above, within the noise, and only a cell far above the others is
    spread = np.sqrt(2.0) * np.sqrt(np.pi / 2 - 1) / np.sqrt(343 / 8)
    field = DisplacementField.zeros((10.0,) * 3, (6.0,) * 3, (4, 4, 4))
    local = np.linspace(7.4, 8.6, field.n_points).reshape(field.shape)
    local[1, 1, 1] = 7.7 + 0.9 + NOISE_Z * spread * 7.7 + 0.2  # just above the quartile's bar
    judge = Judge(None, None, None, field.step, 10, residuals=_KnownResiduals(local, 5.1, 1.8))
    local = judge.local(field)
    assert judge.floor == pytest.approx(5.1)  # the floor itself (the acceptance's) is unchanged
    quartile = float(np.percentile(local, 25.0))
    flagged = judge.unexplained(field, local)
    bar = quartile + 0.9 + NOISE_Z * spread * quartile
    assert np.array_equal(flagged, local > bar)
    assert flagged[1, 1, 1] and 0 < flagged.sum() <= 0.1 * field.n_points
    # the old bar (over eq. 1's floor) flagged three quarters of these right cells
    assert np.mean(local > 5.1 + 0.9 + NOISE_Z * spread * 5.1) > 0.7


def _noise_case(shape=(6, 6, 6), sigma=0.3, seed=0):
    """A measured field, a pass whose corrections are pure matching noise of uncertainty
    ``sigma`` (norm) at every node, and that uncertainty."""
    current = _delta(shape=shape)
    current.provenance[:] = Provenance.MEASURED
    candidate = current.copy()
    rng = np.random.default_rng(seed)
    candidate.u += rng.normal(0.0, sigma / np.sqrt(3.0), current.u.shape)
    return current, candidate, np.full(shape, sigma)


def test_a_region_whose_corrections_are_only_noise_keeps_its_values():
    from napari_dvc_correct.engine.correction.acceptance import noise_only_corrections

    current, candidate, sigma = _noise_case()
    flat = np.zeros(current.shape)
    refused = noise_only_corrections(current, candidate, sigma, flat)
    # the pooled energy of 27 noise corrections scatters around Σσ² by sqrt(2 / 81) of it: a
    # region stands NOISE_Z such spreads above it by chance in about 2 % of the draws
    assert refused.mean() > 0.9
    # the same nodes corrected by 3σ in a coherent patch: not noise, not refused there
    patch = (slice(1, 5), slice(1, 5), slice(1, 5))
    candidate.u[patch + (0,)] += 3.0 * sigma[patch]
    refused = noise_only_corrections(current, candidate, sigma, flat)
    assert not refused[patch].any()


def test_a_bend_above_the_noise_or_a_refilled_value_opens_a_noise_region():
    from napari_dvc_correct.engine.correction.acceptance import noise_only_corrections

    current, candidate, sigma = _noise_case()
    candidate.u = current.u.copy()  # no correction at all: Σ|c|² = 0 <= Σσ² everywhere
    bend = np.zeros(current.shape)
    bend[3, 3, 3] = 1.5 * sigma[3, 3, 3]  # a shape-function bias the noise lets a match see
    current.provenance[0, 0, 0] = Provenance.REPLACED  # a refilled value: no measurement yet
    current.status[0, 5, 0] = Status.LOW_ZNCC
    refused = noise_only_corrections(current, candidate, sigma, bend)
    near = np.zeros(current.shape, bool)
    near[2:5, 2:5, 2:5] = True  # the bent node and its 26 neighbours
    assert not refused[near].any()
    assert not refused[0, 0, 0] and not refused[0, 5, 0]
    others = ~near
    others[0, 0, 0] = others[0, 5, 0] = False
    assert refused[others].all()
    # an unknown uncertainty (an interpolated correcting match) is never judged here, nor is
    # any node where the bend is unknown
    sigma[5, 5, 5] = np.nan
    assert not noise_only_corrections(current, candidate, sigma, bend)[5, 5, 5]
    assert not noise_only_corrections(current, candidate, sigma, np.full(bend.shape, np.nan)).any()


def test_a_refused_node_keeps_its_own_uncertainty():
    current = DisplacementField.zeros((0.0, 0.0, 0.0), (5.0, 5.0, 5.0), (3, 3, 3))
    current.uncertainty = np.full((3, 3, 3, 3), 0.2)
    candidate = current.replace(u=current.u + 0.1, uncertainty=np.full((3, 3, 3, 3), 0.03))
    accept = np.zeros((3, 3, 3), bool)
    accept[0] = True
    mixed = mix_fields(current, candidate, accept)
    assert np.all(mixed.uncertainty[0] == 0.03) and np.all(mixed.uncertainty[1:] == 0.2)
    assert np.all(mixed.u[1:] == 0.0)


def _small_slabs(shape, voxels=None):
    """iter_slabs with 5-plane slabs: many slab borders in a small volume."""
    for start in range(0, int(shape[0]), 5):
        yield slice(start, min(int(shape[0]), start + 5))


@pytest.mark.parametrize("gray", ["identity", "global", "local", "flat"])
@pytest.mark.parametrize("slabs", ["default", "small"])
def test_residuals_made_slab_by_slab_equal_the_whole_volume_formulas(monkeypatch, gray, slabs):
    """local_means, signed_means and gradient_means read the pull-back, the gray-level map, the
    residual and the gradient slab by slab: the same numbers, to the bit, as the whole volumes
    they were computed from before (with 5-plane slabs too, every border of the gradient's
    reach crossed), from a 16-bit reference held as it is or as float32."""
    from scipy import ndimage

    from napari_dvc_correct.engine import slabs as slab_module
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correction import acceptance
    from napari_dvc_correct.engine.evaluation.gray_levels import GrayLevelMap, fit_gray_levels
    from napari_dvc_correct.engine.evaluation.local_accuracy import local_mean_residual
    from napari_dvc_correct.engine.evaluation.phase_sums import residual_phase_sums
    from napari_dvc_correct.engine.evaluation.phases import label_phases, phase_thresholds
    from napari_dvc_correct.engine.fields import warp

    if slabs == "small":
        monkeypatch.setattr(slab_module, "iter_slabs", _small_slabs)
        monkeypatch.setattr(acceptance, "iter_slabs", _small_slabs)
    shape = (33, 28, 30)
    texture = synthetic.two_phase_volume(shape, seed=6)
    reference = np.rint(1000.0 + 20000.0 * texture).astype(np.uint16)
    if gray == "flat":  # one gray value: no phases, no eq. 1
        reference[:] = 7000
    moved_true = synthetic.deform_volume(
        texture, synthetic.affine(np.diag([0.01, -0.02, 0.015]), (16.0, 14.0, 15.0), (0.4, 0, 0))
    )
    deformed = (900.0 + 18000.0 * moved_true).astype(np.float32)
    field = DisplacementField.zeros((4.0, 3.0, 5.0), (5.0, 6.0, 5.0), (6, 4, 5))
    rng = np.random.default_rng(1)
    field = field.replace(u=rng.normal(0.0, 0.4, field.u.shape))
    coefficients = prefilter_of(deformed)
    spline = acceptance.FieldSpline.from_field(field)
    pulled = warp.pull_back(deformed, spline, coefficients=coefficients, cval=np.nan)
    as_float = reference.astype(np.float32)
    maps = {
        "identity": GrayLevelMap.identity(shape),
        "flat": GrayLevelMap.identity(shape),
        "global": GrayLevelMap(contrast=1.07, offset=-31.5, volume_shape=shape),
        "local": fit_gray_levels(as_float, pulled, cell=8),
    }
    assert maps["local"].is_local or gray != "local"
    gray_map = maps[gray]
    halves = (2, 7)
    # before: the whole volumes
    moved = gray_map.apply(pulled)
    if gray == "flat":
        residual, floor = np.abs(moved - as_float), float("inf")
    else:
        thresholds = phase_thresholds(as_float, "auto", 2)
        sums = residual_phase_sums(as_float, moved, label_phases(as_float, thresholds), thresholds)
        residual, floor = sums.residual, sums.same_phase_mean
    local_before = [local_mean_residual(residual, field, h) for h in halves]
    signed_before = local_mean_residual(as_float - moved, field, 2)
    magnitude = ndimage.gaussian_gradient_magnitude(as_float, 1.0)
    gradient_before = [local_mean_residual(magnitude, field, h) for h in halves]
    for held in (reference, as_float):
        residuals = acceptance.ReferenceResiduals(held, deformed, coefficients, gray_map)
        assert residuals.reference is held  # no copy of a scan float32 holds exactly
        residuals.remember(field, pulled)
        local, r0 = residuals.local_means(field, halves)
        for new, old in zip(local, local_before, strict=True):
            np.testing.assert_array_equal(new, old)
        assert r0 == floor or (np.isinf(r0) and not np.isfinite(floor))
        np.testing.assert_array_equal(residuals.signed_means(field, 2), signed_before)
        np.testing.assert_array_equal(residuals.gradient_means(field, 7), gradient_before[1])
        np.testing.assert_array_equal(residuals.gradient_means(field, 2), gradient_before[0])
    # a float64 reference is read as its float32 copy
    residuals = acceptance.ReferenceResiduals(as_float.astype(np.float64), deformed, coefficients)
    assert residuals.reference.dtype == np.float32


def test_the_gradient_is_computed_once_per_grid_and_a_forgotten_pull_back_is_made_again(
    monkeypatch,
):
    from scipy import ndimage

    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correction import acceptance
    from napari_dvc_correct.engine.fields import warp

    reference = synthetic.textured_volume((20, 22, 24), feature_size=3.0, seed=2) * 100.0
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.3, 0.2, -0.4)))
    residuals = acceptance.ReferenceResiduals(
        reference.astype(np.float32), deformed, prefilter_of(deformed)
    )
    field = DisplacementField.zeros((3.0, 3.0, 3.0), (4.0, 4.0, 4.0), (4, 5, 5))
    other = DisplacementField.zeros((2.0, 3.0, 3.0), (4.0, 4.0, 4.0), (4, 5, 5))
    gradients, pulls = [], []
    magnitude = ndimage.gaussian_gradient_magnitude
    monkeypatch.setattr(
        acceptance.ndimage, "gaussian_gradient_magnitude",
        lambda *a, **k: gradients.append(1) or magnitude(*a, **k),
    )  # fmt: skip
    pull_back = warp.pull_back
    monkeypatch.setattr(warp, "pull_back", lambda *a, **k: pulls.append(1) or pull_back(*a, **k))
    residuals.local_means(field, (2, 5))
    first = residuals.gradient_means(field, 2)
    n = len(gradients)  # one slab here: one gradient for both halves of local_means
    assert n == 1
    np.testing.assert_array_equal(residuals.gradient_means(field, 5), residuals.gradient_means(
        field, 5))  # fmt: skip
    residuals.gradient_means(field, 2)
    assert len(gradients) == n  # kept per grid and half
    residuals.gradient_means(other, 2)
    assert len(gradients) == n + 1  # another grid: other nodes
    assert len(pulls) == 1
    held = residuals.pulled_back(field)
    residuals.forget()
    again = residuals.pulled_back(field)
    assert len(pulls) == 2 and again is not held
    np.testing.assert_array_equal(again, held)
    np.testing.assert_array_equal(first, residuals.gradient_means(field, 2))
