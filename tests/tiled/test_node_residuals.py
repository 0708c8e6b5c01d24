"""The out-of-core judge's node blocks: the memory a block of nodes needs, from its geometry."""

import pytest

from napari_dvc_correct.tiled import node_residuals as N


def test_a_node_block_s_bytes_are_its_region_s_voxels_times_the_working_bytes():
    # 4 nodes a step 5 apart, half-size 7, a reach of 2: edge 4·5 + 15 = 35, grown by
    # 2·(2 + the gradient's reach 4) = 12 on each axis
    bytes_ = N.node_bytes((5, 5, 5), 4, 7, 2.0)
    assert bytes_ == pytest.approx(47.0**3 * N.BYTES_PER_NODE_REGION_VOXEL)
    assert N.GRADIENT_REACH == 4
    # a larger block, step or subvolume needs more
    assert N.node_bytes((5, 5, 5), 8, 7, 2.0) > bytes_
    assert N.node_bytes((5, 5, 10), 4, 7, 2.0) > bytes_
    assert N.node_bytes((5, 5, 5), 4, 10, 2.0) > bytes_


def test_a_node_block_s_gradient_is_the_box_mean_of_the_gray_gradient():
    from types import SimpleNamespace

    import numpy as np

    from napari_dvc_correct.engine.fields.field import DisplacementField
    from napari_dvc_correct.io.lazy import ArrayVolume

    x = np.arange(32, dtype=np.float32)
    ramp = np.broadcast_to(3.0 * x, (32, 32, 32)).copy()  # |grad G| = 3 away from the faces
    whole = (slice(0, 32),) * 3
    nodes = DisplacementField.zeros((10.0, 10.0, 10.0), (5.0, 5.0, 5.0), (3, 3, 3))
    job = SimpleNamespace(region=whole, inner=whole, nodes=nodes, halves=(2,), index=7)
    index, means = N._node_gradient_block(ArrayVolume(ramp), job)
    assert index == 7 and means.shape == (3, 3, 3)
    np.testing.assert_allclose(means, 3.0, rtol=1e-3)  # the Gaussian is truncated at 4 sigma
