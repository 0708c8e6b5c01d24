"""The CLI on fields from other tools and on chosen points: --format, --out-format, --roi,
--cylinder, --origin, --points."""

import numpy as np
import pytest

from napari_dvc_correct.cli import main
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.fields.scattered import ScatteredField
from napari_dvc_correct.io.formats import read_field, read_points, write_field
from napari_dvc_correct.io.npz import load_field

SHAPE = (40, 40, 40)
SHIFT = np.array([1.4, -0.6, 2.2])
DVC = ["--subvolume", "15", "--step", "6", "--quiet"]


@pytest.fixture(scope="module")
def volumes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("volumes")
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=21), SHAPE, synthetic.translation(SHIFT)
    )
    paths = []
    for name, volume in (("ref", reference), ("def", deformed)):
        np.save(folder / f"{name}.npy", volume)
        paths.append(str(folder / f"{name}.npy"))
    return paths


def test_points_give_results_at_exactly_those_points(volumes, tmp_path):
    rng = np.random.default_rng(3)
    points = rng.uniform(10.0, 29.0, size=(12, 3))
    csv = tmp_path / "pois.csv"
    np.savetxt(csv, points[:, [2, 0, 1]], delimiter=",", header="x,z,y", comments="")
    out = tmp_path / "at_points.csv"
    assert main(["correlate", *volumes, "--points", str(csv), "--out", str(out), *DVC]) == 0
    result = read_points(out)
    np.testing.assert_allclose(result.points, points, atol=1e-6)
    assert result.valid.all()
    np.testing.assert_allclose(result.u, np.broadcast_to(SHIFT, (12, 3)), atol=0.05)
    npy = tmp_path / "pois.npy"
    np.save(npy, points)
    out2 = tmp_path / "at_points.disp"
    assert main(["correlate", *volumes, "--points", str(npy), "--out", str(out2), *DVC]) == 0
    np.testing.assert_allclose(read_points(out2).points, points, atol=1e-6)


def test_points_out_of_core_give_the_in_memory_points(volumes, tmp_path, capsys):
    """``--points`` with ``--tiled``: the volumes read region by region, the same result."""
    rng = np.random.default_rng(4)
    points = rng.uniform(10.0, 29.0, size=(12, 3))
    npy = tmp_path / "pois.npy"
    np.save(npy, points)
    outs = [tmp_path / "memory.csv", tmp_path / "tiled.csv"]
    assert main(["correlate", *volumes, "--points", str(npy), "--out", str(outs[0]), *DVC]) == 0
    tiled = ["--tiled", "--max-memory", "2GB"]
    assert (
        main(["correlate", *volumes, "--points", str(npy), "--out", str(outs[1]), *DVC, *tiled])
        == 0
    )
    memory, out_of_core = read_points(outs[0]), read_points(outs[1])
    np.testing.assert_array_equal(out_of_core.status, memory.status)
    np.testing.assert_allclose(out_of_core.u, memory.u, atol=1e-3)
    assert out_of_core.valid.all()
    # with --self-correct, --points is refused before anything is written
    bad = tmp_path / "bad.csv"
    command = ["correlate", *volumes, "--points", str(npy), "--out", str(bad), *DVC, "--tiled"]
    assert main([*command, "--self-correct"]) == 2
    assert "--self-correct" in capsys.readouterr().err and not bad.exists()


def test_points_to_a_grid_format_are_refused_before_any_work(
    volumes, tmp_path, capsys, monkeypatch
):
    from napari_dvc_correct.engine.correlation import correlate_points as module

    monkeypatch.setattr(module, "correlate_points", lambda *a, **k: pytest.fail("correlated"))
    npy = tmp_path / "pois.npy"
    np.save(npy, np.full((3, 3), 20.0))
    for suffix in (".npz", ".vti"):
        out = tmp_path / f"at_points{suffix}"
        assert main(["correlate", *volumes, "--points", str(npy), "--out", str(out), *DVC]) == 2
        assert "list of points" in capsys.readouterr().err and not out.exists()


def test_roi_limits_the_grid_to_the_region(volumes, tmp_path):
    out = tmp_path / "roi.npz"
    roi = "12:30,10:26,:"
    assert main(["correlate", *volumes, "--roi", roi, "--out", str(out), *DVC]) == 0
    field = load_field(out)
    points = field.points
    assert np.all((points[:, 0] >= 12) & (points[:, 0] < 30))
    assert np.all((points[:, 1] >= 10) & (points[:, 1] < 26))
    assert field.shape[0] == 3 and field.shape[1] == 3
    good = field.displacement[field.valid.reshape(-1)]
    np.testing.assert_allclose(good, np.broadcast_to(SHIFT, good.shape), atol=0.05)


