"""Tiled correlation: the same field as in memory, from lazy volumes, on threads or a cluster."""

import threading

import numpy as np
import pytest
import tifffile
import zarr

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.interpolation import prefilter
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.progress import Progress, run_to_completion
from napari_dvc_correct.io.lazy import ArrayVolume
from napari_dvc_correct.tiled import (
    MemoryBudgetError,
    correlate_tiled,
    correlate_tiled_iter,
    whole_volume,
)
from napari_dvc_correct.tiled import correlate as tiled
from napari_dvc_correct.tiled.memory import PREFILTER_MARGIN

GRADIENT = np.array([[0.02, 0.0, 0.01], [0.0, -0.01, 0.0], [0.0, 0.0, 0.015]])
# 1e-5: fine enough that a converged answer does not depend on IC-GN's starting guess (see
# test_default_tolerance_agrees_within_the_tolerance for the default)
PARAMS = CorrelationParams(subvolume=15, step=6, tolerance=1e-5)
BATCH = (5, 5, 5)


@pytest.fixture(scope="module")
def pair():
    # long along x so that batches read regions smaller than the volume
    reference = synthetic.textured_volume((46, 46, 120), 2.0, seed=5)
    truth = synthetic.affine(GRADIENT, np.array(reference.shape) / 2, shift=(1.5, -2.2, 0.8))
    return reference, synthetic.deform_volume(reference, truth), truth


@pytest.fixture(scope="module")
def in_memory(pair):
    reference, deformed, _ = pair
    return correlate(reference, deformed, PARAMS)


@pytest.fixture(scope="module")
def local(pair):
    reference, deformed, _ = pair
    return correlate_tiled(reference, deformed, PARAMS, batch_shape=BATCH)


def _converged_in_both(a, b):
    return (a.status == Status.CONVERGED) & (b.status == Status.CONVERGED)


def test_prefilter_margin_reaches_float32_rounding():
    volume = synthetic.textured_volume((72, 72, 72), 2.0, seed=3)
    whole = prefilter(volume)
    m = PREFILTER_MARGIN
    region = prefilter(volume[30 - m : 42 + m, 30 - m : 42 + m, 30 - m : 42 + m])
    core = region[m:-m, m:-m, m:-m]
    gray_range = float(volume.max() - volume.min())
    assert np.max(np.abs(core - whole[30:42, 30:42, 30:42])) < 1e-6 * gray_range  # a few ulps
    short = prefilter(volume[26:46, 26:46, 26:46])[4:-4, 4:-4, 4:-4]  # a 4-voxel margin is not
    assert np.max(np.abs(short - whole[30:42, 30:42, 30:42])) > 1e-5 * gray_range


def test_equals_in_memory_correlation(in_memory, local, pair):
    tiles = local.metadata["tiled"]
    assert tiles["batches"] == 4  # a 5x5x18 grid in 5x5x5 batches
    assert tiles["largest_region_voxels"] < 0.9 * 46 * 46 * 120  # only a region each
    assert local.metadata["global_shift"] == in_memory.metadata["global_shift"]
    both = _converged_in_both(in_memory, local)
    assert both.sum() >= 0.95 * both.size
    assert np.mean(in_memory.status == local.status) >= 0.99
    difference = np.abs(in_memory.u - local.u)[both]
    assert difference.max() < 1e-4, difference.max()
    assert np.abs(in_memory.gradient - local.gradient)[both].max() < 1e-4
    assert np.abs(in_memory.zncc - local.zncc)[both].max() < 1e-5
    # and both are right: the known affine field
    truth = pair[2]
    expected = synthetic.sample_displacement(truth, local.points).reshape(local.u.shape)
    assert np.sqrt(np.mean((local.u - expected)[both] ** 2)) < 0.02


