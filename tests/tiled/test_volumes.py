"""Chunked voxel-wise outputs equal the in-memory ones of engine.fields.warp, on Zarr and TIFF."""

import numpy as np
import pytest
import tifffile
import zarr

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
from napari_dvc_correct.engine.evaluation import residual
from napari_dvc_correct.engine.evaluation.strain import equivalent_strain_field
from napari_dvc_correct.engine.fields import field_spline, warp
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.progress import run_to_completion
from napari_dvc_correct.io.lazy import ArrayVolume
from napari_dvc_correct.tiled.volumes import (
    mean_gray_residual_iter,
    sample_lazy,
    write_dense_field,
    write_equivalent_strain,
    write_gray_residual,
    write_pull_back,
    write_warp_forward,
)

SHAPE = (36, 40, 44)
BLOCK = (16, 16, 16)  # several blocks per axis, so regions are cropped


def _read(path):
    path = str(path)
    if path.endswith(".zarr"):
        return zarr.open_array(path, mode="r")[...]
    return tifffile.imread(path)


@pytest.fixture(scope="module")
def case():
    reference = synthetic.textured_volume(SHAPE, 2.0, seed=4)
    origin, step = (6.0, 6.0, 6.0), (6.0, 7.0, 8.0)
    grid_shape = (5, 5, 5)
    index = np.indices(grid_shape).reshape(3, -1).T
    points = np.asarray(origin) + index * np.asarray(step)
    u = np.stack(
        [
            0.8 + 0.02 * points[:, 0] + 0.4 * np.sin(points[:, 2] / 9.0),
            -1.3 + 0.01 * points[:, 1],
            0.5 - 0.015 * points[:, 2] + 0.3 * np.cos(points[:, 0] / 7.0),
        ],
        axis=1,
    ).reshape(*grid_shape, 3)
    field = DisplacementField(origin, step, u)
    deformed = warp.warp_forward(reference, field, cval=0.5)
    return reference, deformed, field


def test_sample_lazy_equals_whole_volume_sampling(case):
    reference = case[0]
    rng = np.random.default_rng(1)
    points = rng.uniform(-2, np.array(SHAPE) + 1, size=(500, 3))
    points[:5] = np.nan
    expected = sample(prefilter(reference), np.nan_to_num(points, nan=-10.0))
    got = sample_lazy(ArrayVolume(reference), points)
    both = np.isfinite(expected)
    assert np.array_equal(both, np.isfinite(got))
    assert both.sum() > 300
    assert np.max(np.abs(got[both] - expected[both])) < 1e-6


@pytest.mark.parametrize("outside", ["nan", "extrapolate"])
@pytest.mark.parametrize(
    "box",
    [(slice(0, 36), slice(0, 40), slice(0, 44)), (slice(10, 26), slice(3, 19), slice(20, 44))],
)
def test_lazy_pull_back_reads_one_region_and_equals_the_whole_volume(
    case, box, outside, monkeypatch
):
    from napari_dvc_correct.tiled import volumes

    reference, deformed, field = case
    spline = field_spline.FieldSpline.from_field(field)
    expected = warp.pull_back_block(warp.spline_sampler(prefilter(deformed)), spline, box, outside)
    reads = []
    lazy = ArrayVolume(deformed)
    original = lazy.read_region
    monkeypatch.setattr(
        lazy, "read_region", lambda region: reads.append(region) or original(region)
    )
    got = warp.pull_back_block(volumes.LazySampler(lazy), spline, box, outside)
    assert len(reads) == 1  # one region, no second read for missed voxels
    assert np.array_equal(np.isnan(got), np.isnan(expected)) and np.isfinite(expected).sum() > 1000
    assert np.nanmax(np.abs(got - expected)) < 1e-5 * np.abs(deformed).max()
    # a reach too short: the voxels whose positions leave the region are sampled otherwise
    monkeypatch.setattr(volumes, "displacement_reach", lambda spline, box: np.zeros(3, np.int64))
    reads.clear()
    short = warp.pull_back_block(volumes.LazySampler(lazy), spline, box, outside)
    whole = all(s.start == 0 and s.stop == n for s, n in zip(box, SHAPE))
    assert len(reads) == (1 if whole else 2)  # the whole volume leaves no voxel out
    assert np.array_equal(np.isnan(short), np.isnan(expected))
    assert np.nanmax(np.abs(short - expected)) < 1e-5 * np.abs(deformed).max()


@pytest.mark.parametrize(
    "box",
    [(slice(0, 36), slice(0, 40), slice(0, 44)), (slice(20, 36), slice(20, 40), slice(4, 30))],
)
def test_lazy_forward_warp_reads_one_region_and_equals_the_whole_volume(case, box, monkeypatch):
    from napari_dvc_correct.tiled import volumes

    reference, _, field = case
    spline = field_spline.FieldSpline.from_field(field)
    expected, hull = warp.warp_forward_block(warp.spline_sampler(prefilter(reference)), spline, box)
    reads = []
    lazy = ArrayVolume(reference)
    original = lazy.read_region
    monkeypatch.setattr(
        lazy, "read_region", lambda region: reads.append(region) or original(region)
    )
    got, got_hull = warp.warp_forward_block(volumes.LazySampler(lazy), spline, box)
    assert len(reads) == 1
    np.testing.assert_array_equal(got_hull, hull)
    assert np.array_equal(np.isnan(got), np.isnan(expected)) and np.isfinite(expected).sum() > 1000
    assert np.nanmax(np.abs(got - expected)) < 1e-5 * np.abs(reference).max()
    # a reach too short: the positions that leave the region are sampled from the volume
    monkeypatch.setattr(volumes, "displacement_reach", lambda spline, box: np.zeros(3, np.int64))
    reads.clear()
    short, _ = warp.warp_forward_block(volumes.LazySampler(lazy), spline, box)
    whole = all(s.start == 0 and s.stop == n for s, n in zip(box, SHAPE))
    assert len(reads) == (1 if whole else 2)
    assert np.array_equal(np.isnan(short), np.isnan(expected))
    assert np.nanmax(np.abs(short - expected)) < 1e-5 * np.abs(reference).max()


