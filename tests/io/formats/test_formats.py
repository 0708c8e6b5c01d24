"""One entry for every format: the format told by suffix and header, round trips, clear refusals."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.scattered import ScatteredField
from napari_dvc_correct.io import formats as F


def _field() -> DisplacementField:
    field = DisplacementField.zeros((8.0, 9.0, 10.0), (6.0, 5.0, 4.0), (3, 4, 5))
    field.u = field.points.reshape((3, 4, 5, 3)) * np.array([0.01, -0.02, 0.03]) + 0.5
    return field


@pytest.mark.parametrize(
    ("name", "fmt"),
    [("f.tsv", "spam"), ("f.disp", "idvc"), ("f.mat", "aldvc"), ("f.csv", "table"),
     ("f.npz", "npz")],
)  # fmt: skip
def test_each_suffix_writes_its_format_and_reads_back_on_the_grid(tmp_path, name, fmt):
    field = _field()
    path = F.write_field(field, tmp_path / name)
    assert F.sniff_format(path) == fmt
    back = F.read_field(path)
    assert back.shape == field.shape and back.origin == field.origin and back.step == field.step
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)
    assert F.default_suffix(fmt) in (path.suffix, ".npz")


def test_an_npz_is_ours_or_pyaldvcs(tmp_path):
    F.write_field(_field(), tmp_path / "ours.npz")
    F.write_field(_field(), tmp_path / "aldvc.npz", format="aldvc")
    assert F.sniff_format(tmp_path / "ours.npz") == "npz"
    assert F.sniff_format(tmp_path / "aldvc.npz") == "aldvc"
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="neither ours"):
        F.sniff_format(tmp_path / "other.npz")
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a valid .npz"):
        F.sniff_format(tmp_path / "broken.npz")


def test_refusals_name_the_file_and_what_to_do(tmp_path):
    with pytest.raises(FileNotFoundError, match="field file not found"):
        F.sniff_format(tmp_path / "missing.csv")
    with pytest.raises(ValueError, match="cannot tell the format"):
        F.write_field(_field(), tmp_path / "f.xyz")
    with pytest.raises(ValueError, match="unknown field format 'vtk'"):
        F.read_points(F.write_field(_field(), tmp_path / "f.csv"), format="vtk")
    (tmp_path / "empty.csv").write_text("z,y,x,uz,uy,ux\n")
    with pytest.raises(ValueError, match="holds no points"):
        F.read_points(tmp_path / "empty.csv")
    with pytest.raises(ValueError, match="do not apply to the npz format"):
        F.read_points(F.write_field(_field(), tmp_path / "f.npz"), bin_ratio=2)


def test_a_point_given_twice_with_two_values_is_refused():
    points = np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    same = ScatteredField(points=points, u=np.array([[0.1, 0, 0], [0.1, 0, 0], [0.2, 0, 0]]))
    F.refuse_conflicting_duplicates("f.csv", same)  # repeated identical rows are harmless
    other = ScatteredField(points=points, u=np.array([[0.1, 0, 0], [0.3, 0, 0], [0.2, 0, 0]]))
    with pytest.raises(ValueError, match=r"f.csv: 1 point\(s\) .* in rows 1, 2"):
        F.refuse_conflicting_duplicates("f.csv", other)


@pytest.mark.parametrize("suffix", [".h5", ".hdf5", ".vti", ".vtk", ".vtu", ".tif", ".TIFF"])
def test_an_export_for_other_programs_is_refused_in_words(tmp_path, suffix):
    # `export` writes these for ParaView, ImageJ...; given back as --field they used to fail
    # with "not a table of numbers ('utf-8' codec can't decode byte 0x89 ...)"
    path = tmp_path / f"corrected{suffix}"
    path.write_bytes(b"\x89HDF\r\n\x1a\n\x00\xff\xfe binary")
    with pytest.raises(ValueError, match=r"export for other programs.*\.dvcfield or \.npz"):
        F.read_points(path)


def test_a_position_that_is_not_a_number_is_refused_with_the_file_and_the_point(tmp_path):
    # used to say only "point positions must be finite", with neither the file nor the row
    path = tmp_path / "field.csv"
    rows = "\n".join(f"{z},4,5,0.1,0.2,0.3" for z in range(7)) + "\nnan,4,5,0.1,0.2,0.3\n"
    path.write_text("z,y,x,uz,uy,ux\n" + rows)
    with pytest.raises(ValueError, match=r"field\.csv: point positions must be finite: 1 of 8"):
        F.read_points(path)
    with pytest.raises(ValueError, match=r"the first is point 7 counted from 0"):
        F.read_points(path)


def test_points_in_one_plane_are_refused_with_the_files_name(tmp_path):
    # CCPi's repository .disp holds 5 points in one plane; File ▸ Open in napari said only
    # "the field's usable points are all in one plane or line ..." without the file
    path = tmp_path / "plane.csv"
    rows = [(2, 3), (9, 3), (2, 8), (9, 9), (5, 6)]  # scattered, not a grid
    path.write_text("z,y,x,uz,uy,ux\n" + "".join(f"5,{y},{x},0,0,1\n" for y, x in rows))
    with pytest.raises(ValueError, match=r"plane\.csv: .*one plane"):
        F.read_field(path)
