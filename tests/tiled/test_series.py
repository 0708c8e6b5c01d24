"""Tiled scan series: the in-memory series, from lazy files, batch by batch.

Three 48x48x96 states of a noisy two-phase volume under a growing shear band on a growing rigid shift
(slip 0 → 3 → 6 voxels), the first state from a TIFF stack, the second from a Zarr array, the
third from an .npy file. The tiled runs correlate in 5 batches of 4x4x2 POIs, warp and sum the gray
residuals in 12 blocks and judge the correction in node blocks of 3.

Tolerance (as tests/tiled/test_correlate.py and test_correction.py): at IC-GN tolerance 1e-5 the
tiled correlation gives the in-memory field to ~1e-7 voxel (the seed pass starts every POI where
the in-memory run does; the regions' prefilters equal the whole volume's to float32 rounding) and
the tiled correction likewise; the series composes and corrects those fields, so the test asks
for the same statuses and provenance and the displacements within 1e-4 voxel, ten times below
the IC-GN tolerance; the summary's mean gray residuals (block sums of float32 residuals against
slab sums in memory) within 1e-4 relative. Measured: the uncorrected series equal to the bit,
the corrected ones within 4.5e-7 voxel (one pass per state applied), the mean gray residuals
within 6e-9 relative. Where a correction ends with the oriented step (re-matches of the original
pair under oriented windows), the tiled one runs it batch by batch (tests/tiled/test_correction.py).
"""

import threading

import numpy as np
import pytest
import tifffile
import zarr

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.series.strategies import series
from napari_dvc_correct.tiled import correlate as tiled_correlate
from napari_dvc_correct.tiled import whole_volume
from napari_dvc_correct.tiled.memory import MemoryBudgetError
from napari_dvc_correct.tiled.series import series_tiled, series_tiled_iter

SHAPE = (48, 48, 96)  # long along x, so that a batch's region is a part of the volume
PARAMS = CorrelationParams(subvolume=15, step=8, tolerance=1e-5)
RUN = dict(batch_shape=(4, 4, 2), block_shape=(16, 32, 48), node_block=3, workers=2)
CORRECTION = {"max_passes": 1}


def _band(k):
    return synthetic.shear_band(
        np.array(SHAPE) / 2, width=8.0, slip=3.0 * k, shift=(1.0 * k, -0.8 * k, 1.4 * k)
    )


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiled_series")
    volumes = []
    for k in range(3):
        reference, deformed = synthetic.make_pair(
            lambda s: synthetic.two_phase_volume(s, seed=4), SHAPE, _band(k), margin=16
        )
        volumes.append(synthetic.add_noise(deformed, 3.0, seed=10 + k).astype(np.float32))
    tifffile.imwrite(folder / "v0.tif", volumes[0])
    zarr.create_array(str(folder / "v1.zarr"), data=volumes[1], chunks=(16, 16, 16))
    np.save(folder / "v2.npy", volumes[2])
    paths = [folder / "v0.tif", str(folder / "v1.zarr"), folder / "v2.npy"]
    mask = np.ones(SHAPE, np.uint8)
    mask[:, :, :12] = 0  # the first column of POIs is mostly outside
    np.save(folder / "mask.npy", mask)
    return folder, volumes, paths, mask


