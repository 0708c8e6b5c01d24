"""Whole-pipeline correlation tests against known displacement fields (issue 2's targets)."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import correlate, correlate_iter
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.progress import Progress, run_to_completion


def _errors(field, displacement):
    truth = synthetic.sample_displacement(displacement, field.points).reshape(field.u.shape)
    return field.u - truth


@pytest.fixture(scope="module")
def speckle():
    return synthetic.textured_volume((72, 72, 72), feature_size=2.0, seed=5)


def test_subvoxel_translation_bias_and_spread_31(speckle):
    shift = (2.3, -1.45, 0.7)
    deformed = synthetic.deform_volume(speckle, synthetic.translation(shift))
    field = correlate(speckle, deformed, CorrelationParams(subvolume=31, step=6))
    good = field.status == Status.CONVERGED
    assert good.mean() > 0.9
    err = _errors(field, synthetic.translation(shift))[good]
    assert np.all(np.abs(err.mean(axis=0)) < 0.005), err.mean(axis=0)
    assert np.all(err.std(axis=0) < 0.01), err.std(axis=0)


def test_noisy_translation_rmse_21(speckle):
    shift = (-0.4, 1.6, 0.25)
    deformed = synthetic.deform_volume(speckle, synthetic.translation(shift))
    # 5% noise: sigma is 5% of the speckle's gray-level range (1st to 99th percentile)
    low, high = np.percentile(speckle, [1, 99])
    sigma = 0.05 * float(high - low)
    reference = synthetic.add_noise(speckle, sigma, seed=1)
    deformed = synthetic.add_noise(deformed, sigma, seed=2)
    field = correlate(reference, deformed, CorrelationParams(subvolume=21, step=8))
    good = field.status == Status.CONVERGED
    assert good.mean() > 0.9
    rmse = np.sqrt(np.mean(_errors(field, synthetic.translation(shift))[good] ** 2))
    assert rmse < 0.02, rmse


def test_homogeneous_strain_and_shear(speckle):
    gradient = np.array([[0.03, 0.0, 0.01], [0.0, -0.015, 0.0], [0.0, 0.0, 0.02]])
    truth = synthetic.affine(gradient, np.array(speckle.shape) / 2, shift=(0.5, 1.2, -0.8))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=5), speckle.shape, truth
    )
    field = correlate(reference, deformed, CorrelationParams(subvolume=21, step=8))
    good = field.status == Status.CONVERGED
    assert good.mean() > 0.85
    err = _errors(field, truth)[good]
    assert np.sqrt(np.mean(err**2)) < 0.02
    assert np.max(np.abs(field.gradient[good] - gradient)) < 1e-3


@pytest.mark.slow
def test_large_shift_and_rotation_without_seed():
    reference = synthetic.textured_volume((96, 112, 112), feature_size=2.0, seed=8)
    shift = (10.0, -13.0, 18.0)  # |shift| ~ 24.3 voxels
    truth = synthetic.rotation_z(5.0, np.array(reference.shape) / 2, shift)
    deformed = synthetic.deform_volume(reference, truth)
    params = CorrelationParams(subvolume=21, step=10)
    field = correlate(reference, deformed, params)
    # judge the POIs whose whole deformed subvolume is inside the deformed volume
    moved = field.points + synthetic.sample_displacement(truth, field.points)
    half = params.half + 2
    inside = np.all((moved >= half) & (moved <= np.array(reference.shape) - 1 - half), axis=1)
    err = np.linalg.norm(_errors(field, truth).reshape(-1, 3), axis=1)[inside]
    assert inside.sum() > 100
    assert np.mean(err < 0.1) >= 0.95, np.mean(err < 0.1)


def test_noise_region_is_not_a_confident_wrong_answer(speckle):
    rng = np.random.default_rng(4)
    deformed = synthetic.deform_volume(speckle, synthetic.translation((0.5, 0.5, 0.5)))
    deformed[:, :, 40:] = rng.random(deformed[:, :, 40:].shape)  # decorrelated half
    reference = speckle.copy()
    reference[:, :, :12] = 0.5  # flat strip
    field = correlate(reference, deformed, CorrelationParams(subvolume=15, step=8))
    x = field.axis_coordinates()[2]
    decorrelated = x - 7 > 41
    flat = x + 7 < 12
    assert np.all(field.status[:, :, flat] == Status.LOW_TEXTURE)
    confident = (field.status == Status.CONVERGED) & (field.zncc >= 0.5)
    assert not confident[:, :, decorrelated].any()
    assert np.all(np.isnan(field.u[:, :, flat]))
    good = (x - 7 >= 12) & (x + 7 < 39)  # subvolumes that touch neither region
    assert (field.status[:, :, good] == Status.CONVERGED).mean() > 0.9


def test_generator_yields_progress_and_matches_blocking(speckle):
    deformed = synthetic.deform_volume(speckle, synthetic.translation((1.0, 0.0, -0.5)))
    params = CorrelationParams(subvolume=15, step=12, batch_size=8)
    generator = correlate_iter(speckle, deformed, params)
    reports = []
    while True:
        try:
            reports.append(next(generator))
        except StopIteration as stop:
            field = stop.value
            break
    assert all(isinstance(r, Progress) for r in reports)
    assert sum(r.stage == "IC-GN" for r in reports) >= 2
    assert np.allclose(field.u, correlate(speckle, deformed, params).u, equal_nan=True)


def test_given_prefilter_gives_the_same_field_and_must_fit(speckle):
    from napari_dvc_correct.engine.correlation.icgn_reference import gradient_volume
    from napari_dvc_correct.engine.correlation.interpolation import prefilter
    from napari_dvc_correct.engine.correlation.pyramid import Prefiltered
    from napari_dvc_correct.engine.progress import run_to_completion

    deformed = synthetic.deform_volume(speckle, synthetic.translation((0.6, -1.2, 0.3)))
    params = CorrelationParams(subvolume=15, step=12)
    plain = correlate(speckle, deformed, params)
    given = Prefiltered(
        gradient=gradient_volume(prefilter(speckle)), coef_deformed=prefilter(deformed)
    )
    field = run_to_completion(correlate_iter(speckle, deformed, params, prefiltered=given))
    np.testing.assert_array_equal(field.u, plain.u)
    np.testing.assert_array_equal(field.status, plain.status)
    with pytest.raises(ValueError, match="do not fit"):
        run_to_completion(
            correlate_iter(
                speckle,
                deformed,
                params,
                prefiltered=Prefiltered(coef_deformed=prefilter(speckle[:-1])),
            )
        )


def test_mask_skips_pois_outside_material(speckle):
    deformed = synthetic.deform_volume(speckle, synthetic.translation((0.3, 0.0, 0.0)))
    mask = np.zeros(speckle.shape, bool)
    mask[:, :, :36] = True
    field = correlate(speckle, deformed, CorrelationParams(subvolume=15, step=10), mask=mask)
    x = field.axis_coordinates()[2]
    assert np.all(field.status[:, :, x > 36 + 7] == Status.MASKED)
    assert np.all(np.isnan(field.u[:, :, x > 36 + 7]))
    assert (field.status[:, :, x < 36 - 7] == Status.CONVERGED).all()


@pytest.mark.parametrize(
    ("reference", "deformed", "params", "mask", "message"),
    [
        (np.zeros((10, 10)), np.zeros((10, 10)), {}, None, "3-D"),
        (np.zeros((20, 20, 20)), np.zeros((20, 20, 21)), {}, None, "same shape"),
        (np.full((20, 20, 20), np.nan), np.zeros((20, 20, 20)), {}, None, "NaN"),
        (np.zeros((20, 20, 20)), np.zeros((20, 20, 20)), {"subvolume": 31}, None, "larger"),
        (np.zeros((40,) * 3), np.zeros((40,) * 3), {"subvolume": 11}, np.zeros((40,) * 3), "empty"),
        (np.zeros((40,) * 3), np.zeros((40,) * 3), {"subvolume": 11}, np.ones((4, 4, 4)), "mask"),
        (np.zeros((20,) * 3, complex), np.zeros((20,) * 3), {}, None, "real"),
    ],
)
def test_bad_input_is_a_clear_error(reference, deformed, params, mask, message):
    with pytest.raises(ValueError, match=message):
        correlate(reference, deformed, CorrelationParams(**params), mask=mask)


@pytest.mark.parametrize(
    "changes", [{"subvolume": 20}, {"step": 0}, {"order": 3}, {"tolerance": -1.0}]
)
def test_bad_parameters_are_clear_errors(changes):
    with pytest.raises(ValueError):
        CorrelationParams(**changes)


def test_second_order_shape_function_follows_a_bending_field():
    center = np.array([32.0, 32.0, 32.0])

    def bending(points):
        r = (np.asarray(points) - center) / 16.0
        return np.stack([1.2 * r[:, 2] ** 2, 0.5 * r[:, 0] * r[:, 1], -0.8 * r[:, 1] ** 2], axis=1)

    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=9), (64, 64, 64), bending
    )
    rmse = {}
    for order in (1, 2):
        field = correlate(
            reference, deformed, CorrelationParams(subvolume=25, step=10, order=order)
        )
        good = field.status == Status.CONVERGED
        assert good.mean() > 0.9
        rmse[order] = np.sqrt(np.mean(_errors(field, bending)[good] ** 2))
    assert rmse[2] < 0.01
    assert rmse[2] < 0.5 * rmse[1]


# --- noise-aware thresholds and honest flags (issue 10) ---------------------------------------
def test_noise_aware_threshold_keeps_a_noisy_weak_texture_field():
    truth = synthetic.translation((0.3, -0.4, 0.6))
    reference, deformed, sigma = synthetic.noisy_ct_pair((64, 64, 64), truth, noise=0.07, seed=5)
    field = correlate(reference, deformed, CorrelationParams(subvolume=21, step=8))
    noise = field.metadata["noise"]
    assert abs(noise["sigma"] - sigma) < 0.15 * sigma  # estimated from the scans alone
    matched = np.isin(field.status, [Status.CONVERGED, Status.MAX_ITERATIONS, Status.LOW_ZNCC])
    assert matched.all()
    # a fixed threshold of 0.5 would reject a large part of this (good) field ...
    assert (field.zncc < 0.5).mean() > 0.2
    # ... the threshold at this noise level rejects almost none of it
    assert (field.status == Status.LOW_ZNCC).mean() < 0.03
    assert 0.15 < noise["zncc_threshold_median"] < 0.4
    assert np.sqrt(np.mean(_errors(field, truth) ** 2)) < 0.15


def test_clean_scans_keep_the_plain_threshold(speckle):
    deformed = synthetic.deform_volume(speckle, synthetic.translation((0.5, 0.2, -0.3)))
    field = correlate(speckle, deformed, CorrelationParams(subvolume=15, step=12))
    assert field.metadata["noise"]["zncc_threshold_min"] > 0.499
    assert field.metadata["noise"]["sigma"] < 1e-3


def test_noise_against_noise_is_low_texture_not_a_match():
    # half of the field of view is background: the same dark gray plus independent noise in each
    # scan; with a threshold that follows the noise, such POIs must not pass as matches
    truth = synthetic.translation((0.3, -0.4, 0.6))
    reference, deformed, sigma = synthetic.noisy_ct_pair((48, 48, 64), truth, noise=0.06, seed=6)
    rng = np.random.default_rng(8)
    for volume in (reference, deformed):
        volume[:, :, 40:] = 0.1 + rng.normal(0.0, sigma, volume[:, :, 40:].shape)
    field = correlate(reference, deformed, CorrelationParams(subvolume=15, step=8))
    x = field.axis_coordinates()[2]
    background = x - 7 >= 40
    specimen = x + 7 < 40
    assert background.any() and specimen.any()
    good = np.isin(field.status, [Status.CONVERGED, Status.MAX_ITERATIONS])
    assert not good[:, :, background].any()
    assert good[:, :, specimen].mean() > 0.9


def test_fault_case_wrong_matches_do_not_keep_a_good_status_unless_unsure():
    from scipy import ndimage

    rng = np.random.default_rng(0)
    volume = ndimage.gaussian_filter(rng.standard_normal((64, 64, 64)), 1.5)
    volume = (20 + 200 * (volume - volume.min()) / np.ptp(volume)).astype(np.float32)
    shift = (1.25, -0.6, 2.4)
    deformed = synthetic.deform_volume(volume, synthetic.translation(shift))
    reference = volume.copy()
    reference[:13] = 0.0  # a region the reference lacks
    field = correlate(reference, deformed, CorrelationParams(subvolume=15, step=4))
    error = np.linalg.norm(field.u - np.array(shift), axis=-1)
    good = np.isin(field.status, [Status.CONVERGED, Status.MAX_ITERATIONS])
    z = field.axis_coordinates()[0]
    away = z - 7 >= 13
    assert np.all(good[away]) and np.all(error[away] < 0.05)
    # without the uncertainty bound 4 nodes that straddle the slab kept a good status while
    # 2-8 voxels off (uncertainties 0.24-2.6 voxels, 1e-4 elsewhere)
    assert not (good & (error > 0.5)).any()
    assert field.metadata["noise"]["uncertainty_bound"] == pytest.approx(0.1)
    assert np.all(np.isnan(field.measured_displacement.reshape(*field.shape, 3)[~good]))


def test_an_integer_deformed_volume_is_read_as_it_is_with_the_float32_copys_field(monkeypatch):
    """match_iter keeps a large 16-bit pair uncopied (memory, issue 30): same field."""
    from napari_dvc_correct.engine.correlation import correlate as correlate_module

    monkeypatch.setattr(correlate_module, "KEEP_INTEGER_FROM", 0)
    from napari_dvc_correct.engine.correlation.initial_guess import bin_volume, pyramid_levels
    from napari_dvc_correct.engine.correlation.interpolation import prefilter

    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=7),
        (48, 48, 48),
        synthetic.translation((1.4, -7.2, 3.1)),
    )
    scale = 60000.0 / max(float(reference.max()), float(deformed.max()))
    reference = np.rint(reference * scale).astype(np.uint16)
    deformed = np.rint(deformed * scale).astype(np.uint16)
    np.testing.assert_array_equal(prefilter(deformed), prefilter(deformed.astype(np.float32)))
    np.testing.assert_array_equal(
        bin_volume(deformed, 2), bin_volume(deformed.astype(np.float32), 2)
    )
    params = CorrelationParams(subvolume=19, step=8, search_radius=12)
    assert pyramid_levels(12, 19, reference.shape) == 1  # binning and the global shift run
    as_is = correlate(reference, deformed, params)
    copied = correlate(reference.astype(np.float32), deformed.astype(np.float32), params)
    # both volumes are read as they are (no float32 copy of either)
    _, fine = run_to_completion(correlate_module.match_iter(reference, deformed, params))
    assert fine.reference.dtype == np.uint16 and np.shares_memory(fine.reference, reference)
    assert fine.deformed.dtype == np.uint16 and np.shares_memory(fine.deformed, deformed)
    assert np.isin(as_is.status, [0, 1]).mean() > 0.9
    for name in ("u", "status", "zncc", "iterations", "uncertainty"):
        np.testing.assert_array_equal(getattr(as_is, name), getattr(copied, name))


def test_the_blocking_form_takes_every_keyword_of_the_generator(speckle):
    import inspect

    keywords = set(inspect.signature(correlate_iter).parameters)
    assert keywords == set(inspect.signature(correlate).parameters)
    deformed = synthetic.deform_volume(speckle, synthetic.translation((0.5, -0.25, 0.75)))
    params = CorrelationParams(subvolume=21, step=16)
    whole = correlate(speckle, deformed, params)
    active = np.zeros(whole.shape, bool)
    active[0] = True
    part = correlate(speckle, deformed, params, active=active)
    assert np.all(part.status[~active] == Status.NOT_COMPUTED)
    assert np.all(np.isnan(part.u[~active]))
    good = active & (whole.status == Status.CONVERGED)
    assert good.any()
    np.testing.assert_allclose(part.u[good], whole.u[good], atol=0.02)


@pytest.mark.parametrize("seed", [5, 6])
def test_without_a_hint_a_spread_first_batch_hints_the_rest_and_changes_no_number(
    monkeypatch, seed
):
    """With no noise hint, the first IC-GN batch is every k-th POI of the grid and its median
    noise estimate tells the other batches which POIs get the sensitivity pass in IC-GN's call:
    the field equals the one with that pass left to the judge (hint 0), and the judge measures
    fewer POIs."""
    from napari_dvc_correct.engine.correlation import pyramid
    from napari_dvc_correct.engine.correlation.correlate import _noise_power
    from napari_dvc_correct.engine.correlation.noise import noise_estimates

    truth = synthetic.shear_band((24.0,) * 3, width=6.0, slip=2.0, shift=(0.5, -0.7, 1.2))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=seed), (48,) * 3, truth, margin=8
    )
    reference = synthetic.add_noise(reference, 0.03, seed=seed + 1)
    deformed = synthetic.add_noise(deformed, 0.03, seed=seed + 2)
    calls, measured = [], []
    match, statistics = pyramid.PyramidLevel.match, pyramid.PyramidLevel.statistics

    def recording_match(self, centers, warps, order, params, sigma=None, noise_power=0.0):
        result = match(self, centers, warps, order, params, sigma=sigma, noise_power=noise_power)
        if sigma is not None:
            calls.append((centers.copy(), result, noise_power))
        return result

    def counting(self, centers, *args):
        measured.append(len(centers))
        return statistics(self, centers, *args)

    monkeypatch.setattr(pyramid.PyramidLevel, "match", recording_match)
    monkeypatch.setattr(pyramid.PyramidLevel, "statistics", counting)
    params = CorrelationParams(subvolume=15, step=6, batch_size=40)
    hinted = correlate(reference, deformed, params)
    hinted_calls, hinted_measured = calls[:], measured[:]
    calls.clear()
    measured.clear()
    judged = correlate(reference, deformed, params, noise_hint=0.0)
    for name in ("u", "zncc", "status", "iterations", "uncertainty", "gradient"):
        np.testing.assert_array_equal(getattr(hinted, name), getattr(judged, name), err_msg=name)
    assert np.isfinite(hinted.uncertainty).any()
    # the first batch: at most one batch, spread over the whole grid's depth; no hint yet
    centers, (zncc, status, _), power = hinted_calls[0]
    assert len(centers) <= 40 and power == 0.0
    assert np.ptp(centers[:, 0]) >= 0.8 * np.ptp(hinted.points.reshape(-1, 3)[:, 0])
    # the others: the judge's rule at the first batch's median noise estimate
    level = pyramid.PyramidLevel.build(1, reference, deformed, None, 7, params.min_texture)
    variance, gradient_power = np.full(len(centers), np.nan), np.full(len(centers), np.nan)
    level.moments(centers, 1, (variance, gradient_power), slice(None))
    expected = _noise_power(np.median(noise_estimates(variance, zncc, status)))
    assert expected > 0 and all(call[2] == expected for call in hinted_calls[1:])
    assert all(call[2] == 0.0 for call in calls)  # hint 0: none expected noisy
    assert sum(hinted_measured) < sum(measured)


@pytest.mark.parametrize(("order", "window"), [(1, None), (2, None), (2, 4.0)])
def test_a_large_volumes_gradient_on_demand_gives_the_same_field_to_the_last_bit(
    monkeypatch, order, window
):
    """From :data:`.pyramid.GRADIENT_ON_DEMAND_FROM` voxels the fine level keeps ``G``'s
    coefficients instead of ``∇G`` (a third of the memory); every kernel then computes its
    subvolumes' gradient: the field is the same bit for bit (noisy POIs, masked voxels, a
    region the reference lacks that fails and is repaired), weighted subvolumes included."""
    from scipy import ndimage

    from napari_dvc_correct.engine.correlation import pyramid
    from napari_dvc_correct.engine.correlation.correlate import match_iter

    rng = np.random.default_rng(1)
    volume = ndimage.gaussian_filter(rng.standard_normal((52, 48, 44)), 1.5)
    volume = (20 + 200 * (volume - volume.min()) / np.ptp(volume)).astype(np.float32)
    truth = synthetic.shear_band((26.0, 24.0, 22.0), width=6.0, slip=1.5, shift=(0.6, -1.3, 0.4))
    deformed = synthetic.add_noise(synthetic.deform_volume(volume, truth), 1.5, seed=2)
    reference = volume.copy()
    reference[:9] = 0.0  # a region the reference lacks: failed matches and their repair
    mask = np.ones(reference.shape, bool)
    mask[:, :, 28:] = False
    params = CorrelationParams(
        subvolume=13 if order == 1 else 15, step=5, order=order, window=window
    )
    fields = []
    for threshold in (2**40, 0):
        monkeypatch.setattr(pyramid, "GRADIENT_ON_DEMAND_FROM", threshold)
        _, fine = run_to_completion(match_iter(reference, deformed, params, mask=mask))
        assert fine.gradient.shape[0] == (3 if threshold else 1)
        fields.append(correlate(reference, deformed, params, mask=mask))
    stored, on_demand = fields
    statuses = set(np.unique(stored.status).tolist())
    assert {int(Status.CONVERGED), int(Status.MASKED)} <= statuses and len(statuses) >= 3
    assert np.isfinite(stored.uncertainty).any()
    for name in ("u", "status", "zncc", "iterations", "uncertainty", "gradient"):
        np.testing.assert_array_equal(getattr(stored, name), getattr(on_demand, name), name)
