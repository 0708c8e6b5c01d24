"""Slabs along z: whole planes, at most the voxels asked for, covering the volume once."""

import pytest

from napari_dvc_correct.engine.slabs import SLAB_VOXELS, iter_slabs


@pytest.mark.parametrize(
    ("shape", "voxels", "starts"),
    [
        ((30, 33, 41), 33 * 41 * 4, [0, 4, 8, 12, 16, 20, 24, 28]),  # 4 planes a slab
        ((5, 10, 10), 350, [0, 3]),  # 3 planes fit in 350 voxels
        ((3, 100, 100), 10, [0, 1, 2]),  # a plane larger than asked: one plane a slab
        ((7, 4, 4), SLAB_VOXELS, [0]),  # small volume: one slab
    ],
)
def test_slabs_cover_the_volume_in_order_without_overlap(shape, voxels, starts):
    slabs = list(iter_slabs(shape, voxels))
    assert [s.start for s in slabs] == starts
    assert [s.stop for s in slabs] == [*starts[1:], shape[0]]
    plane = shape[1] * shape[2]
    assert all((s.stop - s.start) * plane <= max(voxels, plane) for s in slabs)
