"""The volumes of a job (jobs/volumes.py): read whole in memory, opened lazily out of core."""

import numpy as np
import pytest

from napari_dvc_correct.engine.run_options import RunOptions
from napari_dvc_correct.jobs.volumes import load_volume


@pytest.fixture
def volume_file(tmp_path):
    volume = np.arange(6 * 7 * 8, dtype=np.float32).reshape(6, 7, 8)
    path = tmp_path / "scan.npy"
    np.save(path, volume)
    return volume, path


def test_in_memory_the_volume_is_read_whole_with_its_values(volume_file):
    volume, path = volume_file
    loaded = load_volume(path, RunOptions())
    assert isinstance(loaded, np.ndarray)
    np.testing.assert_array_equal(loaded, volume)


def test_out_of_core_the_volume_is_opened_lazily_and_reads_the_same_region(volume_file):
    volume, path = volume_file
    lazy = load_volume(path, RunOptions(tiled=True))
    assert not isinstance(lazy, np.ndarray)
    assert tuple(lazy.shape) == volume.shape
    np.testing.assert_array_equal(np.asarray(lazy[1:4, 2:5, 3:7]), volume[1:4, 2:5, 3:7])


def test_a_volume_with_nan_is_refused_in_memory(tmp_path):
    volume = np.ones((4, 4, 4), np.float32)
    volume[1, 2, 3] = np.nan
    np.save(tmp_path / "bad.npy", volume)
    with pytest.raises(ValueError):
        load_volume(tmp_path / "bad.npy", RunOptions())