def test_origin_and_cylinder(volumes, tmp_path):
    out = tmp_path / "cyl.npz"
    args = ["--cylinder", "20,20,9,10:30", "--origin", "10,11,11", "--out", str(out)]
    assert main(["correlate", *volumes, *args, *DVC]) == 0
    field = load_field(out)
    assert field.origin == (10.0, 11.0, 11.0)
    radial = np.hypot(field.points[:, 1] - 20, field.points[:, 2] - 20)
    computed = field.status.reshape(-1) != Status.NOT_COMPUTED
    assert computed.any() and (~computed).any()
    assert np.all(radial[computed] <= 9) and np.all(radial[~computed] > 9)


def test_bad_placement_options_are_refused(volumes, tmp_path, capsys):
    out = tmp_path / "x.npz"
    assert main(["correlate", *volumes, "--roi", "1:2,3", "--out", str(out), *DVC]) == 2
    assert "three ranges" in capsys.readouterr().err
    assert main(["correlate", *volumes, "--cylinder", "1,2", "--out", str(out), *DVC]) == 2
    assert main(["correlate", *volumes, "--out", str(tmp_path / "x.txt"), *DVC]) == 2
    assert not out.exists()


def test_correct_a_spam_field_and_write_it_back_as_spam(volumes, tmp_path, capsys):
    grid = tmp_path / "ours.npz"
    assert main(["correlate", *volumes, "--out", str(grid), *DVC]) == 0
    field = load_field(grid)
    field.u = field.u + 0.3  # an imperfect field from "another tool"
    spam_in = tmp_path / "ldic.tsv"
    write_field(field, spam_in, "spam")
    out = tmp_path / "corrected.tsv"
    code = main(
        ["correct", *volumes, "--field", str(spam_in), "--format", "spam", "--subvolume", "15",
         "--out", str(out), "--out-format", "spam", "--max-passes", "2", "--quiet"]
    )  # fmt: skip
    assert code == 0
    assert "spam field on a" in capsys.readouterr().out
    corrected = read_field(out, "spam")
    assert corrected.same_grid(field)  # the imported field's grid is kept
    error = corrected.displacement[corrected.valid.reshape(-1)] - SHIFT
    assert np.sqrt(np.mean(error**2)) < 0.1


def test_correct_scattered_points_reports_at_the_original_points(volumes, tmp_path):
    rng = np.random.default_rng(8)
    points = rng.uniform(11.0, 27.0, size=(150, 3))  # inside the 10..28 correction grid
    table_in = tmp_path / "davis.csv"
    write_field(ScatteredField(points, np.broadcast_to(SHIFT + 0.4, (150, 3))), table_in, "table")
    out = tmp_path / "corrected.csv"
    code = main(
        ["correct", *volumes, "--field", str(table_in), "--subvolume", "15", "--grid-step", "6",
         "--out", str(out), "--max-passes", "1", "--quiet"]
    )  # fmt: skip
    assert code == 0
    at_points = read_points(out)
    np.testing.assert_allclose(at_points.points, points, atol=1e-6)
    grid = load_field(tmp_path / "corrected_grid.npz")
    assert grid.step == (6.0, 6.0, 6.0)
    good = at_points.valid
    assert good.all()
    error = np.linalg.norm(at_points.u[good] - SHIFT, axis=1)
    assert np.median(error) < 0.15, np.median(error)


def test_evaluate_an_imported_field(volumes, tmp_path, capsys):
    grid = tmp_path / "ours.npz"
    assert main(["correlate", *volumes, "--out", str(grid), *DVC]) == 0
    idvc_file = tmp_path / "run.disp"
    write_field(load_field(grid), idvc_file, "idvc")
    out_dir = tmp_path / "report"
    code = main(
        ["evaluate", *volumes, "--field", str(idvc_file), "--format", "idvc", "--compare",
         str(grid), "--out-dir", str(out_dir), "--no-volumes", "--quiet"]
    )  # fmt: skip
    assert code == 0
    assert "accuracy index" in capsys.readouterr().out
    assert (out_dir / "report.md").exists()


