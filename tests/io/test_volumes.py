"""read_volume: every supported layout gives back the stored volume; every bad file is named."""

import re
from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_dvc_correct.io.volumes import read_volume


@pytest.fixture(scope="module")
def volume():
    return np.random.default_rng(0).integers(0, 60000, (12, 10, 9)).astype(np.uint16)


def _named(path):
    return re.escape(str(path))


# --- what it reads -----------------------------------------------------------------------------
def test_tiff_stack_is_memory_mapped(tmp_path, volume):
    path = tmp_path / "scan.tif"
    tifffile.imwrite(path, volume)
    out = read_volume(path)
    assert isinstance(out, np.memmap)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, volume)
    plain = read_volume(path, mmap=False)
    assert not isinstance(plain, np.memmap)
    np.testing.assert_array_equal(plain, volume)


def test_compressed_tiff_is_read_whole(tmp_path, volume):
    path = tmp_path / "scan.TIFF"  # the suffix is matched in any case
    tifffile.imwrite(path, volume, compression="zlib")
    np.testing.assert_array_equal(read_volume(path), volume)


def test_folder_of_slices_in_numeric_order(tmp_path, volume):
    # unpadded numbers: by name, slice_10 would come before slice_2
    for z, plane in enumerate(volume):
        tifffile.imwrite(tmp_path / f"slice_{z + 1}.tif", plane)
    (tmp_path / "notes.txt").write_text("not a slice")
    out = read_volume(tmp_path)
    assert out.shape == volume.shape
    np.testing.assert_array_equal(out, volume)


def test_npy_is_memory_mapped(tmp_path):
    volume = np.linspace(0.0, 1.0, 8 * 9 * 10, dtype=np.float32).reshape(8, 9, 10)
    path = tmp_path / "volume.npy"
    np.save(path, volume)
    out = read_volume(path)
    assert isinstance(out, np.memmap)
    np.testing.assert_array_equal(out, volume)
    assert not isinstance(read_volume(path, mmap=False), np.memmap)


def test_npz_with_one_array_or_one_named_volume(tmp_path, volume):
    one = tmp_path / "one.npz"
    np.savez(one, data=volume)
    np.testing.assert_array_equal(read_volume(one), volume)
    named = tmp_path / "named.npz"
    np.savez_compressed(named, mask=volume > 30000, volume=volume)
    np.testing.assert_array_equal(read_volume(named), volume)


# --- what it refuses ---------------------------------------------------------------------------
def test_missing_path(tmp_path):
    path = tmp_path / "nowhere.tif"
    with pytest.raises(FileNotFoundError, match=f"volume not found: {_named(path)}"):
        read_volume(path)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("broken.tif", b"II*\x00 this is not a tiff", "is not a readable TIFF file"),
        ("text.tif", b"hello, not an image", "is not a readable TIFF file"),
        ("broken.npy", b"\x93NUMPY garbage", "is not a readable .npy file"),
        ("broken.npz", b"PK\x03\x04 truncated zip", "is not a readable .npz file"),
    ],
)
def test_corrupt_files_are_named(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError, match=f"{_named(path)} {message}"):
        read_volume(path)


def test_pickled_npy_is_refused(tmp_path):
    path = tmp_path / "objects.npy"
    np.save(path, np.empty((2, 2, 2), dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=f"{_named(path)} is not a readable .npy file"):
        read_volume(path)


@pytest.mark.parametrize("suffix", [".npy", ".tif"])
def test_wrong_dimension_is_named(tmp_path, suffix):
    path = tmp_path / f"image{suffix}"
    image = np.zeros((10, 11), np.uint8)
    np.save(path, image) if suffix == ".npy" else tifffile.imwrite(path, image)
    with pytest.raises(ValueError, match=f"{_named(path)} must be a 3-D volume"):
        read_volume(path)


def test_npz_with_several_arrays_and_none_named_volume(tmp_path, volume):
    path = tmp_path / "several.npz"
    np.savez(path, a=volume, b=volume)
    with pytest.raises(ValueError, match=f"{_named(path)} holds 2 arrays \\(a, b\\)"):
        read_volume(path)


def test_nan_values_are_named(tmp_path):
    path = tmp_path / "nan.npy"
    volume = np.zeros((4, 4, 4), np.float32)
    volume[3, 3, 3] = np.nan
    np.save(path, volume)
    with pytest.raises(ValueError, match=f"{_named(path)} contains NaN"):
        read_volume(path)


def test_unsupported_suffix(tmp_path):
    path = tmp_path / "scan.png"
    path.write_bytes(b"\x89PNG")
    with pytest.raises(ValueError, match=f"{_named(path)}: unsupported volume format '.png'"):
        read_volume(path)


def test_folder_without_slices_or_with_mismatched_slices(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no slices here")
    with pytest.raises(ValueError, match=f"{_named(empty)} is a folder with no .tif slices"):
        read_volume(empty)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    tifffile.imwrite(mixed / "s1.tif", np.zeros((8, 8), np.uint8))
    tifffile.imwrite(mixed / "s2.tif", np.zeros((8, 9), np.uint8))
    with pytest.raises(ValueError, match=f"{_named(mixed)}: the TIFF slices could not be read"):
        read_volume(mixed)


def test_one_array_of_several_named_after_a_colon(tmp_path, volume):
    """rock_lower.npz holds reference, deformed and box_zyx: 'rock_lower.npz:deformed' reads one
    (user audit, item 5); the refusal without a name says how to give one."""
    from napari_dvc_correct.io.lazy import open_volume
    from napari_dvc_correct.io.volumes import split_member

    path = tmp_path / "pair.npz"
    np.savez(path, reference=volume, deformed=volume + 1, box_zyx=np.array([0, 12, 0, 10, 0, 9]))
    np.testing.assert_array_equal(read_volume(f"{path}:deformed"), volume + 1)
    np.testing.assert_array_equal(read_volume(f"{path}:reference"), volume)
    lazy = open_volume(f"{path}:deformed")
    np.testing.assert_array_equal(lazy.read_region((slice(None),) * 3), volume + 1)
    with pytest.raises(ValueError, match="name the one to read: .*pair.npz:reference"):
        read_volume(path)
    with pytest.raises(ValueError, match="holds no array 'nope'; it holds reference, deformed"):
        read_volume(f"{path}:nope")
    with pytest.raises(ValueError, match="3-D"):  # box_zyx is no volume
        read_volume(f"{path}:box_zyx")
    with pytest.raises(FileNotFoundError):
        read_volume(f"{tmp_path / 'absent.npz'}:reference")
    # only after an .npz, and never over a file that exists under the whole name
    assert split_member("scan.tif:x") == (Path("scan.tif:x"), None)
    odd = tmp_path / "odd.npz:x"
    np.savez(tmp_path / "odd.npz", x=volume)
    odd.write_bytes(b"")
    assert split_member(odd) == (odd, None)
