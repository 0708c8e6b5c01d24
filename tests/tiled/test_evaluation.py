"""Tiled evaluation: the in-memory Evaluation, block by block from lazily read TIFF and Zarr.

Tolerances. Each block prefilters its own region of the other volume; those B-spline coefficients
equal the whole volume's to float32 rounding (docs/scaling.md), so a residual voxel differs by at
most ~1e-7 of the gray range (about 130 gray levels here: ~1e-5 gray levels); means of many
voxels agree better (4e-8 measured for the local means), ~1e-8 relative. Counts are geometry
(hull, volume bounds) and equal exactly, except that a voxel whose moved gray lies within that
rounding of a threshold may change phase (none did here; the tests allow 1 in 10⁴).
"""

import numpy as np
import pytest
import tifffile
import zarr

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    affine,
    deform_volume,
    sample_displacement,
    two_phase_volume,
)
from napari_dvc_correct.io.lazy import open_volume
from napari_dvc_correct.tiled.evaluation import (
    choose_block_shape,
    estimate_evaluation_memory,
    evaluate_tiled,
    evaluate_tiled_iter,
)
from napari_dvc_correct.tiled.memory import MemoryBudgetError

SHAPE = (40, 44, 48)
BLOCK = (16, 24, 20)  # 3 x 2 x 3 = 18 blocks, none aligned with the grid's cells


def grid_field(function, subvolume=11, step=6):
    origin, step, shape = grid_for_volume(SHAPE, subvolume, step)
    base = DisplacementField.zeros(origin, step, shape)
    return base.replace(u=sample_displacement(function, base.points).reshape((*shape, 3)))


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """Noisy two-phase scans under a known affine field; G as TIFF, F as Zarr, both float32."""
    folder = tmp_path_factory.mktemp("tiled_evaluation")
    clean = two_phase_volume(SHAPE, seed=4)
    gradient = np.array([[-0.02, 0.005, 0.0], [0.0, 0.01, 0.004], [0.003, 0.0, 0.01]])
    truth = affine(gradient, center=(20.0, 22.0, 24.0), shift=(1.3, -0.7, 2.1))
    reference = add_noise(clean, 3.0, seed=5).astype(np.float32)
    deformed = add_noise(deform_volume(clean, truth), 3.0, seed=6).astype(np.float32)
    tifffile.imwrite(folder / "G.tif", reference)
    zarr.save_array(str(folder / "F.zarr"), deformed)
    exact = grid_field(truth)
    fields = {"exact": exact, "wrong": exact.replace(u=exact.u + 0.7)}
    return folder, reference, deformed, fields


def assert_same_evaluation(a, b, residual_tol=1e-5):
    """``b`` (tiled) equals ``a`` (in memory) to the float32 prefilter's rounding."""
    assert np.array_equal(a.thresholds_reference, b.thresholds_reference)
    assert np.array_equal(a.thresholds_deformed, b.thresholds_deformed)
    for ours, theirs in zip(a.phases_reference + a.phases_deformed,
                            b.phases_reference + b.phases_deformed):  # fmt: skip
        assert (ours.phase, ours.voxels, ours.lower, ours.upper) == (
            theirs.phase, theirs.voxels, theirs.lower, theirs.upper,
        )  # fmt: skip
        assert theirs.mean_gray == pytest.approx(ours.mean_gray, rel=1e-12)
    assert b.contrast == pytest.approx(a.contrast, rel=1e-12) and a.phase_pair == b.phase_pair
    assert np.array_equal(a.edges, b.edges) and a.options == b.options
    for x, y in zip(a.fields, b.fields):
        assert x.name == y.name and x.voxels == y.voxels
        assert y.mean_residual == pytest.approx(x.mean_residual, rel=1e-7)
        assert y.background.mean == pytest.approx(x.background.mean, rel=1e-7)
        assert abs(y.background.voxels - x.background.voxels) <= 1e-4 * x.background.voxels
        for (k, mean, n), (k2, mean2, n2) in zip(x.background.per_phase, y.background.per_phase):
            assert k == k2 and abs(n - n2) <= 1e-4 * max(n, 1)
            assert mean2 == pytest.approx(mean, rel=1e-6, nan_ok=True)
        assert y.background_used == pytest.approx(x.background_used, rel=1e-7)
        assert y.accuracy == pytest.approx(x.accuracy, abs=1e-8)
        assert np.array_equal(x.bins.voxels, y.bins.voxels)
        np.testing.assert_allclose(y.bins.mean_residual, x.bins.mean_residual, atol=residual_tol)
        np.testing.assert_allclose(y.bin_accuracy, x.bin_accuracy, atol=1e-6)
        np.testing.assert_allclose(y.local_residual, x.local_residual, atol=residual_tol)
        np.testing.assert_allclose(y.local_accuracy, x.local_accuracy, atol=1e-6)
        assert y.local_accuracy_index == pytest.approx(x.local_accuracy_index, abs=1e-6)
        np.testing.assert_array_equal(y.equivalent_strain, x.equivalent_strain)