def test_vtk_outputs_for_paraview(volumes, tmp_path):
    vtk = pytest.importorskip("vtk")
    out = tmp_path / "roi.vti"
    assert main(["correlate", *volumes, "--roi", "12:30,10:26,:", "--out", str(out), *DVC]) == 0
    reader = vtk.vtkXMLImageDataReader()
    reader.SetFileName(str(out))
    reader.Update()
    assert reader.GetOutput().GetDimensions()[::-1][:2] == (3, 3)
    points = tmp_path / "pois.npy"
    np.save(points, np.array([[15.0, 16.5, 17.0], [20.0, 21.0, 22.25]]))
    out = tmp_path / "pois.vtu"
    assert main(["correlate", *volumes, "--points", str(points), "--out", str(out), *DVC]) == 0
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(out))
    reader.Update()
    assert reader.GetOutput().GetNumberOfPoints() == 2


def test_a_field_off_whole_voxels_asks_for_a_grid_step(volumes, tmp_path, capsys):
    points = np.stack(np.meshgrid(*[10.5 + 6.0 * np.arange(3)] * 3, indexing="ij"), -1).reshape(
        -1, 3
    )
    path = tmp_path / "half.csv"
    write_field(ScatteredField(points, np.broadcast_to(SHIFT, points.shape)), path, "table")
    out = tmp_path / "c.csv"
    args = ["correct", *volumes, "--field", str(path), "--subvolume", "15", "--out", str(out)]
    assert main([*args, "--quiet"]) == 2
    assert "--grid-step" in capsys.readouterr().err
    assert not out.exists()


def test_our_dvcfield_suffix_is_an_output_of_every_command(tmp_path):
    # the panels and `export` write `.dvcfield`; correlate/correct refused `--out f.dvcfield`
    # ("must end with .npz, .tsv, ...") and clean asked for .npz
    from argparse import Namespace

    from napari_dvc_correct.commands import _common
    from napari_dvc_correct.commands._field_formats import output_format
    from napari_dvc_correct.commands.series import field_suffix

    assert output_format(Namespace(out_format="auto"), str(tmp_path / "f.dvcfield")) == "npz"
    assert field_suffix(Namespace(out_format="auto"), at_points=False) == ".npz"  # unchanged
    assert field_suffix(Namespace(out_format="npz"), at_points=False) == ".npz"
    assert _common.check_output_path(str(tmp_path / "f.dvcfield"), suffixes=(".npz", ".dvcfield"))


def test_points_from_a_ccpi_roi_and_from_other_tools_field_files(tmp_path, capsys):
    """``--points`` takes the point files DVC users have: a CCPi ``.roi`` cloud (``n x y z``, no
    header, x the fastest axis) and the points of a spam TSV (``Zpos``...), pyALDVC .npz/.mat,
    iDVC .disp or our own table (``z [voxel]``), each in its own axis order. All were refused
    ('the header must name the columns z, y, x', or a UTF-8 error for the .npz)."""
    from napari_dvc_correct.commands._grid_options import load_points

    points = np.array([[5.0, 7.0, 9.5], [5.0, 8.0, 11.0], [6.0, 7.0, 13.25]])  # z, y, x
    roi = tmp_path / "cloud.roi"
    roi.write_text("".join(f"{n + 1}\t{x:g}\t{y:g}\t{z:g}\n" for n, (z, y, x) in enumerate(points)))
    np.testing.assert_array_equal(load_points(str(roi)), points)
    field = ScatteredField(points=points, u=np.tile([0.5, -0.25, 1.0], (3, 1)))
    for name in ("f.tsv", "f.disp", "f.mat", "f.csv"):
        write_field(field, tmp_path / name, "aldvc" if name.endswith(".mat") else None)
        np.testing.assert_allclose(load_points(str(tmp_path / name)), points, atol=1e-9)
    write_field(field, tmp_path / "al.npz", "aldvc")
    np.testing.assert_allclose(load_points(str(tmp_path / "al.npz")), points, atol=1e-9)
    (tmp_path / "bad.roi").write_text("1\t2\n")
    with pytest.raises(ValueError, match="n x y z"):
        load_points(str(tmp_path / "bad.roi"))
    (tmp_path / "cloud.txt").write_text(roi.read_text())  # a headerless cloud, another suffix
    with pytest.raises(ValueError, match="suffix .roi"):
        load_points(str(tmp_path / "cloud.txt"))