def test_batches_with_a_margin_give_the_in_memory_field():
    """Seeds on whole-grid indices: each batch starts its POIs from the in-memory guesses.

    A large shift (searched over 12 voxels) and a rotation of 0.08 rad about x (the displacement
    changes by 0.4 voxel from POI to POI, 1.2 from seed to seed): a POI's guess depends on which
    seed it copies, and IC-GN, stopped at its tolerance, keeps a trace of where it started. With
    the seeds laid out per batch, 108 of the 1000 POIs differed from the in-memory run by up to
    1.7e-3 voxel (and 557 took a different number of iterations). Margin 2: the seeds on the
    y = 0 face fail (their deformed subvolumes leave the volume), so the nearest good seed of a
    POI there can be two POIs away. 1e-6 voxel: the region's B-spline coefficients equal the
    whole volume's to float32 rounding (PREFILTER_MARGIN), nothing else differs.
    """
    reference = synthetic.textured_volume((64, 64, 64), 2.0, seed=5)
    rotation = np.array([[0.0, -0.08, 0.0], [0.08, 0.0, 0.0], [0.0, 0.0, 0.0]])
    truth = synthetic.affine(rotation, np.array(reference.shape) / 2, shift=(6.3, -7.2, 4.8))
    deformed = synthetic.deform_volume(reference, truth)
    params = CorrelationParams(subvolume=15, step=5, tolerance=1e-5, search_radius=12)
    a = correlate(reference, deformed, params)
    b = correlate_tiled(
        reference, deformed, params, batch_shape=(4, 4, 10), margin=2, seed_pass=False
    )
    assert a.shape == (10, 10, 10) and b.metadata["tiled"]["batches"] == 9
    assert np.sum(a.status == Status.CONVERGED) > 900
    np.testing.assert_array_equal(b.status, a.status)
    np.testing.assert_array_equal(b.iterations, a.iterations)
    np.testing.assert_allclose(b.u, a.u, rtol=0, atol=1e-6)  # NaN where both are NaN
    np.testing.assert_allclose(b.gradient, a.gradient, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.zncc, a.zncc, rtol=0, atol=1e-6)


@pytest.fixture(scope="module")
def rotation_case():
    """A large shift (searched over 12 voxels) and a rotation of 0.08 rad about x: the
    displacement changes by 0.4 voxel from POI to POI, 1.2 from seed to seed."""
    reference = synthetic.textured_volume((64, 64, 64), 2.0, seed=5)
    rotation = np.array([[0.0, -0.08, 0.0], [0.08, 0.0, 0.0], [0.0, 0.0, 0.0]])
    truth = synthetic.affine(rotation, np.array(reference.shape) / 2, shift=(6.3, -7.2, 4.8))
    deformed = synthetic.deform_volume(reference, truth)
    params = CorrelationParams(subvolume=15, step=5, tolerance=1e-5, search_radius=12)
    return reference, deformed, params, correlate(reference, deformed, params)


def test_the_seed_pass_gives_the_in_memory_field(rotation_case):
    """The seeds matched and judged on the whole grid first: every POI starts from the
    in-memory guess, and the default margin of one POI lets the repair and the median test of
    every pyramid level see, at a batch's face, the neighbours they see in memory.

    Without the seed pass (seeds searched per batch on whole-grid indices) this margin left 11
    POIs up to 4.8e-4 voxel away and 15 with other iteration counts. 1e-6 voxel: the seeds'
    and the batches' regions differ from the whole volume only by the coarse level's prefilter
    at the region's edge (COARSE_PREFILTER_MARGIN; measured 4e-8 voxel here).
    """
    reference, deformed, params, a = rotation_case
    b = correlate_tiled(reference, deformed, params, batch_shape=(4, 4, 10))
    tiles = b.metadata["tiled"]
    assert tiles["batches"] == 9 and tiles["margin"] == 1 and tiles["seed_pass"]
    assert 40 < tiles["good_seeds"] < 64  # of 4 x 4 x 4 seeds (stride 3: 0, 3, 6, 9)
    assert np.sum(a.status == Status.CONVERGED) > 900
    np.testing.assert_array_equal(b.status, a.status)
    np.testing.assert_array_equal(b.iterations, a.iterations)
    np.testing.assert_allclose(b.u, a.u, rtol=0, atol=1e-6)  # NaN where both are NaN
    np.testing.assert_allclose(b.gradient, a.gradient, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.zncc, a.zncc, rtol=0, atol=1e-6)


