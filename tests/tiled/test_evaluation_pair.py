"""The pair's map and r0 block by block (tiled/evaluation_pair.py); the whole evaluation's
equality with the in-memory one is tested in test_evaluation.py."""

from __future__ import annotations

import numpy as np

from napari_dvc_correct.tiled.evaluation_pair import region_block


class _Lazy:
    def __init__(self, values):
        self.values = values

    def read_region(self, block):
        return self.values[block]


def test_the_region_of_a_block_is_read_from_an_array_or_a_lazy_volume():
    region = np.zeros((4, 5, 6), np.uint8)
    region[1:3, 2:4, :] = 1
    block = (slice(1, 4), slice(0, 5), slice(2, 6))
    expected = region[block] != 0
    assert region_block(None, block) is None
    assert np.array_equal(region_block(region, block), expected)
    assert np.array_equal(region_block(_Lazy(region), block), expected)
    assert region_block(region, block).dtype == bool
