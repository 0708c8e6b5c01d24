"""The format modules' shared helpers: axis order, unusable nodes, text tables."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField, Status
from napari_dvc_correct.engine.fields.scattered import ScatteredField
from napari_dvc_correct.io.formats import _common as C


def test_axis_order_flips_are_their_own_inverse():
    zyx = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(C.flip_vectors(zyx), [[3.0, 2.0, 1.0]])
    gradient = np.arange(9.0).reshape(1, 3, 3)  # du_z/dX_x is [0, 0, 2]
    flipped = C.flip_tensors(gradient)
    assert flipped[0, 0, 2] == 6.0 and flipped[0, 2, 0] == 2.0  # rows and columns reversed
    np.testing.assert_array_equal(C.flip_tensors(flipped), gradient)


def test_unusable_nodes_become_nan_in_a_copy():
    field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (2, 2, 2))
    field.u[:] = 1.0
    field.gradient = np.zeros((2, 2, 2, 3, 3))
    assert C.unusable_as_nan(field) is field  # nothing to change: the field itself
    field.status[0, 1, 1] = Status.DIVERGED
    out = C.unusable_as_nan(field)
    assert np.isnan(out.u[0, 1, 1]).all() and np.isnan(out.gradient[0, 1, 1]).all()
    assert np.isfinite(out.u).sum() == 7 * 3 and field.u[0, 1, 1, 0] == 1.0  # input kept
    scattered = C.as_scattered(field)
    assert isinstance(scattered, ScatteredField) and scattered.n_points == 8
    assert C.as_scattered(scattered) is scattered
    with pytest.raises(TypeError, match="DisplacementField or ScatteredField"):
        C.as_scattered(np.zeros((8, 3)))


def test_named_tables_with_comments_empty_cells_and_bad_cells(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("# written by hand\n\nz,y,x,u\n1,2,3,0.5\n4,5,6,\n")
    assert C.first_line(path) == "z,y,x,u" and C.header_row(path) == 2
    names, rows = C.read_named_table(path, None)
    assert names == ["z", "y", "x", "u"]
    np.testing.assert_array_equal(rows[0], [1, 2, 3, 0.5])
    assert np.isnan(rows[1, 3])  # an empty cell
    np.testing.assert_array_equal(C.column(names, rows, "w", "u"), [0.5, np.nan])
    assert C.column(names, rows, "w", required=False) is None
    with pytest.raises(ValueError, match="missing column 'w'"):
        C.column(names, rows, "w")
    header_only = tmp_path / "h.csv"
    header_only.write_text("a,b\n")
    assert C.read_named_table(header_only, ",")[1].shape == (0, 2)
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,oops\n")
    with pytest.raises(ValueError, match="bad.csv: not a table of numbers"):
        C.read_named_table(bad, ",")
    (tmp_path / "empty.csv").write_text("# nothing\n")
    with pytest.raises(ValueError, match="the file is empty"):
        C.read_named_table(tmp_path / "empty.csv", ",")