def test_cancel_during_the_seed_pass_stops_the_work(monkeypatch, pair):
    reference, deformed, _ = pair
    started = []
    batches = []
    real = tiled.match_seeds

    def counted(job, *volumes):
        started.append(len(job.rows))
        return real(job, *volumes)

    monkeypatch.setattr(tiled, "match_seeds", counted)
    monkeypatch.setattr(tiled, "match_batch", lambda *a: batches.append(a))
    before = set(threading.enumerate())
    generator = correlate_tiled_iter(reference, deformed, PARAMS, batch_shape=(2, 2, 2), workers=1)
    for report in generator:
        if report.stage == "seeds":
            assert report.total == 81  # every 2x2x2 box of the 5x5x18 grid holds a seed
            break
    generator.close()  # returns once the task running now has finished
    assert 1 <= len(started) <= 3 and not batches
    # no thread that could start another task outlives the close, so the count is final
    assert not [t for t in set(threading.enumerate()) - before if t.is_alive()]
    assert len(started) <= 3


def test_default_tolerance_agrees_within_the_tolerance(pair):
    """At tolerance 1e-3 IC-GN stops within 1e-3 of the optimum, wherever it started from."""
    reference, deformed, _ = pair
    params = PARAMS.replace(tolerance=1e-3)
    a = correlate(reference, deformed, params)
    b = correlate_tiled(reference, deformed, params, batch_shape=BATCH)
    both = _converged_in_both(a, b)
    difference = np.abs(a.u - b.u)[both].max(axis=-1)
    assert both.sum() >= 0.95 * both.size
    assert difference.max() < 1e-3
    assert np.mean(difference < 1e-4) >= 0.98


def test_lazy_files_give_the_same_field(tmp_path, pair, local):
    reference, deformed, _ = pair
    scale = 60000.0 / float(max(reference.max(), deformed.max()))
    g16 = np.round(reference * scale).astype(np.uint16)
    f16 = np.round(deformed * scale).astype(np.uint16)
    tifffile.imwrite(tmp_path / "g.tif", g16)
    zarr.create_array(str(tmp_path / "f.zarr"), data=f16, chunks=(16, 16, 16))
    from_files = correlate_tiled(
        tmp_path / "g.tif", str(tmp_path / "f.zarr"), PARAMS, batch_shape=BATCH, workers=1
    )
    from_arrays = correlate_tiled(g16, f16, PARAMS, batch_shape=BATCH, workers=2)
    np.testing.assert_array_equal(from_files.status, from_arrays.status)
    np.testing.assert_array_equal(from_files.u, from_arrays.u)  # same batches: same numbers
    both = _converged_in_both(from_files, local)
    assert np.abs(from_files.u - local.u)[both].max() < 1e-2  # uint16 quantisation only


def test_distributed_cluster_gives_the_same_answer(pair, local):
    import distributed

    reference, deformed, _ = pair
    with distributed.LocalCluster(
        n_workers=2,
        processes=True,
        threads_per_worker=1,
        dashboard_address=None,
        memory_limit="2GiB",
    ) as cluster:
        messages = []
        generator = correlate_tiled_iter(
            ArrayVolume(reference),
            ArrayVolume(deformed),
            PARAMS,
            batch_shape=BATCH,
            scheduler=cluster.scheduler_address,
        )
        while True:
            try:
                messages.append(next(generator))
            except StopIteration as stop:
                remote = stop.value
                break
    assert remote.metadata["tiled"]["workers"] == 2
    assert sum(p.stage == "IC-GN" for p in messages) == 4
    np.testing.assert_array_equal(remote.status, local.status)
    np.testing.assert_allclose(remote.u, local.u, rtol=0, atol=1e-9)


def test_mask_and_low_texture_as_in_memory(pair):
    reference, _, truth = pair
    weak = reference.copy()
    # faint texture: low against the whole volume's contrast (as in memory), not against a
    # region's that holds nothing else
    weak[:, :, 66:] = 0.5 + 0.02 * (weak[:, :, 66:] - 0.5)
    deformed = synthetic.deform_volume(weak, truth)
    mask = np.ones(reference.shape, bool)
    mask[:, :, :30] = False
    a = correlate(weak, deformed, PARAMS, mask=mask)
    b = correlate_tiled(weak, deformed, PARAMS, mask=mask, batch_shape=BATCH)
    for code in (Status.MASKED, Status.LOW_TEXTURE, Status.CONVERGED):
        assert np.sum(a.status == code) > 20
    np.testing.assert_array_equal(a.status, b.status)
    both = _converged_in_both(a, b)
    assert np.abs(a.u - b.u)[both].max() < 1e-4


