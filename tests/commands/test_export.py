"""``napari-dvc-correct export``: every format written, read back and compared with the field."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from napari_dvc_correct.cli import main
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.io.export import EXPORT_FORMATS
from napari_dvc_correct.io.formats import read_field, read_points, write_field
from napari_dvc_correct.io.npz import load_field, save_field

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402

VOXEL = (0.5, 0.25, 2.0)  # z, y, x mm


def known_field() -> DisplacementField:
    """A field on a grid off the origin, with a failed node (its value NaN in every export) and
    a node replaced by cleaning (its status kept, provenance REPLACED)."""
    field = DisplacementField.zeros((7.0, 8.0, 9.0), (4.0, 5.0, 6.0), (3, 4, 5))
    rng = np.random.default_rng(7)
    field.u = rng.normal(scale=2.0, size=field.u.shape)
    field.zncc[:] = rng.uniform(0.6, 1.0, field.shape)
    field.status[1, 2, 3] = Status.DIVERGED
    field.status[2, 0, 1] = Status.LOW_ZNCC
    field.provenance[2, 0, 1] = Provenance.REPLACED
    field.metadata["voxel_size"] = VOXEL
    return field


@pytest.fixture
def source(tmp_path):
    path = tmp_path / "in" / "field.dvcfield"
    path.parent.mkdir()
    save_field(known_field(), path)
    return path


def _vtk(reader_name, path):
    reader = getattr(vtk, reader_name)()
    reader.SetFileName(str(path))
    if hasattr(reader, "ReadAllScalarsOn"):
        reader.ReadAllScalarsOn()
        reader.ReadAllVectorsOn()
    reader.Update()
    return reader.GetOutput()


def _expected_u(field):
    """The displacement an export holds: NaN at the failed node, the value elsewhere."""
    u = field.u.copy()
    u[~field.valid] = np.nan
    return u


def _read_back(fmt, path, out_dir):
    """(u (nz, ny, nx, 3) voxels, status or None, origin, step) of an exported file."""
    field = known_field()
    vs = np.asarray(VOXEL)
    if fmt in ("dvcfield", "npz"):
        back = load_field(path)
        return back.u, back.status, back.origin, back.step
    if fmt == "hdf5":
        with h5py.File(path, "r") as h5:
            group = h5["field"]
            np.testing.assert_allclose(group.attrs["voxel_size"], vs)
            return group["u"][()], group["status"][()], group.attrs["origin"], group.attrs["step"]
    if fmt in ("vti", "vtk"):
        image = _vtk("vtkXMLImageDataReader" if fmt == "vti" else "vtkStructuredPointsReader", path)
        assert image.GetDimensions() == field.shape[::-1]
        data = image.GetPointData()
        # VTK: x fastest (numpy's C order of (z, y, x)), vectors (ux, uy, uz) in mm
        u = vtk_to_numpy(data.GetArray("displacement")).reshape(*field.shape, 3)[..., ::-1] / vs
        status = vtk_to_numpy(data.GetArray("status")).reshape(field.shape)
        origin = np.asarray(image.GetOrigin())[::-1] / vs
        step = np.asarray(image.GetSpacing())[::-1] / vs
        return u, status, origin, step
    if fmt == "vtu":
        grid = _vtk("vtkXMLUnstructuredGridReader", path)
        points = vtk_to_numpy(grid.GetPoints().GetData())[:, ::-1] / vs
        data = grid.GetPointData()
        u = vtk_to_numpy(data.GetArray("displacement"))[:, ::-1] / vs
        status = vtk_to_numpy(data.GetArray("status"))
        np.testing.assert_allclose(points, field.points, atol=1e-5)  # the nodes, in C order
        return u.reshape(*field.shape, 3), status.reshape(field.shape), field.origin, field.step
    if fmt == "tiff":
        stem = path.with_suffix("")
        u = np.stack(
            [tifffile.imread(stem.parent / f"{stem.name}_{c}.tif") for c in ("uz", "uy", "ux")],
            axis=-1,
        )
        status = tifffile.imread(stem.parent / f"{stem.name}_status.tif")
        with tifffile.TiffFile(stem.parent / f"{stem.name}_ux.tif") as tif:
            info = json.loads(tif.imagej_metadata["Info"])
        origin = np.asarray(info["translate"]) / vs
        step = np.asarray(info["scale"]) / vs
        return u, status, origin, step
    # csv, spam, idvc, aldvc: our readers read them back (csv: the plain table reader)
    reader = {"csv": "table", "spam": "spam", "idvc": "idvc", "aldvc": "aldvc"}[fmt]
    back = read_field(path, reader)
    status = back.status if fmt in ("csv", "spam", "aldvc") else None
    return back.u, status, back.origin, back.step


@pytest.mark.parametrize("fmt", list(EXPORT_FORMATS))
def test_every_format_round_trips(fmt, source, tmp_path, capsys):
    field = known_field()
    out = tmp_path / "out" / "converted"
    out.parent.mkdir()
    assert main(["export", str(source), str(out), "--format", fmt, "--quiet"]) == 0
    path = out.with_name(out.name + EXPORT_FORMATS[fmt])
    printed = capsys.readouterr().out
    assert str(path.name) in printed or fmt == "tiff"
    u, status, origin, step = _read_back(fmt, path, out.parent)
    np.testing.assert_allclose(origin, field.origin, atol=1e-5)
    np.testing.assert_allclose(step, field.step, atol=1e-5)
    ours = fmt in ("dvcfield", "npz")  # ours keeps the grid u and NaNs the flat displacement
    expected = field.u if ours else _expected_u(field)
    finite = np.isfinite(expected)
    assert ours or finite.sum() == expected.size - 3  # only the failed node's 3 components
    np.testing.assert_allclose(u[finite], expected[finite], rtol=1e-5, atol=1e-5)
    if ours:
        flat = load_field(path).measured_displacement.reshape(*field.shape, 3)
        assert np.isnan(flat[1, 2, 3]).all()
    else:
        assert np.isnan(u[1, 2, 3]).all()  # the failed node: NaN next to its status
    if status is not None:
        assert status[1, 2, 3] == Status.DIVERGED
        assert status[0, 0, 0] == Status.CONVERGED
    # formats without room for the metadata get the provenance beside them, as from the panel
    side = out.parent / "converted_provenance.json"
    assert side.is_file() == (fmt not in ("dvcfield", "npz", "hdf5"))
    if side.is_file():
        assert json.loads(side.read_text())["source"] == str(source)


def test_another_tools_file_converts_to_ours_and_back(tmp_path):
    """A spam TSV in, our field file out (the same grid and values), and out again as iDVC."""
    field = known_field()
    spam_file = tmp_path / "ldic.tsv"
    write_field(field, spam_file, "spam")
    ours = tmp_path / "from_spam.dvcfield"
    assert main(["export", str(spam_file), str(ours), "--quiet"]) == 0
    back = load_field(ours)
    assert back.same_grid(field)
    good = field.valid & (field.status != Status.LOW_ZNCC)
    np.testing.assert_allclose(back.u[good], field.u[good], atol=1e-5)
    disp = tmp_path / "again.disp"
    assert main(["export", str(ours), str(disp), "--quiet"]) == 0
    np.testing.assert_allclose(read_field(disp, "idvc").u[good], field.u[good], atol=1e-5)


def test_scattered_points_stay_points_or_are_put_on_a_grid(tmp_path, capsys):
    rng = np.random.default_rng(3)
    points = rng.uniform(10, 40, size=(60, 3))
    table = tmp_path / "points.csv"
    table.write_text(
        "z,y,x,uz,uy,ux\n"
        + "\n".join(",".join(f"{v:.6f}" for v in (*p, 0.5, -0.25, 1.0)) for p in points)
    )
    out = tmp_path / "points.vtu"
    assert main(["export", str(table), str(out), "--quiet"]) == 0
    grid = _vtk("vtkXMLUnstructuredGridReader", out)
    assert grid.GetNumberOfPoints() == 60  # the tool's own points
    np.testing.assert_allclose(vtk_to_numpy(grid.GetPoints().GetData())[:, ::-1], points, atol=1e-5)
    assert "points" in capsys.readouterr().out
    image = tmp_path / "gridded.vti"
    assert main(["export", str(table), str(image), "--quiet"]) == 0
    assert "put on a grid" in capsys.readouterr().out
    data = _vtk("vtkXMLImageDataReader", image).GetPointData()
    u = vtk_to_numpy(data.GetArray("displacement"))
    finite = np.isfinite(u).all(axis=1)
    assert finite.any()
    np.testing.assert_allclose(
        u[finite], np.broadcast_to([1.0, -0.25, 0.5], u[finite].shape), atol=1e-5
    )


def test_bad_requests_are_refused_with_one_line_and_nothing_written(source, tmp_path, capsys):
    before = source.read_bytes()
    # the input itself
    assert main(["export", str(source), str(source), "--quiet"]) == 2
    assert "also an input" in capsys.readouterr().err
    assert source.read_bytes() == before
    # a format name that does not exist: argparse lists the choices
    with pytest.raises(SystemExit) as stop:
        main(["export", str(source), str(tmp_path / "x.vti"), "--format", "paraview"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'paraview'" in err and all(name in err for name in EXPORT_FORMATS)
    # a suffix that names no format, or another than --format
    assert main(["export", str(source), str(tmp_path / "x.xyz"), "--quiet"]) == 2
    assert "cannot tell the format" in capsys.readouterr().err
    assert main(["export", str(source), str(tmp_path / "x.vtk"), "--format", "vti"]) == 2
    assert "--format vti writes .vti" in capsys.readouterr().err
    # a missing input, a missing folder
    assert main(["export", str(tmp_path / "none.dvcfield"), str(tmp_path / "x.vti")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["export", str(source), str(tmp_path / "no" / "x.vti")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_the_provenance_side_file_may_not_be_the_input(tmp_path, capsys):
    """``OUT.vti`` writes ``OUT_provenance.json``; a table field of that name is refused."""
    field = known_field()
    table = tmp_path / "run_provenance.json"
    write_field(field, table, "table")
    assert read_points(table, "table").n_points == field.n_points
    before = table.read_bytes()
    assert main(["export", str(table), str(tmp_path / "run.vti"), "--in-format", "table"]) == 2
    assert "is the input field" in capsys.readouterr().err
    assert table.read_bytes() == before and not (tmp_path / "run.vti").exists()


def test_two_runs_into_one_stem_keep_each_file_s_provenance(tmp_path, capsys):
    """Two formats of one field share ``run_provenance.json`` (it lists both); another field
    written to that stem in a third format is refused: it would re-describe the others."""
    first, second = known_field(), known_field()
    second.u = second.u + 0.5
    save_field(first, tmp_path / "a.dvcfield")
    save_field(second, tmp_path / "b.dvcfield")
    for name in ("run.vti", "run.csv"):
        assert main(["export", str(tmp_path / "a.dvcfield"), str(tmp_path / name)]) == 0
    side = tmp_path / "run_provenance.json"
    assert json.loads(side.read_text())["files"] == ["run.csv", "run.vti"]
    before = side.read_bytes()
    capsys.readouterr()
    assert main(["export", str(tmp_path / "b.dvcfield"), str(tmp_path / "run.tsv")]) == 2
    assert "describes run.csv, run.vti, written from another field" in capsys.readouterr().err
    assert side.read_bytes() == before and not (tmp_path / "run.tsv").exists()


FORMATS_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "formats"


@pytest.mark.skipif(
    not FORMATS_DIR.is_dir(),
    reason=f"the other tools' real files are not here ({FORMATS_DIR}: ../shared is absent)",
)
@pytest.mark.parametrize(
    ("name", "reader", "fmt"),
    [
        ("spam/reg_ldic/ref-def-ldic.tsv", "spam", "dvcfield"),
        ("pyaldvc/aldvc.mat", "aldvc", "spam"),
        ("ccpi_dvc/snow48/snow48.disp", "idvc", "aldvc"),
    ],
)
def test_real_files_of_other_tools_convert_with_their_values(name, reader, fmt, tmp_path):
    """spam, ALDVC and iDVC files from those tools' own runs: converted, read back, the same
    grid and the same displacement at every node the tool measured."""
    source = FORMATS_DIR / name
    out = tmp_path / f"converted{EXPORT_FORMATS[fmt]}"
    assert main(["export", str(source), str(out), "--quiet"]) == 0
    original = read_field(source, reader)
    back = load_field(out) if fmt == "dvcfield" else read_field(out, fmt)
    assert back.same_grid(original)
    good = original.valid & back.valid
    assert good.sum() >= 0.9 * original.valid.sum()
    np.testing.assert_allclose(back.u[good], original.u[good], rtol=1e-5, atol=1e-4)


def _evaluated_field() -> DisplacementField:
    """:func:`known_field` with an evaluation's error estimate and resolution on it (a node
    without texture: infinite resolution, written as undefined)."""
    from napari_dvc_correct.engine.evaluation.error_estimate import attach_estimate

    field = known_field()
    rng = np.random.default_rng(11)
    estimate = rng.uniform(0.0, 1.0, field.shape)
    resolution = rng.uniform(0.05, 0.3, field.shape)
    estimate[0, 1, 2] = np.nan
    resolution[0, 1, 2] = np.inf
    attach_estimate(field, estimate, resolution, background_residual=2.5)
    return field


def _evaluation_read_back(fmt, path):
    """(error_estimate, error_resolution) on the grid as the exported file holds them."""
    from napari_dvc_correct.engine.evaluation.error_estimate import estimate_of, resolution_of

    field = known_field()
    if fmt in ("dvcfield", "npz"):
        back = load_field(path)
        return estimate_of(back), resolution_of(back)
    if fmt == "hdf5":
        with h5py.File(path, "r") as h5:
            return h5["grid/error_estimate"][()], h5["grid/error_resolution"][()]
    if fmt in ("vti", "vtk", "vtu"):
        name = {"vti": "vtkXMLImageDataReader", "vtk": "vtkStructuredPointsReader"}
        data = _vtk(name.get(fmt, "vtkXMLUnstructuredGridReader"), path).GetPointData()
        return tuple(
            vtk_to_numpy(data.GetArray(key)).reshape(field.shape)  # x fastest: C order
            for key in ("error_estimate", "error_resolution")
        )
    if fmt == "tiff":
        stem = path.with_suffix("")
        return tuple(
            tifffile.imread(stem.parent / f"{stem.name}_{key}.tif")
            for key in ("error_estimate", "error_resolution")
        )
    if fmt == "csv":
        with open(path, newline="") as stream:
            rows = list(csv.DictReader(stream))
        index = {
            (round(float(r["z"])), round(float(r["y"])), round(float(r["x"]))): r for r in rows
        }
        values = np.full((2, *field.shape), np.nan)
        for n, point in enumerate(field.points):
            row = index[tuple(int(round(v)) for v in point)]
            k = np.unravel_index(n, field.shape)
            values[(0, *k)] = float(row["error_estimate"])
            values[(1, *k)] = float(row["error_resolution"])
        return values[0], values[1]
    # spam, idvc, aldvc hold the field only: the side file keeps the evaluation's metadata
    side = json.loads(path.with_name(path.stem + "_provenance.json").read_text())
    entry = side["metadata"]["error_estimate"]
    as_array = [np.asarray(entry[k], dtype=float) for k in ("voxels", "resolution_voxels")]
    return tuple(as_array)


@pytest.mark.parametrize("fmt", list(EXPORT_FORMATS))
def test_the_error_estimate_and_its_resolution_round_trip_in_every_format(fmt, tmp_path):
    """An evaluated field exported in each format: its per-node error estimate and the
    residual's resolution come back node by node (NaN where undefined; an infinite resolution,
    a node without texture, as undefined)."""
    from napari_dvc_correct.engine.evaluation.error_estimate import estimate_of, resolution_of

    field = _evaluated_field()
    source = tmp_path / "evaluated.dvcfield"
    save_field(field, source)
    out = tmp_path / "out" / "converted"
    out.parent.mkdir()
    assert main(["export", str(source), str(out), "--format", fmt, "--quiet"]) == 0
    estimate, resolution = _evaluation_read_back(fmt, out.with_name(out.name + EXPORT_FORMATS[fmt]))
    np.testing.assert_allclose(estimate, estimate_of(field), atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(resolution, resolution_of(field), atol=1e-6, equal_nan=True)
    assert np.isnan(resolution[0, 1, 2]) and np.isfinite(resolution).sum() == field.n_points - 1


def test_its_errors_name_out_as_the_user_typed_it(source, tmp_path, capsys):
    # export has a positional OUT, but its refusals said "--out ...", an option it does not have
    assert main(["export", str(source), str(source), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "OUT " in err and "--out" not in err, err
    assert main(["export", str(source), "/proc/x.vti", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "OUT: cannot write into /proc" in err and "--out" not in err, err