CASES = {
    "total": dict(strategy="total"),
    "incremental, mask": dict(strategy="incremental", masked=True),
    "total, corrected": dict(strategy="total", correct_total=True),
    "incremental, both corrected, mask": dict(
        strategy="incremental", correct_increments=True, correct_total=True, masked=True
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_equals_the_in_memory_series(states, case, tmp_path):
    folder, volumes, paths, mask = states
    options = dict(CASES[case])
    masked = options.pop("masked", False)
    options["correction_options"] = CORRECTION
    a = series(volumes, PARAMS, mask=mask.astype(bool) if masked else None, **options)
    b = series_tiled(
        paths, PARAMS, mask=folder / "mask.npy" if masked else None, temp_dir=tmp_path,
        **options, **RUN,
    )  # fmt: skip
    assert not any(tmp_path.iterdir())  # the temporary arrays are gone
    assert len(b.totals) == 2 and len(b.increments) == len(a.increments)
    for x, y in zip(a.totals + a.increments, b.totals + b.increments):
        tiles = y.metadata["tiled"]
        assert tiles["batches"] > 1 and tiles["largest_region_voxels"] < np.prod(SHAPE)
        np.testing.assert_array_equal(y.status, x.status)
        np.testing.assert_array_equal(y.provenance, x.provenance)
        np.testing.assert_allclose(y.u, x.u, rtol=0, atol=1e-4)  # NaN where both are NaN
    assert b.totals[1].valid.mean() > 0.5  # a field worth comparing
    if masked:
        assert (a.increments[-1].status == Status.MASKED).any()  # the carried mask is used
    for x, y in zip(a.summary(), b.summary()):
        assert x.keys() == y.keys()
        for key in ("state", "strategy", "valid_fraction", "correction_passes"):
            assert y[key] == x[key]
        for key in ("mean_displacement", "max_displacement", "mean_zncc"):
            assert y[key] == pytest.approx(x[key], abs=1e-4, nan_ok=True)
        for key in ("mean_gray_residual", "mean_gray_residual_uncorrected"):
            assert y[key] == pytest.approx(x[key], rel=1e-4, nan_ok=True)
    if options.get("correct_total"):
        assert b.totals[1].metadata["series"]["corrected_total"]
        assert "tiled" in b.totals[1].metadata["correction"]


def test_the_plan_comes_first_and_names_every_kind_of_run(states):
    _, _, paths, _ = states
    generator = series_tiled_iter(
        paths, PARAMS, strategy="incremental", correct_increments=True, **RUN
    )
    first = next(generator)
    generator.close()
    assert first.stage == "plan"
    for part in ("correlation: estimated peak memory", "correction: estimated peak memory",
                 "gray residuals: 12 blocks"):  # fmt: skip
        assert part in first.message


def test_refuses_a_run_over_max_memory_before_any_work(states, tmp_path, monkeypatch):
    _, _, paths, _ = states
    started = []
    monkeypatch.setattr(whole_volume, "volume_tasks", lambda *a: started.append(a))
    generator = series_tiled_iter(paths, PARAMS, max_memory="1MB", temp_dir=tmp_path)
    with pytest.raises(MemoryBudgetError, match="--max-memory"):
        next(generator)
    # the correction's plan too, with batches small enough for the correlation
    generator = series_tiled_iter(
        paths, PARAMS, correct_total=True, max_memory="400MB", temp_dir=tmp_path,
        block_shape=(256, 256, 256), workers=1,
    )  # fmt: skip
    with pytest.raises(MemoryBudgetError, match="blocks need an estimated"):
        next(generator)
    assert not started and not any(tmp_path.iterdir())


def test_cancel_stops_the_work_and_removes_the_temporary_arrays(states, tmp_path, monkeypatch):
    folder, _, paths, _ = states
    batches = []
    real = tiled_correlate.match_batch

    def counted(job, *volumes):
        batches.append(1)
        return real(job, *volumes)

    monkeypatch.setattr(tiled_correlate, "match_batch", counted)
    before = set(threading.enumerate())
    generator = series_tiled_iter(
        paths, PARAMS, strategy="incremental", mask=folder / "mask.npy", temp_dir=tmp_path,
        batch_shape=(4, 4, 2), workers=1, block_shape=(16, 32, 48),
    )  # fmt: skip
    stages = []
    for report in generator:
        stages.append(report.stage)
        if report.stage == "state 2 of 2: increment: IC-GN" and report.done == 2:
            break
    generator.close()
    assert "state 2 of 2: mask: warp mask" in stages  # the mask was carried to state 1
    seen = len(batches)
    assert 5 + 2 <= seen < 5 + 5  # state 1's 5 batches, and not all of state 2's
    assert not [t for t in threading.enumerate() if t.name == "dvc-dask-local"]
    assert not any(tmp_path.iterdir())  # the carried mask is gone
    # no thread that could start another batch outlives the close, so the count is final
    assert not [t for t in set(threading.enumerate()) - before if t.is_alive()]
    assert len(batches) == seen  # nothing runs after the close


def test_refuses_bad_input(states):
    _, _, paths, _ = states
    with pytest.raises(ValueError, match="at least 2"):
        series_tiled(paths[:1], PARAMS)
    with pytest.raises(ValueError, match="strategy"):
        series_tiled(paths, PARAMS, strategy="sideways")
    with pytest.raises(ValueError, match="whole voxels"):
        series_tiled(paths, PARAMS, grid=((10.5, 10, 10), (8, 8, 8), (2, 2, 2)))


def test_a_distributed_cluster_gives_the_local_series(states):
    import distributed

    _, _, paths, _ = states
    paths = paths[:2]  # one pair: its correlation, correction and residual on the cluster
    options = dict(strategy="total", correct_total=True, correction_options=CORRECTION)
    local = series_tiled(paths, PARAMS, **options, **RUN)
    with distributed.LocalCluster(
        n_workers=1, processes=False, threads_per_worker=2, dashboard_address=None
    ) as cluster:
        with distributed.Client(cluster) as client:
            remote = series_tiled(
                paths, PARAMS, scheduler=client, **options,
                **{k: v for k, v in RUN.items() if k != "workers"},
            )  # fmt: skip
    for x, y in zip(local.totals + local.increments, remote.totals + remote.increments):
        assert y.metadata["tiled"]["scheduler"] != "local threads"
        np.testing.assert_array_equal(y.status, x.status)
        np.testing.assert_allclose(y.u, x.u, rtol=0, atol=1e-9)
    assert [r["mean_gray_residual"] for r in remote.summary()] == pytest.approx(
        [r["mean_gray_residual"] for r in local.summary()], rel=1e-9, nan_ok=True
    )
