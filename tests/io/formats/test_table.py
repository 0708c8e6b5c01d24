"""Plain CSV/TSV tables (io/formats/table.py): names, units, xyz order, round trips."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.scattered import ScatteredField, to_grid
from napari_dvc_correct.io.formats import read_field, read_points, sniff_format, table, write_field


def test_named_columns_in_any_order_with_units(known, tmp_path, scattered_points):
    u = known.affine(scattered_points)
    voxel = np.array([0.02, 0.01, 0.01])  # mm per voxel (z, y, x)
    rows = [
        f"{p[2] * voxel[2]},{d[0] * 1000 * voxel[0]},{p[0]},{p[1]},{d[1]},{d[2]}"
        for p, d in zip(scattered_points, u)
    ]
    path = tmp_path / "f.csv"
    path.write_text(
        "# from a script\nx [mm],uz (um),z [voxel],y,uy [px],ux\n" + "\n".join(rows) + "\n"
    )
    assert sniff_format(path) == "table"
    points = read_points(path, voxel_size=voxel)
    np.testing.assert_allclose(points.points, scattered_points, atol=1e-9)
    np.testing.assert_allclose(points.u, u, atol=1e-9)


def test_dic_names_u_v_w_are_along_x_y_z(known, tmp_path, scattered_points):
    d = known.translation(scattered_points)
    rows = [f"{p[2]}\t{p[1]}\t{p[0]}\t{q[2]}\t{q[1]}\t{q[0]}" for p, q in zip(scattered_points, d)]
    path = tmp_path / "f.tsv"
    path.write_text("X\tY\tZ\tU\tV\tW\n" + "\n".join(rows) + "\n")
    assert sniff_format(path) == "table"
    points = read_points(path)
    np.testing.assert_allclose(points.points, scattered_points)
    np.testing.assert_allclose(points.u, np.broadcast_to(known.shift, (30, 3)))


def test_headerless_tables_follow_the_xyz_switch(known, tmp_path, grid_points):
    u = known.affine(grid_points)
    zyx = tmp_path / "zyx.txt"
    np.savetxt(zyx, np.column_stack([grid_points, u]))
    xyz = tmp_path / "xyz.txt"
    np.savetxt(xyz, np.column_stack([grid_points[:, ::-1], u[:, ::-1]]))
    a = read_field(zyx, "table")
    b = read_field(xyz, "table", xyz=True)
    np.testing.assert_allclose(a.displacement, known.affine(a.points), atol=1e-9)
    np.testing.assert_allclose(b.u, a.u, atol=1e-12)


def test_physical_units_need_the_voxel_size(known, tmp_path):
    path = tmp_path / "f.csv"
    path.write_text("z [mm],y [mm],x [mm],uz,uy,ux\n1,2,3,0,0,0\n")
    with pytest.raises(ValueError, match="voxel size"):
        read_points(path)
    path.write_text("z [inch],y,x,uz,uy,ux\n1,2,3,0,0,0\n")
    with pytest.raises(ValueError, match="unknown unit"):
        read_points(path)
    path.write_text("z,y,x,uz,uy\n1,2,3,0,0\n")
    with pytest.raises(ValueError, match="missing column"):
        read_points(path)


def test_one_based_positions(known, tmp_path, scattered_points):
    path = tmp_path / "f.csv"
    rows = [f"{p[0] + 1},{p[1] + 1},{p[2] + 1},0,0,0" for p in scattered_points]
    path.write_text("z,y,x,uz,uy,ux\n" + "\n".join(rows) + "\n")
    np.testing.assert_allclose(read_points(path, index_base=1).points, scattered_points)


@pytest.mark.parametrize(
    "name,options", [("g.csv", {}), ("g.tsv", {"xyz": True}), ("m.csv", {"voxel_size": 0.05})]
)
def test_round_trip(known, tmp_path, grid_points, name, options):
    field = to_grid(ScatteredField(grid_points, known.affine(grid_points), zncc=np.full(60, 0.7)))
    write_field(field, tmp_path / name, "table", **options)
    read_options = {"voxel_size": options["voxel_size"]} if "voxel_size" in options else {}
    back = read_field(tmp_path / name, "table", **read_options)
    assert back.same_grid(field)
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)
    np.testing.assert_array_equal(back.status, field.status)
    np.testing.assert_allclose(back.zncc, 0.7, atol=1e-6)


def test_scattered_round_trip(known, tmp_path, scattered_points):
    field = ScatteredField(scattered_points, known.affine(scattered_points))
    table.write(field, tmp_path / "s.csv")
    back = read_points(tmp_path / "s.csv")
    np.testing.assert_allclose(back.points, scattered_points, atol=1e-6)
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)


def test_header_only_and_ragged_files_are_refused_with_their_name(tmp_path):
    """Issue 27 item 6: a header and no rows, or a short row, is a ValueError naming the file."""
    cases = {
        "h.tsv": "NodeNumber\tZpos\tYpos\tXpos\tZdisp\tYdisp\tXdisp\treturnStatus\n",
        "h.disp": "n\tx\ty\tz\tstatus\tobjmin\tu\tv\tw\n",
        "h.csv": "z,y,x,uz,uy,ux\n",
        "short.csv": "z,y,x,uz,uy,ux\n1,2,3,0,0,0\n1,2,3,0\n",
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match=name.replace(".", r"\.")):
            read_points(tmp_path / name)


def test_empty_cells_are_nan_and_valid_zero_is_not_usable(tmp_path):
    """pyALDVC's CSV writes non-finite values as empty cells and a ``valid`` flag."""
    path = tmp_path / "frame.csv"
    path.write_text(
        "x,y,z,valid,disp_u,disp_v,disp_w,exx\n1.0,2.0,3.0,1,0.5,0.25,0.125,\n"
        "4.0,5.0,6.0,0,0.5,0.25,0.125,0.1\n"
    )
    points = read_points(path)
    assert np.allclose(points.points[0], [3.0, 2.0, 1.0])
    assert np.allclose(points.u[0], [0.125, 0.25, 0.5])
    assert points.valid.tolist() == [True, False]


def test_a_point_given_twice_with_two_displacements_is_refused(tmp_path):
    """Issue 27 item 11: which of two displacements holds cannot be guessed; the grid is not
    made silently from one of them. Identical repeated rows are harmless."""
    rows = ["z,y,x,uz,uy,ux"] + [f"{z},{y},{x},0.1,0.2,0.3" for z in (4, 8) for y in (4, 8)
                                 for x in (4, 8)]  # fmt: skip
    path = tmp_path / "twice.csv"
    path.write_text("\n".join([*rows, "8,4,8,0.1,0.2,0.3"]) + "\n")
    assert read_points(path).n_points == 9
    path.write_text("\n".join([*rows, "8,4,8,0.1,2.5,0.3"]) + "\n")
    with pytest.raises(ValueError, match=r"twice.csv: 1 point\(s\) appear more than once .*8\.0, "
                                         r"4\.0, 8\.0\) in rows 6, 9"):  # fmt: skip
        read_points(path)
    with pytest.raises(ValueError, match="appear more than once"):
        read_field(path)
