"""Tiled self-correction: the in-memory correction's field, from lazy files, block by block.

The case is a small version of tests/engine/test_correction.py's: a noisy two-phase volume under a
shear band on a rigid shift, whose first-order DVC the correction improves. The tiled run reads the
reference from a TIFF stack and the deformed volume from a Zarr array, warps in 12 blocks,
correlates each pass in 8 batches and judges the nodes in 8 node blocks.

Tolerance: every block reads the volumes' values exactly and prefilters a region whose 12-voxel
margin makes its coefficients equal the whole volume's to ~2.4e-7 of the gray range (measured in
docs/scaling.md), so warped grays and residuals agree to ~1e-5 relative; the correcting DVC starts
from a zero field (no seed search), so the batches start every POI where the in-memory run does.
The fields then agree to 1.5e-7 voxel (measured); the test allows 1e-4 voxel, ten times below the
IC-GN tolerance, residual means to 1e-4 relative, and asks for the same statuses and the same
acceptance counts.

On this case both corrections end with the oriented step (0.141 -> 0.053 voxel after the passes):
the planar nodes re-matched on the original pair under oriented windows, batch by batch in the
tiled run (its regions' prefilters equal the whole volume's to float32 rounding, as above; two
layers of neighbouring nodes per batch, so that the repair of a noisy match starts where it does
in memory). Measured: the same 125 nodes matched and accepted, the fields within 4.6e-8 voxel.
"""

import threading

import numpy as np
import pytest
import tifffile
import zarr

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction.acceptance import ReferenceResiduals
from napari_dvc_correct.engine.correction.cleaning import clean
from napari_dvc_correct.engine.correction.self_correction import correct, correction_table
from napari_dvc_correct.engine.correction.volumes import InMemoryVolumes
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.interpolation import prefilter
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.progress import run_to_completion
from napari_dvc_correct.tiled.correction import TiledVolumes, correct_tiled, correct_tiled_iter
from napari_dvc_correct.tiled.memory import MemoryBudgetError

SIZE = 48
BAND = synthetic.shear_band((SIZE / 2,) * 3, width=8.0, slip=6.0, shift=(3.0, -2.0, 4.0))
PARAMS = CorrelationParams(subvolume=17, step=6)  # a 5x5x5 grid
RUN = dict(batch_shape=(3, 3, 3), block_shape=(16, 32, 32), node_block=3, workers=2)
PASSES = 2


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiled_correction")
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.two_phase_volume(s, seed=4), (SIZE,) * 3, BAND, margin=16
    )
    reference = synthetic.add_noise(reference, 4.0, seed=1).astype(np.float32)
    deformed = synthetic.add_noise(deformed, 4.0, seed=2).astype(np.float32)
    tifffile.imwrite(folder / "g.tif", reference)
    zarr.create_array(str(folder / "f.zarr"), data=deformed, chunks=(16, 16, 16))
    measured = correlate(reference, deformed, PARAMS)
    in_memory = correct(reference, deformed, measured, max_passes=PASSES)
    return folder, reference, deformed, measured, in_memory


@pytest.fixture(scope="module")
def tiled(case):
    folder, _, _, measured, _ = case
    temp = folder / "temporary"
    temp.mkdir()
    field = correct_tiled(
        folder / "g.tif", str(folder / "f.zarr"), measured, max_passes=PASSES, temp_dir=temp, **RUN
    )
    return field, temp


def _rmse(field):
    error = field.displacement - BAND(field.points)
    return float(np.sqrt(np.nanmean(np.sum(error**2, axis=1))))


def test_node_residuals_block_by_block_equal_the_whole_volume(case):
    folder, reference, deformed, measured, _ = case
    field = clean(measured)
    volumes = TiledVolumes(folder / "g.tif", folder / "f.zarr", node_block=2, workers=2)
    try:
        # the gray-level map block by block equals the whole volume's (same sums, same trims)
        gray = run_to_completion(volumes.fit_gray_levels(field))
        in_memory = InMemoryVolumes(reference, deformed, "loaded")
        gray_whole = run_to_completion(in_memory.fit_gray_levels(field))
        assert gray.contrast == pytest.approx(gray_whole.contrast, rel=1e-5)
        assert gray.offset == pytest.approx(gray_whole.offset, abs=1e-3)
        whole = ReferenceResiduals(reference, deformed, prefilter(deformed), gray)
        blocks = run_to_completion(volumes.residuals())  # 27 node blocks of up to 2x2x2 nodes
        (cell, region), floor = whole.local_means(field, (3, 8))
        (cell_b, region_b), floor_b = blocks.local_means(field, (3, 8))
        # a region's prefilter equals the whole volume's to ~2.4e-7 of the gray range at the
        # 12-voxel margin (docs/scaling.md): ~5e-5 gray levels here, ~1e-5 of a cell's residual
        np.testing.assert_allclose(cell_b, cell, rtol=1e-4)
        np.testing.assert_allclose(region_b, region, rtol=1e-4)
        assert np.isfinite(floor) and floor_b == pytest.approx(floor, rel=1e-5)
        np.testing.assert_allclose(  # G is read exactly: only the box sums' rounding
            blocks.gradient_means(field, 3), whole.gradient_means(field, 3), rtol=1e-6
        )
        np.testing.assert_array_equal(blocks.thresholds[0], whole.thresholds_g)
        np.testing.assert_allclose(
            blocks.signed_means(field, 3), whole.signed_means(field, 3), rtol=1e-4, atol=1e-3
        )
    finally:
        volumes.close()


