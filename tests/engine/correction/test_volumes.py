"""The self-correction's volume operations in memory, on a pair related by a known translation."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction import volumes as V
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.progress import run_to_completion

SHAPE = (32, 32, 32)
SHIFT = (1.5, -1.0, 0.5)


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume(SHAPE, feature_size=3.0, seed=4) * 100.0
    deformed = synthetic.deform_volume(reference, synthetic.translation(SHIFT))
    return reference, deformed


def _uniform(u) -> DisplacementField:
    zero = DisplacementField.zeros((4.0, 4.0, 4.0), (6.0, 6.0, 6.0), (5, 5, 5))
    return zero.replace(u=np.broadcast_to(u, zero.u.shape).copy())


@pytest.mark.parametrize("frame", ["reference", "loaded"])
def test_the_true_field_aligns_the_pair_and_a_wrong_one_does_not(pair, frame):
    reference, deformed = pair
    volumes = V.InMemoryVolumes(reference, deformed, frame)
    volumes.gray_levels = None  # raw gray levels
    moved, residual = run_to_completion(volumes.align(_uniform(SHIFT)))
    _, wrong = run_to_completion(volumes.align(_uniform((0.0, 0.0, 0.0))))
    assert moved.dtype == np.float32 and moved.shape == SHAPE and np.isfinite(moved).all()
    scale = float(np.std(reference))
    assert residual < 0.05 * scale < wrong  # the true field explains the pair
    g, f, mask = run_to_completion(volumes.matching_pair(moved, _uniform(SHIFT)))
    if frame == "reference":  # (G, F~): F pulled back onto G
        assert g is volumes.reference and f is moved
        inner = (slice(6, -6),) * 3
        assert np.abs(moved - reference)[inner].mean() < 0.05 * scale
    else:  # (G', F): G pushed forward onto F
        assert g is moved and f is volumes.deformed
    assert mask is None


def test_a_mask_travels_with_the_loaded_frame(pair):
    reference, deformed = pair
    mask = np.zeros(SHAPE, bool)
    mask[8:24, 8:24, 8:24] = True
    volumes = V.InMemoryVolumes(reference, deformed, "loaded", mask=mask)
    shift = (3.0, 0.0, 0.0)
    _, _, moved_mask = run_to_completion(volumes.matching_pair(None, _uniform(shift)))
    expected = np.zeros(SHAPE, bool)
    expected[11:27, 8:24, 8:24] = True  # the material moved 3 voxels along z
    np.testing.assert_array_equal(moved_mask, expected)


def test_the_warped_mask_reuses_the_aligned_fields_inverse_and_equals_a_fresh_warp(pair):
    from napari_dvc_correct.engine.fields import warp

    reference, deformed = pair
    rng = np.random.default_rng(0)
    mask = np.zeros(SHAPE, bool)
    mask[5:27, 7:25, 6:28] = True
    field = _uniform(SHIFT)
    field.u += rng.normal(0.0, 0.4, field.u.shape)  # a bent field: cells solved voxel by voxel
    expected = warp.warp_forward(mask, field, cval=0.0) > 0.5
    volumes = V.InMemoryVolumes(reference, deformed, "loaded", mask=mask)
    moved, _ = run_to_completion(volumes.align(field))
    assert volumes._inverse is not None  # kept for the mask
    moved_alone, _ = warp.warp_forward_with_residual(reference, deformed, field)
    moved_alone[~np.isfinite(moved_alone)] = volumes.fill
    np.testing.assert_array_equal(moved, moved_alone)  # the shared stage changes nothing
    _, _, warped = run_to_completion(volumes.matching_pair(moved, field))
    np.testing.assert_array_equal(warped, expected)
    assert volumes._inverse is None  # used once
    other = field.replace(u=field.u + 0.25)  # another field: its own inverse
    _, _, warped = run_to_completion(volumes.matching_pair(moved, other))
    np.testing.assert_array_equal(warped, warp.warp_forward(mask, other, cval=0.0) > 0.5)


def test_unfinite_voxels_take_the_fill_and_the_hull_mean_skips_them():
    volume = np.array([1.0, np.nan, np.inf, 4.0])
    np.testing.assert_array_equal(V._finite_or_fill(volume, 2.5), [1.0, 2.5, 2.5, 4.0])
    assert V._finite_or_fill(np.ones(3), 0.0).dtype == np.float32
    difference = np.array([[1.0, np.nan], [3.0, 5.0]])
    assert V._hull_mean(difference, (slice(0, 2), slice(0, 1))) == 2.0
    assert np.isnan(V._hull_mean(difference, (slice(0, 1), slice(1, 2))))


def test_the_gray_level_map_is_not_diluted_by_the_scans_noise():
    # an unchanged CT-like pair, noise of 5 % of the gray range on both scans, and the loaded
    # scan 0.85x darker: least squares would read the contrast ~10 % short
    shape, shift = (48, 48, 48), (0.4, -1.3, 0.25)
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.concrete_ct_volume(s, seed=8), shape, synthetic.translation(shift), 12
    )
    sigma = synthetic.ct_noise_sigma(reference, 0.05)
    reference = synthetic.add_noise(reference, sigma, seed=1)
    deformed = synthetic.add_noise(deformed, sigma, seed=2) * 0.85 + 0.1
    volumes = V.InMemoryVolumes(reference, deformed, "reference")
    zero = DisplacementField.zeros((6.0, 6.0, 6.0), (6.0, 6.0, 6.0), (7, 7, 7))
    gray = run_to_completion(volumes.fit_gray_levels(zero.replace(u=zero.u + np.array(shift))))
    assert gray.fit == "errors in variables" and volumes.gray_levels is gray
    assert 0.85 * gray.contrast == pytest.approx(1.0, abs=0.015)  # least squares: 0.966
    assert gray.noise.moved == pytest.approx(0.565 * (0.85 * sigma) ** 2, rel=0.1)


def test_the_correcting_runs_noise_hint_is_half_the_input_fields_noise_variance():
    from napari_dvc_correct.engine.correction.volumes import NOISE_HINT_FRACTION, noise_hint
    from napari_dvc_correct.engine.fields.field import DisplacementField

    field = DisplacementField.zeros((0.0, 0.0, 0.0), (4.0, 4.0, 4.0), (3, 3, 3))
    assert noise_hint(field) is None  # another program's field: no estimate, no hint
    field.metadata["noise"] = {"sigma": 2.0}
    assert noise_hint(field) == NOISE_HINT_FRACTION * 4.0 == 2.0
    field.metadata["noise"] = {"sigma": 0.0}
    assert noise_hint(field) is None


def test_the_aligned_volume_is_filled_in_place():
    made = np.array([1.0, np.nan, 3.0], np.float32)
    assert V._finite_or_fill(made, 2.0) is made
    np.testing.assert_array_equal(made, [1.0, 2.0, 3.0])


@pytest.fixture(scope="module")
def sheared_uint16_pair():
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    truth = synthetic.shear_band((20.0,) * 3, width=6.0, slip=3.0, shift=(0.5, -0.7, 1.2))
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.two_phase_volume(s, seed=2), (40,) * 3, truth, margin=8
    )
    rng = np.random.default_rng(3)
    reference, deformed = (
        np.rint(2000.0 + 200.0 * v + rng.normal(0.0, 150.0, v.shape)).astype(np.uint16)
        for v in (reference, deformed)
    )
    field = correlate(reference, deformed, CorrelationParams(subvolume=15, step=5))
    return reference, deformed, field


@pytest.mark.parametrize("frame", ["loaded", "reference"])
def test_integer_scans_are_held_as_they_are_and_correct_to_the_same_bits(
    monkeypatch, sheared_uint16_pair, frame
):
    """A 16-bit pair (large ones: the threshold is lowered here) is held without float32
    copies; the corrected field, its quality arrays and every pass's record equal those of the
    same scans given as float32 (the copies held before), bit for bit."""
    from napari_dvc_correct.engine.correction.self_correction import correct
    from napari_dvc_correct.engine.correlation import correlate as correlate_module

    reference, deformed, field = sheared_uint16_pair
    mask = None
    if frame == "loaded":  # the mask's forward warp too
        mask = np.zeros(reference.shape, bool)
        mask[2:38, 3:37, 1:39] = True
    monkeypatch.setattr(correlate_module, "KEEP_INTEGER_FROM", 0)
    volumes = V.InMemoryVolumes(reference, deformed, frame, mask)
    assert volumes.reference is reference and volumes.deformed is deformed
    as_float = [v.astype(np.float32) for v in (reference, deformed)]
    held = correct(reference, deformed, field, frame=frame, mask=mask, max_passes=2)
    copied = correct(*as_float, field, frame=frame, mask=mask, max_passes=2)
    assert held.metadata["correction"]["passes_applied"] >= 1  # the passes ran
    names = ("u", "zncc", "status", "iterations", "provenance", "uncertainty", "gradient")
    for name in names:
        np.testing.assert_array_equal(getattr(held, name), getattr(copied, name), err_msg=name)
    for before, after in zip(
        copied.metadata["correction_passes"], held.metadata["correction_passes"], strict=True
    ):
        before, after = dict(before), dict(after)
        before.pop("seconds"), after.pop("seconds")
        assert before == after


def test_a_correcting_run_drops_the_judged_fields_pull_back(pair):
    from napari_dvc_correct.engine.correction.pass_update import zero_start
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    reference, deformed = pair
    volumes = V.InMemoryVolumes(reference, deformed, "loaded")
    field = _uniform(SHIFT)
    run_to_completion(volumes.fit_gray_levels(field))
    residuals = run_to_completion(volumes.residuals())
    assert residuals._last is not None  # the gray-level fit's pull-back, handed over
    moved, _ = run_to_completion(volumes.align(field))
    pair_ = run_to_completion(volumes.matching_pair(moved, field))
    grid = (field.origin, field.step, field.shape)
    run = volumes.correlate(CorrelationParams(15, 6), pair_, grid=grid, initial=zero_start(grid))
    assert residuals._last is None  # not held while the correcting DVC runs
    delta = run_to_completion(run)
    assert np.all(np.abs(delta.u[delta.valid]) < 0.05)  # the true field leaves nothing to do


@pytest.mark.parametrize("frame", ["loaded", "reference"])
def test_large_volumes_let_go_of_the_judged_pull_back_when_aligning(monkeypatch, pair, frame):
    reference, deformed = pair
    field = _uniform(SHIFT)
    results = {}
    for release_from in (np.inf, 0):
        monkeypatch.setattr(V, "RELEASE_PULL_BACK_FROM", release_from)
        volumes = V.InMemoryVolumes(reference, deformed, frame)
        run_to_completion(volumes.fit_gray_levels(field))
        residuals = run_to_completion(volumes.residuals())
        held = residuals._last
        results[release_from] = run_to_completion(volumes.align(field))
        assert (residuals._last is held) == (release_from == np.inf)
    kept, released = results[np.inf], results[0]
    np.testing.assert_array_equal(kept[0], released[0])
    assert kept[1] == released[1]
