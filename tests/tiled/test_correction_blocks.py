"""The out-of-core correction's block tasks: the scans' statistics and the mask as the engine
reads it, block by block equal to the whole volume."""

import itertools

import numpy as np

from napari_dvc_correct.io.lazy import ArrayVolume
from napari_dvc_correct.tiled import correction_blocks as B


def _blocks(shape, size):
    starts = [range(0, n, s) for n, s in zip(shape, size)]
    for corner in itertools.product(*starts):
        yield tuple(slice(c, min(c + s, n)) for c, s, n in zip(corner, size, shape))


def test_block_statistics_add_up_to_the_whole_volume_s():
    volume = np.random.default_rng(3).normal(100.0, 10.0, (13, 17, 19)).astype(np.float32)
    volume[2, 3, 4] = np.nan
    volume[10, 1, 1] = np.inf
    lazy = ArrayVolume(volume)
    parts = [B.statistics_block(lazy, 4, box) for box in _blocks(volume.shape, (5, 6, 7))]
    samples = np.concatenate([p[0] for p in parts])
    whole = volume[::4, ::4, ::4].ravel()
    np.testing.assert_array_equal(np.sort(samples), np.sort(whole))  # the same lattice
    finite = np.isfinite(volume)
    assert sum(p[2] for p in parts) == finite.sum() and sum(p[3] for p in parts) == 2
    assert sum(p[1] for p in parts) == np.sum(volume[finite], dtype=np.float64)


def test_the_mask_reads_as_zero_or_one():
    mask = ArrayVolume(np.array([[[0, 3, -1, 0]]], np.int16))
    nonzero = B.NonZero(mask)
    assert nonzero.shape == (1, 1, 4) and nonzero.dtype == np.float32
    region = (slice(0, 1), slice(0, 1), slice(1, 4))
    np.testing.assert_array_equal(nonzero.read_region(region), [[[1.0, 1.0, 0.0]]])