def test_equals_the_in_memory_correction(case, tiled):
    _, _, _, measured, in_memory = case
    field, _ = tiled
    assert _rmse(in_memory) < 0.75 * _rmse(measured)  # the case is one the correction improves
    np.testing.assert_array_equal(field.status, in_memory.status)
    np.testing.assert_array_equal(field.provenance, in_memory.provenance)
    assert np.max(np.abs(field.u - in_memory.u)) < 1e-4
    a, b = correction_table(in_memory), correction_table(field)
    assert len(a) == len(b) == PASSES + 1 and sum(p.accepted for p in b[1:]) >= 1
    for x, y in zip(a, b):
        assert (x.accepted_nodes, x.rejected_nodes, x.improved_nodes) == (
            y.accepted_nodes,
            y.rejected_nodes,
            y.improved_nodes,
        )
        assert y.mean_gray_residual == pytest.approx(x.mean_gray_residual, rel=1e-4)
        assert y.noise_floor == pytest.approx(x.noise_floor, rel=1e-4)
        assert y.local_residual_after == pytest.approx(x.local_residual_after, rel=1e-4)
    info = field.metadata["correction"]
    assert info["tiled"]["block_shape"] == [16, 32, 32]
    assert info["pass_order"] == in_memory.metadata["correction"]["pass_order"]


@pytest.mark.parametrize("frame", ["loaded", "reference"])
def test_with_a_mask_in_either_frame_as_in_memory(case, frame):
    folder, reference, deformed, measured, _ = case
    mask = np.ones(reference.shape, np.uint8)
    mask[:, :, :14] = 0  # the first grid column's subvolumes (x 3..19) are mostly outside
    np.save(folder / f"mask_{frame}.npy", mask * 255)  # any non-zero value is material
    options = dict(frame=frame, max_passes=1)
    a = correct(reference, deformed, measured, mask=mask.astype(bool), **options)
    b = correct_tiled(
        folder / "g.tif", folder / "f.zarr", measured, mask=folder / f"mask_{frame}.npy",
        **options, **RUN,
    )  # fmt: skip
    assert np.any(a.status == Status.MASKED)  # the mask is used
    np.testing.assert_array_equal(a.status, b.status)
    assert np.max(np.abs(a.u - b.u)) < 1e-4
    x, y = correction_table(a)[1], correction_table(b)[1]
    assert (x.accepted_nodes, x.rejected_nodes) == (y.accepted_nodes, y.rejected_nodes)
    assert y.mean_gray_residual == pytest.approx(x.mean_gray_residual, rel=1e-4)


def test_temporary_arrays_are_removed(tiled):
    _, temp = tiled
    assert temp.exists() and not any(temp.iterdir())


def test_cancel_stops_the_blocks_and_removes_the_temporary_arrays(case, tmp_path):
    folder, _, _, measured, _ = case
    temp = tmp_path / "not" / "there yet"  # a folder the user names is created
    generator = correct_tiled_iter(
        folder / "g.tif", folder / "f.zarr", measured, temp_dir=temp, **RUN
    )
    stages = []
    for report in generator:
        stages.append(report.stage)
        if report.stage == "warp" and report.done == 2:  # in the middle of the first warp
            break
    generator.close()
    assert stages[0] == "plan" and "statistics (reference)" in stages
    assert temp.is_dir() and not any(temp.iterdir())
    assert not [t for t in threading.enumerate() if t.name == "dvc-dask-local"]