@pytest.mark.parametrize("suffix", [".zarr", ".tif"])
def test_pull_back_and_warp_forward(tmp_path, case, suffix):
    reference, deformed, field = case
    info = write_pull_back(
        ArrayVolume(deformed), field, tmp_path / f"pulled{suffix}", block_shape=BLOCK, cval=-1.0
    )
    assert info["blocks"] > 8
    expected = warp.pull_back(deformed, field, cval=-1.0)
    np.testing.assert_allclose(_read(info["path"]), expected, rtol=0, atol=1e-6)
    info = write_warp_forward(reference, field, tmp_path / f"forward{suffix}", block_shape=BLOCK)
    expected = warp.warp_forward(reference, field)
    got = _read(info["path"])
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("mode", ["reference", "loaded"])
def test_gray_residual_and_its_mean(tmp_path, case, mode):
    reference, deformed, field = case
    info = write_gray_residual(
        reference, deformed, field, tmp_path / "residual.zarr", mode=mode, block_shape=BLOCK
    )
    expected = residual.gray_residual(reference, deformed, field, mode=mode)
    got = _read(info["path"])
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
    assert info["mean"] == pytest.approx(np.nanmean(expected), rel=1e-5, abs=1e-6)
    assert info["mean"] < 0.02  # the field explains the pair


@pytest.mark.parametrize("mode, region", [("reference", "hull"), ("loaded", "volume")])
def test_mean_gray_residual_block_by_block_writes_nothing(tmp_path, case, mode, region):
    reference, deformed, field = case
    deformed = deformed + 0.01 * synthetic.textured_volume(SHAPE, 2.0, seed=9)  # a residual
    expected = residual.mean_gray_residual(reference, deformed, field, mode=mode, region=region)
    generator = mean_gray_residual_iter(
        reference, deformed, field, mode=mode, region=region, block_shape=BLOCK, workers=2
    )
    reports = []
    while True:
        try:
            reports.append(next(generator))
        except StopIteration as stop:
            got = stop.value
            break
    assert [r.done for r in reports] == list(range(1, 28)) and reports[-1].total == 27
    # float32 rounding of the regions' prefilters, the sums in another order
    assert got == pytest.approx(expected, rel=1e-5) and got > 1e-3
    assert not any(tmp_path.iterdir())


def test_mean_gray_residual_of_a_cancelled_run_stops_the_blocks(case):
    import threading

    reference, deformed, field = case
    generator = mean_gray_residual_iter(reference, deformed, field, block_shape=BLOCK, workers=1)
    assert next(generator).done == 1
    generator.close()
    assert not [t for t in threading.enumerate() if t.name == "dvc-dask-local"]
    assert run_to_completion(
        mean_gray_residual_iter(reference, deformed, field, workers=1)
    ) == pytest.approx(residual.mean_gray_residual(reference, deformed, field), rel=1e-5)


def test_dense_field_and_equivalent_strain(tmp_path, case):
    field = case[2]
    info = write_dense_field(field, SHAPE, tmp_path / "dense.zarr", block_shape=BLOCK)
    dense = _read(info["path"])
    assert dense.shape == (*SHAPE, 3)
    np.testing.assert_allclose(dense, field_spline.densify(field, shape=SHAPE), rtol=0, atol=1e-6)
    info = write_equivalent_strain(field, SHAPE, tmp_path / "strain.tif", block_shape=BLOCK)
    grid = equivalent_strain_field(field)
    expected = field_spline.densify(
        field_spline.FieldSpline(field.origin, field.step, grid[..., None]), shape=SHAPE
    )
    np.testing.assert_allclose(_read(info["path"]), expected[..., 0], rtol=0, atol=1e-6)


class _Broken(ArrayVolume):
    def read_region(self, slices):
        if slices[0].start and slices[0].start > 0:
            raise OSError("disk gone")
        return super().read_region(slices)


def test_a_failed_run_leaves_the_earlier_output(tmp_path, case):
    reference, deformed, field = case
    target = tmp_path / "pulled.zarr"
    write_pull_back(deformed, field, target, block_shape=BLOCK)
    before = _read(target)
    with pytest.raises(OSError, match="disk gone"):
        write_pull_back(_Broken(deformed), field, target, block_shape=BLOCK, cval=7.0)
    np.testing.assert_array_equal(_read(target), before)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pulled.zarr"]
    with pytest.raises(ValueError, match=r"\.zarr, \.tif or \.tiff"):
        write_pull_back(deformed, field, tmp_path / "pulled.h5")