def test_progress_states_the_memory_estimate_first(pair):
    reference, deformed, _ = pair
    generator = correlate_tiled_iter(reference, deformed, PARAMS, batch_shape=BATCH)
    first = next(generator)
    generator.close()
    assert isinstance(first, Progress) and first.stage == "plan"
    assert "estimated peak memory" in first.message and "4 batches" in first.message


def test_refuses_a_run_over_max_memory(pair):
    reference, deformed, _ = pair
    with pytest.raises(MemoryBudgetError, match=r"more than the limit of .*--max-memory"):
        correlate_tiled(reference, deformed, PARAMS, batch_shape=(6, 6, 6), max_memory="20MB")
    with pytest.raises(MemoryBudgetError, match="even one POI per batch"):
        correlate_tiled(reference, deformed, PARAMS, max_memory="1MB")


def test_a_batch_chosen_by_max_memory_is_not_refused_after_the_whole_volume_pass(pair):
    # regression: the check after the whole-volume pass counted the POIs held between a batch's
    # two tasks as if batches were one POI (27 times each POI, margins included), so a batch that
    # --max-memory had chosen was then refused (seen on the 512³ benchmark)
    from napari_dvc_correct.tiled.memory import choose_batch_shape, estimate_peak_memory

    reference, deformed, _ = pair
    params = PARAMS.replace(tolerance=1e-3)
    sizes = dict(workers=1, margin=1)
    budget = estimate_peak_memory(reference.shape, np.float32, params, (3, 3, 3), **sizes)
    budget += 64 * 1024  # just above a 3³ batch; a 4³ batch needs more
    assert choose_batch_shape(reference.shape, np.float32, params, budget, **sizes) == (3, 3, 3)
    one = estimate_peak_memory(reference.shape, np.float32, params, (1, 1, 1), workers=0, margin=1)
    three = estimate_peak_memory(
        reference.shape, np.float32, params, (3, 3, 3), workers=0, margin=1
    )
    assert one - three > 64 * 1024  # the old check would have refused this run
    messages = []
    generator = correlate_tiled_iter(reference, deformed, params, max_memory=budget, workers=1)
    try:
        while True:
            messages.append(next(generator).message)
    except StopIteration as stop:
        field = stop.value
    assert "of up to 3x3x3 POIs" in messages[0]
    assert np.mean(field.valid) > 0.9


def test_refuses_a_run_larger_than_the_machine(monkeypatch, pair):
    reference, deformed, _ = pair
    monkeypatch.setattr(tiled, "available_memory", lambda: 50 * 2**20)
    with pytest.raises(MemoryBudgetError, match="available on this machine"):
        correlate_tiled(reference, deformed, PARAMS, batch_shape=(6, 6, 6), workers=2)


def test_rejects_volumes_with_nan(pair):
    reference, deformed, _ = pair
    broken = deformed.copy()
    broken[40, 3, 3] = np.nan
    with pytest.raises(ValueError, match="deformed volume contains NaN"):
        correlate_tiled(reference, broken, PARAMS, batch_shape=BATCH)
    with pytest.raises(ValueError, match="same shape"):
        correlate_tiled(reference, deformed[:-1], PARAMS)


def test_uncertainty_travels_through_the_batches(pair):
    reference, deformed, _ = pair
    a = correlate(reference, deformed, PARAMS)
    b = correlate_tiled(reference, deformed, PARAMS, batch_shape=BATCH)
    both = _converged_in_both(a, b)
    assert both.sum() > 20
    assert np.all(np.isfinite(b.uncertainty[both]))
    np.testing.assert_allclose(b.uncertainty[both], a.uncertainty[both], rtol=0.1, atol=1e-6)