def test_tiled_evaluation_from_tiff_and_zarr_equals_the_in_memory_one(pair, tmp_path):
    folder, reference, deformed, fields = pair
    memory = evaluate_fields(reference, deformed, fields, bin_by="exact", n_bins=4)
    outputs = {
        "labels_reference": tmp_path / "labels_G.tif",
        ("residual", "wrong"): tmp_path / "residual_wrong.zarr",
        ("labels_mapped", "wrong"): tmp_path / "mapped_wrong.tif",
    }
    reports = []
    tiled = None
    generator = evaluate_tiled_iter(
        open_volume(folder / "G.tif"), open_volume(folder / "F.zarr"), fields, bin_by="exact",
        n_bins=4, block_shape=BLOCK, workers=2, outputs=outputs,
    )  # fmt: skip
    while True:
        try:
            reports.append(next(generator))
        except StopIteration as stop:
            tiled = stop.value
            break
    assert reports[0].stage == "plan" and "18 blocks" in reports[0].message
    assert [r.total for r in reports if r.stage == "evaluate"][-1] == 18
    assert_same_evaluation(memory, tiled)
    # the volumes written block by block are the in-memory ones
    np.testing.assert_array_equal(
        np.asarray(tiled.labels_reference), memory.labels_reference.astype(np.float32)
    )
    residual = np.asarray(tiled["wrong"].residual)
    expected = memory["wrong"].residual
    assert np.array_equal(np.isnan(residual), np.isnan(expected))
    np.testing.assert_allclose(residual, expected, atol=1e-4, equal_nan=True)
    mapped = np.asarray(tiled["wrong"].labels_mapped)
    assert np.mean(mapped != memory["wrong"].labels_mapped) <= 1e-4
    assert tiled["exact"].residual is None and tiled.labels_deformed is None
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in outputs.values())


def test_loaded_mode_user_thresholds_and_own_background(pair):
    folder, reference, deformed, fields = pair
    options = dict(mode="loaded", phases=[133.0], phases_deformed=[136.0],
                   shared_background=False, strain_method="least-squares")  # fmt: skip
    memory = evaluate_fields(reference, deformed, fields, keep_volumes=False, **options)
    tiled = evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, block_shape=BLOCK,
                           scheduler="sync", **options)  # fmt: skip
    assert_same_evaluation(memory, tiled)
    assert tiled["wrong"].background_used == tiled["wrong"].background.mean


def test_three_phases_auto_in_one_block_and_in_many(pair):
    folder, reference, deformed, fields = pair
    memory = evaluate_fields(reference, deformed, fields, n_phases=3, keep_volumes=False)
    for block in (SHAPE, (8, 64, 64)):
        tiled = evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, n_phases=3,
                               block_shape=block, workers=2)  # fmt: skip
        assert tiled.thresholds_reference.size == 2
        assert_same_evaluation(memory, tiled)


def test_too_little_memory_is_refused_before_anything_is_read_or_written(pair, tmp_path):
    folder, _, _, fields = pair
    outputs = {("residual", "exact"): tmp_path / "residual.tif"}
    need = estimate_evaluation_memory(SHAPE, BLOCK, list(fields.values()), workers=2)
    with pytest.raises(MemoryBudgetError, match="--max-memory"):
        evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, block_shape=BLOCK,
                       workers=2, max_memory=need - 1, outputs=outputs)  # fmt: skip
    with pytest.raises(MemoryBudgetError, match="even blocks of 16"):
        evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, max_memory=1000)
    assert not list(tmp_path.iterdir())
    # the estimate grows with the blocks held at once, and max_memory picks a block that fits
    items = list(fields.values())
    assert estimate_evaluation_memory(SHAPE, BLOCK, items, workers=4) > need
    chosen = choose_block_shape(SHAPE, items, need, workers=2)
    assert np.prod(chosen) < np.prod(SHAPE)
    assert estimate_evaluation_memory(SHAPE, chosen, items, workers=2) <= need
    result = evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, workers=2,
                            max_memory=need)  # fmt: skip
    assert np.isfinite(result["exact"].accuracy)