def test_a_disp_grid_is_written_back_in_its_rows_order_under_its_labels(tmp_path):
    """iDVC's own point clouds run x slowest (and CCPi ``dvc`` writes rows in processing
    order): a regular cloud read as a grid was written back in the grid's C order under labels
    1..N, so label 2 named another point than in the user's file. The rows now keep the file's
    order and labels, each with its own point's value."""
    from argparse import Namespace

    from napari_dvc_correct.commands._field_formats import read_input_field, write_output_field

    xs = np.arange(3) * 6.0 + 10
    cloud = np.array([(x, y, z) for x in xs for y in xs[:2] for z in xs])  # x slowest
    labels = np.arange(len(cloud)) + 101
    u_xyz = np.column_stack([0.01 * cloud[:, 0], -0.5 + 0.0 * cloud[:, 1], 0.02 * cloud[:, 2]])
    rows = [f"{n}\t{x:g}\t{y:g}\t{z:g}\t0\t0.01\t{u:.6f}\t{v:.6f}\t{w:.6f}"
            for n, (x, y, z), (u, v, w) in zip(labels, cloud, u_xyz)]  # fmt: skip
    source = tmp_path / "run.disp"
    source.write_text("n\tx\ty\tz\tstatus\tobjmin\tu\tv\tw\n" + "\n".join(rows) + "\n")
    args = Namespace(format="auto", out_format="auto", idvc_objective="znssd")
    imported = read_input_field(args, str(source))
    assert imported.points is None  # a regular grid, kept
    out = tmp_path / "back.disp"
    write_output_field(args, imported.field, str(out), points=None, rows=imported.rows)
    back = read_points(out)
    assert back.metadata["source"]["point_ids"] == labels.tolist()
    np.testing.assert_allclose(back.points, read_points(source).points)
    np.testing.assert_allclose(back.u, read_points(source).u, atol=1e-6)


def test_a_table_without_header_says_how_its_columns_were_read(tmp_path, capsys):
    """A table without a header is read by position (z y x uz uy ux, or x y z with --xyz): the
    guess was silent, so an x, y, z table (pyALDVC, OpenCorr order) gave swapped axes without
    a word. Each command that reads it now warns, naming the order used and --xyz."""
    from argparse import Namespace

    from napari_dvc_correct.commands._field_formats import read_input_field

    path = tmp_path / "bare.csv"
    rows = [[z, y, x, 0.5, -0.25, 1.0] for z in (8, 14) for y in (8, 14) for x in (8, 14)]
    np.savetxt(path, rows, delimiter=",")
    for xyz, order in ((False, "z y x uz uy ux"), (True, "x y z ux uy uz")):
        args = Namespace(format="auto", xyz=xyz, voxel_size=None, command="correct")
        read_input_field(args, str(path))
        err = capsys.readouterr().err
        assert "bare.csv has no header line" in err and order in err
        assert ("--xyz reads" in err) is (not xyz)
    named = tmp_path / "named.csv"
    np.savetxt(named, rows, delimiter=",", header="z,y,x,uz,uy,ux", comments="")
    read_input_field(Namespace(format="auto", xyz=False, voxel_size=None), str(named))
    assert capsys.readouterr().err == ""


def test_a_scattered_disp_is_written_back_under_its_labels(tmp_path):
    """An irregular iDVC cloud is corrected on a grid and written back at its points, in its
    rows' order: under its own labels ``n`` (were 1..N)."""
    from argparse import Namespace

    from napari_dvc_correct.commands._field_formats import read_input_field, write_output_field

    rng = np.random.default_rng(5)
    cloud = rng.uniform(8.0, 30.0, size=(40, 3))  # x, y, z
    labels = rng.permutation(np.arange(500, 540))
    rows = [f"{n}\t{x:.4f}\t{y:.4f}\t{z:.4f}\t0\t0.01\t0.25\t-0.5\t0.75"
            for n, (x, y, z) in zip(labels, cloud)]  # fmt: skip
    source = tmp_path / "cloud.disp"
    source.write_text("n\tx\ty\tz\tstatus\tobjmin\tu\tv\tw\n" + "\n".join(rows) + "\n")
    args = Namespace(format="auto", out_format="auto", idvc_objective="znssd")
    imported = read_input_field(args, str(source))
    assert imported.points is not None  # scattered: put on a grid
    out = tmp_path / "back.disp"
    write_output_field(args, imported.field, str(out), points=imported.points)
    back = read_points(out)
    assert back.metadata["source"]["point_ids"] == labels.tolist()
    np.testing.assert_allclose(back.points, read_points(source).points, atol=1e-6)
