"""validate_volume: what the engine refuses (with the volume's name), and what it passes untouched."""

import numpy as np
import pytest
from numpy.lib.stride_tricks import as_strided

from napari_dvc_correct.engine.validation import validate_volume


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.float32, np.float64, bool])
def test_good_volumes_come_back_as_the_same_object(dtype):
    volume = np.ones((4, 5, 6), dtype)
    before = volume.copy()
    assert validate_volume(volume) is volume
    np.testing.assert_array_equal(volume, before)


def test_a_nested_list_becomes_an_array():
    out = validate_volume([[[1.0, 2.0], [3.0, 4.0]]])
    assert isinstance(out, np.ndarray) and out.shape == (1, 2, 2)


@pytest.mark.parametrize("shape", [(8, 8), (8,), (2, 3, 4, 5), ()])
def test_not_three_dimensional(shape):
    with pytest.raises(ValueError, match=r"reference must be a 3-D volume \(z, y, x\), got shape"):
        validate_volume(np.zeros(shape), "reference")


@pytest.mark.parametrize("shape", [(0, 4, 4), (4, 0, 4), (4, 4, 0)])
def test_empty(shape):
    with pytest.raises(ValueError, match=r"mask is empty \(shape"):
        validate_volume(np.zeros(shape), "mask")


@pytest.mark.parametrize("dtype", [np.complex64, object, "U3", "datetime64[s]"])
def test_not_real_numbers(dtype):
    volume = np.zeros((3, 3, 3), dtype)
    with pytest.raises(ValueError, match="deformed must hold real numbers, got dtype"):
        validate_volume(volume, "deformed")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16])
def test_nan_and_inf(bad, dtype):
    volume = np.zeros((6, 7, 8), dtype)
    volume[5, 6, 7] = bad  # the very last voxel
    with pytest.raises(ValueError, match="scan.tif contains NaN or infinite values"):
        validate_volume(volume, "scan.tif")
    # the check can be turned off (and integers have no NaN to look for)
    assert validate_volume(volume, check_finite=False) is volume


def test_memory_mapped_volume_is_checked_and_returned_as_is(tmp_path):
    path = tmp_path / "volume.raw"
    volume = np.memmap(path, dtype=np.float32, mode="w+", shape=(48, 48, 48))
    volume[:] = 1.0
    volume.flush()
    readonly = np.memmap(path, dtype=np.float32, mode="r", shape=(48, 48, 48))
    out = validate_volume(readonly)
    assert out is readonly and isinstance(out, np.memmap)
    volume[47, 47, 47] = np.nan
    volume.flush()
    with pytest.raises(ValueError, match="volume contains NaN"):
        validate_volume(np.memmap(path, dtype=np.float32, mode="r", shape=(48, 48, 48)))


def test_nan_in_the_last_slab_of_a_large_volume_is_found():
    # 48 x 1024 x 1024 float32 (192 MiB) without the memory: each z-plane repeats one value, so
    # the volume is checked in slabs of 2**24 voxels (16 planes) and the NaN sits in the last one
    planes = np.ones(48, np.float32)
    large = as_strided(planes, shape=(48, 1024, 1024), strides=(4, 0, 0), writeable=False)
    assert validate_volume(large) is large
    planes[47] = np.nan
    with pytest.raises(ValueError, match="contains NaN or infinite values"):
        validate_volume(large)
    planes[47], planes[0] = 1.0, np.inf
    with pytest.raises(ValueError, match="contains NaN or infinite values"):
        validate_volume(large)