def test_bad_input_is_the_in_memory_error_and_writes_nothing(pair, tmp_path):
    folder, reference, deformed, fields = pair
    outputs = {("residual", "exact"): tmp_path / "residual.tif"}
    other = grid_field(lambda p: np.zeros_like(p))
    far = other.replace(origin=tuple(o + 30.0 for o in other.origin))
    with pytest.raises(ValueError, match="does not fit the volume"):
        evaluate_tiled(folder / "G.tif", folder / "F.zarr", {"far": far}, outputs=outputs)
    with pytest.raises(ValueError, match="has no voxel"):  # a phase empty in the reference
        evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, block_shape=BLOCK,
                       phases=[150.0, 150.0001], outputs=outputs)  # fmt: skip
    with pytest.raises(ValueError, match="phase 2 does not exist"):  # found after the blocks
        evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, block_shape=BLOCK,
                       phase_pair=(0, 2), outputs=outputs)  # fmt: skip
    with pytest.raises(ValueError, match="names no evaluated field"):
        evaluate_tiled(
            reference, deformed, fields, outputs={("residual", "other"): tmp_path / "r.tif"}
        )
    broken = deformed.copy()
    broken[30, 5, 7] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        evaluate_tiled(reference, broken, fields, block_shape=BLOCK, outputs=outputs)
    assert not list(tmp_path.iterdir())


def test_a_distributed_cluster_gives_the_local_evaluation(pair, tmp_path):
    """Two worker processes read the files by path and write the residual themselves."""
    import distributed

    folder, _, _, fields = pair
    local = evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, block_shape=BLOCK)
    outputs = {("residual", "wrong"): tmp_path / "residual.tif"}
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None,
        memory_limit="2GiB",
    ) as cluster:  # fmt: skip
        remote = evaluate_tiled(folder / "G.tif", folder / "F.zarr", fields, block_shape=BLOCK,
                                scheduler=cluster.scheduler_address, outputs=outputs)  # fmt: skip
    for x, y in zip(local.fields, remote.fields):  # the same code on the same blocks
        assert (x.mean_residual, x.background, x.accuracy) == (
            y.mean_residual, y.background, y.accuracy,
        )  # fmt: skip
        np.testing.assert_array_equal(x.local_residual, y.local_residual)
        np.testing.assert_array_equal(x.bins.mean_residual, y.bins.mean_residual)
    assert np.isfinite(np.asarray(remote["wrong"].residual)).any()


def test_a_cancelled_run_stops_and_leaves_no_output(pair, tmp_path):
    folder, _, _, fields = pair
    outputs = {
        ("residual", "exact"): tmp_path / "residual.tif",
        "labels_deformed": tmp_path / "l.zarr",
    }
    generator = evaluate_tiled_iter(folder / "G.tif", folder / "F.zarr", fields,
                                    block_shape=(8, 8, 8), workers=1, outputs=outputs)  # fmt: skip
    for report in generator:
        if report.stage == "evaluate":  # the outputs exist (as temporary files) from here on
            assert report.done < report.total
            break
    assert len(list(tmp_path.iterdir())) == 2  # being written
    generator.close()
    assert not list(tmp_path.iterdir())


def test_a_specimen_region_block_by_block_equals_in_memory(pair):
    """The specimen region (issue 26) read block by block: the in-memory evaluation's numbers."""
    from napari_dvc_correct.engine.correlation.placement import Cylinder
    from napari_dvc_correct.engine.evaluation.accuracy import specimen_mask

    folder, reference, deformed, fields = pair
    region = specimen_mask(SHAPE, Cylinder((21.5, 23.5), 17.0))
    expected = evaluate_fields(reference, deformed, fields, keep_volumes=False, region=region)
    got = evaluate_tiled(
        open_volume(folder / "G.tif"), open_volume(folder / "F.zarr"), fields,
        block_shape=BLOCK, scheduler="sync", region=region,
    )  # fmt: skip
    assert sum(s.voxels for s in expected.phases_reference) == int(region.sum())
    assert_same_evaluation(expected, got)
    for x, y in zip(expected.fields, got.fields):
        np.testing.assert_allclose(y.error_estimate, x.error_estimate, rtol=1e-5, atol=1e-6)