def test_noisy_run_judges_every_batch_at_the_whole_run_noise():
    """Noise three times as strong beyond x = 48 as before it, and one batch on each side: each
    batch's own median of s² (1 - ZNCC) is far from the whole run's, so thresholds taken per
    batch moved 5 statuses (and the tiled field recorded no noise). The median over all batches'
    POIs, taken between the IC-GN and the judging, gives the in-memory thresholds, statuses and
    noise record; u within 1e-6 voxel as in the clean cases (measured 9e-8)."""
    truth = synthetic.translation((0.3, -0.4, 0.6))
    reference, deformed, sigma = synthetic.noisy_ct_pair((48, 48, 96), truth, noise=0.03, seed=5)
    rng = np.random.default_rng(3)
    for volume in (reference, deformed):
        volume[:, :, 48:] += rng.normal(0.0, 2.0 * sigma, volume[:, :, 48:].shape)
    params = CorrelationParams(subvolume=15, step=6, tolerance=1e-5)
    a = correlate(reference, deformed, params)
    b = correlate_tiled(reference, deformed, params, batch_shape=(6, 6, 7))
    assert a.shape == (5, 5, 13) and b.metadata["tiled"]["batches"] == 2
    noise = a.metadata["noise"]
    assert sigma < noise["sigma"] < 3 * sigma  # between the two halves' noise
    assert noise["zncc_threshold_min"] < 0.3 < noise["zncc_threshold_max"]  # thresholds matter
    assert np.sum(a.status == Status.LOW_ZNCC) > 10
    assert b.metadata["noise"] == noise
    np.testing.assert_array_equal(b.status, a.status)
    np.testing.assert_array_equal(b.iterations, a.iterations)
    np.testing.assert_allclose(b.u, a.u, rtol=0, atol=1e-6)  # NaN where both are NaN
    np.testing.assert_allclose(b.zncc, a.zncc, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.uncertainty, a.uncertainty, rtol=1e-3, atol=1e-4)


def test_weighted_matches_from_a_field_as_in_memory_reading_the_whole_volume_once(
    pair, monkeypatch
):
    """Every subvolume weighted by an anisotropic window (the self-correction's oriented step),
    some POIs matched from a field: the in-memory weighted run's field to the bit (measured;
    the weights move the plain answer by 8e-3 voxel on this noisy pair, so they are used). A
    second run given the first's whole-volume pass reads no whole volume again."""
    from napari_dvc_correct.engine.correction.oriented import oriented_window

    reference, deformed, _ = pair
    deformed = synthetic.add_noise(deformed, 0.05 * float(np.std(deformed)), seed=3)
    measured = correlate(reference, deformed, PARAMS)
    weights = oriented_window(PARAMS.half, (1.0, 0.0, 1.0), 2.0, 6.0)
    active = np.zeros(measured.shape, bool)
    active[1:4, :, 3:12] = True  # in 3 of the 4 batches
    options = dict(initial=measured, active=active)
    a = correlate(reference, deformed, PARAMS, weights=weights, **options)
    plain = correlate(reference, deformed, PARAMS, **options)
    assert np.nanmax(np.abs(a.u - plain.u)) > 1e-3
    reads = []
    volume_tasks = whole_volume.volume_tasks
    monkeypatch.setattr(
        whole_volume, "volume_tasks", lambda *args: reads.append(args) or volume_tasks(*args)
    )
    runs = []
    for whole in (None, "reused"):
        if whole == "reused":
            lazy = [ArrayVolume(v) for v in (reference, deformed)]
            whole = run_to_completion(
                whole_volume.whole_volume_iter(*lazy, None, 0, (None, 2, None))
            )
            reads.clear()
        runs.append(
            correlate_tiled(
                reference, deformed, PARAMS, weights=weights, whole=whole, batch_shape=BATCH,
                **options,
            )
        )  # fmt: skip
        assert len(reads) == (1 if whole is None else 0)
    for b in runs:
        assert b.metadata["tiled"]["batches"] == 3  # only those with POIs to match
        np.testing.assert_array_equal(b.status, a.status)
        np.testing.assert_array_equal(b.iterations, a.iterations)
        np.testing.assert_allclose(b.u, a.u, rtol=0, atol=1e-6)  # NaN where both are NaN
        np.testing.assert_allclose(b.uncertainty, a.uncertainty, rtol=0, atol=1e-6)


def test_refuses_bad_weights_and_a_reused_pass_without_a_field_before_any_work(pair):
    reference, deformed, _ = pair
    with pytest.raises(ValueError, match="subvolume's shape"):
        next(correlate_tiled_iter(reference, deformed, PARAMS, weights=np.ones((3, 3, 3))))
    with pytest.raises(ValueError, match="initial field"):
        next(correlate_tiled_iter(reference, deformed, PARAMS, whole=object()))
