"""Lazy volumes: every reader returns the same regions as the array it stores."""

import pickle

import numpy as np
import pytest
import tifffile
import zarr

from napari_dvc_correct.io.lazy import (
    ArrayVolume,
    LazyVolume,
    NpyVolume,
    SliceFolderVolume,
    TiffVolume,
    ZarrVolume,
    as_lazy,
    iter_blocks,
    normalize_slices,
    open_volume,
)

REGIONS = [
    (slice(0, 12), slice(0, 10), slice(0, 9)),
    (slice(3, 7), slice(2, 9), slice(4, 5)),
    (slice(11, 12), slice(9, 10), slice(0, 9)),
    (slice(None), slice(None), slice(None)),
]


@pytest.fixture(scope="module")
def volume():
    rng = np.random.default_rng(3)
    return rng.integers(0, 60000, size=(12, 10, 9)).astype(np.uint16)


def _check_regions(lazy, volume):
    assert isinstance(lazy, LazyVolume)
    assert lazy.shape == volume.shape
    assert lazy.dtype == volume.dtype
    for region in REGIONS:
        block = lazy.read_region(region)
        assert block.dtype == np.float32 and block.flags.c_contiguous
        np.testing.assert_array_equal(block, volume[region].astype(np.float32))


def test_array_volume_regions_and_indexing(volume):
    lazy = ArrayVolume(volume)
    _check_regions(lazy, volume)
    np.testing.assert_array_equal(lazy[2:4], volume[2:4].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(lazy), volume.astype(np.float32))


def test_contiguous_tiff_is_memory_mapped(tmp_path, volume):
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, volume)
    lazy = open_volume(path)
    assert isinstance(lazy, TiffVolume) and lazy.memory_mapped
    _check_regions(lazy, volume)


def test_compressed_tiff_is_read_through_zarr(tmp_path, volume):
    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, volume, compression="zlib")
    lazy = open_volume(path)
    assert isinstance(lazy, TiffVolume) and not lazy.memory_mapped
    _check_regions(lazy, volume)


def test_npy_volume(tmp_path, volume):
    path = tmp_path / "volume.npy"
    np.save(path, volume)
    lazy = open_volume(path)
    assert isinstance(lazy, NpyVolume)
    _check_regions(lazy, volume)
    fortran = tmp_path / "fortran.npy"
    np.save(fortran, np.asfortranarray(volume))
    _check_regions(open_volume(fortran), volume)


def test_zarr_array(tmp_path, volume):
    path = tmp_path / "volume.zarr"
    zarr.create_array(str(path), data=volume, chunks=(4, 5, 5))
    lazy = open_volume(path)
    assert isinstance(lazy, ZarrVolume)
    assert lazy.chunks == (4, 5, 5)
    _check_regions(lazy, volume)


def test_ome_zarr_first_level_by_default(tmp_path, volume):
    path = tmp_path / "image.ome.zarr"
    group = zarr.open_group(str(path), mode="w", zarr_format=2)
    group.create_array("0", data=volume[None, None], chunks=(1, 1, 6, 5, 5))
    coarse = volume[::2, ::2, ::2]
    group.create_array("1", data=coarse[None, None], chunks=(1, 1, 6, 5, 5))
    group.attrs["multiscales"] = [
        {
            "version": "0.4",
            "axes": [{"name": a} for a in "tczyx"],
            "datasets": [{"path": "0"}, {"path": "1"}],
        }
    ]
    _check_regions(open_volume(path), volume)
    second = open_volume(path, level=1)
    assert second.shape == coarse.shape
    np.testing.assert_array_equal(second.read_region(REGIONS[3]), coarse.astype(np.float32))
    with pytest.raises(ValueError, match="level 5 does not exist"):
        open_volume(path, level=5)


def test_ome_zarr_v05_metadata(tmp_path, volume):
    path = tmp_path / "image.zarr"
    group = zarr.open_group(str(path), mode="w")
    group.create_array("s0", data=volume, chunks=(6, 5, 5))
    group.attrs["ome"] = {"version": "0.5", "multiscales": [{"datasets": [{"path": "s0"}]}]}
    _check_regions(open_volume(path), volume)


