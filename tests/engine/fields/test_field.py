import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import (
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)


def test_points_follow_origin_and_step():
    field = DisplacementField.zeros(origin=(1, 2, 3), step=(2, 3, 4), shape=(2, 2, 2))
    assert np.allclose(field.points[-1], [3, 5, 7])


def test_valid_combines_status_provenance_and_finiteness():
    field = DisplacementField.zeros((0, 0, 0), (1, 1, 1), (1, 1, 4))
    field.status[0, 0, 1] = Status.DIVERGED
    field.status[0, 0, 2] = Status.DIVERGED
    field.provenance[0, 0, 2] = Provenance.REPLACED
    field.u[0, 0, 3, 0] = np.nan
    assert field.valid.tolist() == [[[True, False, True, False]]]
    assert Status.MAX_ITERATIONS.label == "max iterations"


@pytest.mark.parametrize(
    "kwargs", [{"u": np.zeros((2, 2, 3))}, {"step": (0, 1, 1)}, {"zncc": np.zeros((1, 1, 1))}]
)
def test_bad_fields_are_refused(kwargs):
    values = {"origin": (0, 0, 0), "step": (1, 1, 1), "u": np.zeros((2, 2, 2, 3))} | kwargs
    with pytest.raises(ValueError):
        DisplacementField(**values)


def test_grid_keeps_subvolumes_inside_and_is_centred():
    origin, step, shape = grid_for_volume((50, 60, 70), 21, 8)
    for o, s, n, size in zip(origin, step, shape, (50, 60, 70)):
        assert o >= 12 and o + s * (n - 1) + 12 <= size - 1  # 2-voxel margin
        assert o + s * n + 12 > size - 1  # one more node would not fit
    with pytest.raises(ValueError, match="larger than the volume"):
        grid_for_volume((10, 40, 40), 21, 8)


def test_node_counts_agree_with_the_counts_by_status():
    """A usable fraction of 1.000 next to "diverged 5" is right when those 5 were filled in: the
    counts say so (matched + filled = usable; the filled keep their failed status)."""
    from napari_dvc_correct.engine.fields.field import Provenance, Status, node_counts

    field = DisplacementField.zeros((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (10, 10, 10))
    flat_status = field.status.reshape(-1)
    flat_provenance = field.provenance.reshape(-1)
    flat_status[:5] = Status.DIVERGED
    flat_provenance[:5] = Provenance.REPLACED  # cleaning filled them in
    flat_status[5:8] = Status.DIVERGED  # not filled
    flat_status[8:10] = Status.MAX_ITERATIONS
    flat_status[10:14] = Status.MASKED
    counts = field.node_counts()
    assert counts == node_counts(field.status, field.provenance, field.u)
    assert (counts.total, counts.matched, counts.filled) == (1000, 988, 5)
    assert counts.usable == int(field.valid.sum()) == 993
    assert counts.usable_fraction == pytest.approx(field.valid.mean())
    assert counts.statuses == {"converged": 986, "max iterations": 2, "diverged": 8, "masked": 4}
    assert counts.text() == (
        "usable 993 of 1000 nodes (0.993): 988 matched, 5 filled in; status: converged 986, "
        "max iterations 2, diverged 8, masked 4"
    )
    # a good status with a non-finite value is not usable, hence not matched either
    field.u[0, 0, 9] = np.nan
    assert field.node_counts().matched == 987


def test_a_run_without_a_region_and_many_textureless_nodes_suggests_one():
    field = DisplacementField.zeros((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (10, 10, 10))
    flat_status = field.status.reshape(-1)
    flat_status[:49] = Status.LOW_TEXTURE  # 4.9 %: below the share, no hint
    assert field.node_counts().region_hint(region_given=False) is None
    flat_status[49] = Status.LOW_TEXTURE  # 5 %
    hint = field.node_counts().region_hint(region_given=False)
    assert hint.startswith("50 of 1000 nodes (5 %) found no texture") and "region" in hint
    assert field.node_counts().region_hint(region_given=True) is None  # the user gave one