def test_refuses_a_run_over_max_memory_before_any_work(case, tmp_path):
    folder, _, _, measured, _ = case
    generator = correct_tiled_iter(
        folder / "g.tif", folder / "f.zarr", measured, temp_dir=tmp_path, max_memory="1MB"
    )
    with pytest.raises(MemoryBudgetError, match="--max-memory"):
        next(generator)
    assert not any(tmp_path.iterdir())


def test_a_distributed_cluster_gives_the_local_field(case, tiled):
    import distributed

    folder, _, _, measured, _ = case
    local, _ = tiled
    with distributed.LocalCluster(
        n_workers=2,
        processes=True,
        threads_per_worker=1,
        dashboard_address=None,
        memory_limit="2GiB",
    ) as cluster:
        remote = run_to_completion(
            correct_tiled_iter(
                folder / "g.tif",
                str(folder / "f.zarr"),
                measured,
                max_passes=PASSES,
                scheduler=cluster.scheduler_address,
                **{k: v for k, v in RUN.items() if k != "workers"},
            )
        )
    assert remote.metadata["correction"]["tiled"]["scheduler"] == cluster.scheduler_address
    np.testing.assert_array_equal(remote.status, local.status)
    np.testing.assert_allclose(remote.u, local.u, rtol=0, atol=1e-9)


def test_selective_passes_out_of_core_equal_in_memory():
    # a bump in one corner of 64^3 (tests/engine/test_correction.py's case): passes 2 and 3
    # match only near the nodes the pass before moved (1715 and 1466 of 1728 POIs), in memory
    # and batch by batch alike (measured: 7.9e-8 voxel, the same statuses and counts)
    center = np.array([19.0, 19.0, 19.0])

    def bump(points):
        points = np.asarray(points, np.float64)
        weight = np.exp(-np.sum((points - center) ** 2, axis=-1) / 50.0)
        u = np.zeros_like(points)
        u[..., 0], u[..., 1], u[..., 2] = 1.5, -1.0, 2.0 + 2.5 * weight
        return u

    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=3), (64,) * 3, bump, margin=12
    )
    measured = correlate(reference, deformed, CorrelationParams(subvolume=15, step=4))
    in_memory = correct(reference, deformed, measured, max_passes=3)
    tiled = correct_tiled(
        reference,
        deformed,
        measured,
        max_passes=3,
        batch_shape=(6, 6, 6),
        block_shape=(32, 64, 64),
        node_block=6,
        workers=2,
    )
    rows = [correction_table(field) for field in (in_memory, tiled)]
    assert rows[0][3].matched_nodes < measured.n_points  # a selective pass ran
    for a, b in zip(*rows):
        assert (a.matched_nodes, a.judged_nodes, a.accepted_nodes, a.improved_nodes) == (
            b.matched_nodes,
            b.judged_nodes,
            b.accepted_nodes,
            b.improved_nodes,
        )
    np.testing.assert_allclose(tiled.u, in_memory.u, atol=1e-4)
    np.testing.assert_array_equal(tiled.status, in_memory.status)


def test_the_oriented_step_runs_block_by_block_as_in_memory(case, tiled):
    """Both records say the step ran on the same nodes with the same outcome (the seconds
    aside), and it is what brings the field near the truth on this case."""
    _, _, _, measured, in_memory = case
    field, _ = tiled
    a = dict(in_memory.metadata["correction"]["oriented"])
    b = dict(field.metadata["correction"]["oriented"])
    assert a.pop("seconds") > 0 and b.pop("seconds") > 0
    assert b == a
    assert b["ran"] is True and b["accepted_nodes"] > 0.5 * field.n_points
    assert b["planar_nodes"] == b["matched_nodes"] and b["directions"] >= 2  # several runs
    assert b["subvolume"] == 25  # 1.5 x the 17^3 subvolume: the batches' margins held it
    assert _rmse(field) < 0.3 * _rmse(measured) and _rmse(field) < 0.06


def test_the_skipped_oriented_step_says_why_as_in_memory(case):
    """A second-order first run: the passes' own boxes follow the field, so neither back-end
    re-matches the original pair, and both records say so."""
    folder, reference, deformed, _, _ = case
    params = PARAMS.replace(order=2)
    measured = correlate(reference, deformed, params)
    a = correct(reference, deformed, measured, max_passes=1)
    b = correct_tiled(folder / "g.tif", folder / "f.zarr", measured, max_passes=1, **RUN)
    info = b.metadata["correction"]["oriented"]
    assert info == a.metadata["correction"]["oriented"]
    assert info["ran"] is False and "follow the field" in info["reason"]
    np.testing.assert_array_equal(a.status, b.status)
    assert np.max(np.abs(a.u - b.u)) < 1e-4