def test_zarr_group_without_multiscales_needs_a_component(tmp_path, volume):
    path = tmp_path / "group.zarr"
    group = zarr.open_group(str(path), mode="w")
    group.create_array("a", data=volume)
    group.create_array("b", data=volume)
    with pytest.raises(ValueError, match="name the array"):
        open_volume(path)
    _check_regions(open_volume(path, component="b"), volume)


def test_slice_folder_in_natural_order(tmp_path, volume):
    folder = tmp_path / "slices"
    folder.mkdir()
    for z, plane in enumerate(volume):
        tifffile.imwrite(folder / f"slice_{z}.tif", plane)  # slice_10 sorts after slice_9
    lazy = open_volume(folder)
    assert isinstance(lazy, SliceFolderVolume)
    _check_regions(lazy, volume)


def test_slice_folder_with_a_wrong_slice(tmp_path, volume):
    folder = tmp_path / "slices"
    folder.mkdir()
    for z, plane in enumerate(volume[:3]):
        tifffile.imwrite(folder / f"s{z:03d}.tif", plane)
    tifffile.imwrite(folder / "s003.tif", volume[3, :5])
    lazy = open_volume(folder)
    with pytest.raises(ValueError, match="same shape"):
        lazy.read_region((slice(2, 4), slice(None), slice(None)))


def test_file_volumes_pickle_without_their_handles(tmp_path, volume):
    tiff = tmp_path / "stack.tif"
    tifffile.imwrite(tiff, volume, compression="zlib")
    store = tmp_path / "volume.zarr"
    zarr.create_array(str(store), data=volume, chunks=(4, 5, 5))
    for lazy in (open_volume(tiff), open_volume(store)):
        lazy.read_region(REGIONS[1])  # opens the handle
        clone = pickle.loads(pickle.dumps(lazy))
        assert clone._handle is None
        _check_regions(clone, volume)


def test_open_volume_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_volume(tmp_path / "missing.tif")
    other = tmp_path / "volume.raw"
    other.write_bytes(b"\0" * 8)
    with pytest.raises(ValueError, match="unsupported volume format"):
        open_volume(other)
    not_tiff = tmp_path / "fake.tif"
    not_tiff.write_bytes(b"not a tiff")
    with pytest.raises(ValueError, match="not a readable TIFF"):
        open_volume(not_tiff)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no .tif slices"):
        open_volume(empty)
    with pytest.raises(ValueError, match="3-D"):
        ArrayVolume(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="real numbers"):
        ArrayVolume(np.zeros((2, 2, 2), complex))


def test_as_lazy_accepts_paths_arrays_and_volumes(tmp_path, volume):
    path = tmp_path / "volume.npy"
    np.save(path, volume)
    assert isinstance(as_lazy(path), NpyVolume)
    assert isinstance(as_lazy(str(path)), NpyVolume)
    wrapped = as_lazy(volume)
    assert isinstance(wrapped, ArrayVolume)
    assert as_lazy(wrapped) is wrapped


def test_normalize_slices():
    assert normalize_slices((slice(None), slice(2, None), (1, 3)), (5, 6, 7)) == (
        slice(0, 5),
        slice(2, 6),
        slice(1, 3),
    )
    with pytest.raises(ValueError, match="step 1"):
        normalize_slices((slice(0, 4, 2), slice(None), slice(None)), (5, 5, 5))
    with pytest.raises(ValueError, match="empty region"):
        normalize_slices((slice(3, 3), slice(None), slice(None)), (5, 5, 5))
    with pytest.raises(ValueError, match="3 slices"):
        normalize_slices((slice(None),), (5, 5, 5))


@pytest.mark.parametrize("shape", [(13, 11, 7), (64, 40, 33), (5, 3, 2)])
@pytest.mark.parametrize("align", [1, 2, 4])
def test_iter_blocks_tiles_the_volume_once_on_aligned_edges(shape, align):
    count = np.zeros(shape[:2], int)
    for z, y in iter_blocks(shape, block_voxels=300, align=align):
        assert z.start % align == 0 and y.start % align == 0
        count[z, y] += 1
    assert np.all(count == 1)
