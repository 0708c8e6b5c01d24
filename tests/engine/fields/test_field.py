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
