"""The Export dock: every format from a real run, extras, report, and bad choices."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import tifffile

from napari_dvc_correct.engine.evaluation.strain import equivalent_strain_field
from napari_dvc_correct.io.formats import read_field
from napari_dvc_correct.io.npz import load_field
from napari_dvc_correct.layers import field_of
from napari_dvc_correct.widgets import EvaluateWidget
from napari_dvc_correct.widgets.export import ExportWidget


def _dock(viewer):
    widget = ExportWidget(viewer)
    viewer.window.add_dock_widget(widget)
    return widget


def test_every_format(correlated, run_panel, tmp_path):
    viewer = correlated.viewer
    field = field_of(viewer.layers["|u| (uncorrected)"])
    widget = _dock(viewer)
    assert widget.field.currentText() == "uncorrected"
    widget.path.setText(str(tmp_path / "run"))
    expected = {
        ".dvcfield": ["run.dvcfield"],
        ".npz": ["run.npz"],
        ".h5": ["run.h5"],
        ".vti": ["run.vti"],
        ".vtk": ["run.vtk"],
        ".csv": ["run.csv"],
        ".tif": [f"run_{q}.tif" for q in ("uz", "uy", "ux", "magnitude", "zncc", "status")],
        ".tsv": ["run.tsv"],  # the other tools' formats (were offered for points only)
        ".disp": ["run.disp"],
        ".mat": ["run.mat"],
    }
    for suffix, names in expected.items():
        widget.set_format(suffix)
        widget.path.setText(str(tmp_path / "run"))
        run_panel(widget)
        assert widget.last_error is None, widget.last_error
        for name in names:
            assert (tmp_path / name).is_file(), name
    np.testing.assert_array_equal(load_field(tmp_path / "run.npz").u, field.u)
    np.testing.assert_array_equal(load_field(tmp_path / "run.dvcfield").u, field.u)
    with h5py.File(tmp_path / "run.h5", "r") as h5:
        np.testing.assert_array_equal(h5["field/u"][()], field.u)
        assert h5["grid/equivalent_strain"].shape == field.shape  # strain went with the field
        np.testing.assert_allclose(h5["field"].attrs["voxel_size"], (2.0, 1.5, 1.5))
    np.testing.assert_allclose(tifffile.imread(tmp_path / "run_ux.tif"), field.u[..., 2])
    for name in ("run.tsv", "run.disp", "run.mat"):  # each reads back as the same grid
        back = read_field(tmp_path / name)
        assert back.shape == field.shape, name
        np.testing.assert_allclose(back.origin, field.origin)
        np.testing.assert_allclose(back.u, field.u, atol=1e-6, equal_nan=True, err_msg=name)
    assert (tmp_path / "run_equivalent_strain.tif").is_file()  # extra grid array as its own stack
    assert "Wrote" in widget.message.text()
    # formats without room for metadata get the provenance next to them
    side = json.loads((tmp_path / "run_provenance.json").read_text())
    assert side["source"] == "uncorrected" and side["corrected"] is False
    assert side["params"]["subvolume"] == field.params["subvolume"]


def test_strain_residual_and_report(correlated, run_panel, tmp_path):
    viewer = correlated.viewer
    evaluate = EvaluateWidget(viewer)
    viewer.window.add_dock_widget(evaluate)
    run_panel(evaluate)
    widget = _dock(viewer)
    widget.set_format(".csv")
    widget.path.setText(str(tmp_path / "soil.csv"))
    widget.strain_tiff.setChecked(True)
    widget.residual_tiff.setChecked(True)
    widget.report.setChecked(True)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    residual = tifffile.imread(tmp_path / "soil_residual.tif")
    np.testing.assert_allclose(residual, viewer.layers["residual volume (uncorrected)"].data)
    strain = tifffile.imread(tmp_path / "soil_equivalent_strain.tif")
    field = field_of(viewer.layers["|u| (uncorrected)"])
    np.testing.assert_allclose(strain, equivalent_strain_field(field), rtol=1e-6)
    with tifffile.TiffFile(tmp_path / "soil_equivalent_strain.tif") as tif:
        info = json.loads(tif.imagej_metadata["Info"])
    np.testing.assert_allclose(info["scale"], viewer.layers["|u| (uncorrected)"].scale)
    np.testing.assert_allclose(info["translate"], viewer.layers["|u| (uncorrected)"].translate)
    report = json.loads((tmp_path / "soil_report.json").read_text())
    assert "accuracy index p" in report["field: uncorrected"]
    # the command line's report (evaluate --out-dir), from the same evaluation: every value
    # renders (no "|" splitting a cell), phases numbered as in the panel, the CLI's plots
    folder = tmp_path / "soil_report"
    text = (folder / "report.md").read_text(encoding="utf-8")
    evaluation = evaluate.evaluation
    assert text.startswith("# DVC accuracy evaluation")
    assert "r(X) = |F(X + u(X)) − G(X)|" in text
    assert f"|g1 − g2| = {evaluation.contrast:.4g}" in text
    assert "The accuracy index uses phases 1 and 2" in text and "phases 0" not in text
    for table_line in (line for line in text.splitlines() if line.startswith("| ")):
        cells = table_line.replace("\\|", "").strip("|").split("|")
        assert all(cell.strip() for cell in cells), table_line  # no cell emptied
    assert "### Background residual per phase (eq. 1)" in text
    for name in (
        "residual_histogram.png",
        "residual_slices.png",
        "accuracy_vs_strain.png",
        "background.csv",
    ):
        assert (folder / name).is_file(), name
        assert name in text or name.endswith(".csv")
    assert f"{evaluation.fields[0].accuracy:.6g}" in text


@pytest.mark.parametrize("problem", ["no folder", "no residual yet", "no field"])
def test_bad_choices_show_a_message(problem, request, tmp_path):
    if problem == "no field":
        viewer = request.getfixturevalue("make_napari_viewer")()
    else:
        viewer = request.getfixturevalue("correlated").viewer
    widget = _dock(viewer)
    widget.path.setText(str(tmp_path / "missing" / "x.npz"))
    if problem == "no residual yet":
        widget.path.setText(str(tmp_path / "x.npz"))
        widget.report.setChecked(True)
    assert widget.run() is None
    expected = {
        "no folder": "does not exist",
        "no residual yet": "run Evaluate first",
        "no field": "run Correlate first",
    }[problem]
    assert expected in widget.message.text()
    assert list(tmp_path.iterdir()) == []


def test_points_result_in_every_point_format(points_panel, run_panel, tmp_path):
    """A Correlate run at the points of a Points layer is listed and written at those points:
    CSV (one row per point), the NPZ and .vtu of ``correlate --points``; grid formats refused."""
    import csv

    from napari_dvc_correct.engine.fields.field import Status
    from napari_dvc_correct.io.formats import read_points
    from napari_dvc_correct.layers import plugin_metadata
    from napari_dvc_correct.quantities import point_quantities

    viewer = points_panel.viewer
    run_panel(points_panel)
    result = plugin_metadata(viewer.layers["|u| (points)"])["points_field"]
    widget = _dock(viewer)
    assert widget.field.currentText() == "points"
    assert "4 points of interest of 'my points'" in widget.writes.text()
    offered = [widget.format.itemData(i) for i in range(widget.format.count())]
    assert offered[:3] == [".csv", ".npz", ".vtu"] and ".vti" not in offered
    assert not widget.strain_tiff.isEnabled() and not widget.report.isEnabled()
    with pytest.raises(ValueError, match="no grid for .vti"):
        widget.set_format(".vti")
    assert sorted(offered) == sorted((".csv", ".npz", ".vtu", ".tsv", ".disp", ".mat"))
    for suffix in offered:
        widget.set_format(suffix)
        widget.path.setText(str(tmp_path / "pois"))
        run_panel(widget)
        assert widget.last_error is None, widget.last_error
        assert (tmp_path / f"pois{suffix}").is_file(), suffix
    rows = list(csv.DictReader(open(tmp_path / "pois.csv", newline="")))
    assert len(rows) == result.n_points
    column = lambda *names: np.array([[float(r[n]) for n in names] for r in rows])  # noqa: E731
    np.testing.assert_allclose(column("z", "y", "x"), result.points, rtol=1e-8)
    np.testing.assert_allclose(column("uz", "uy", "ux"), result.u, rtol=1e-8)
    np.testing.assert_allclose(column("zncc")[:, 0], result.zncc, rtol=1e-6)
    assert [r["status_name"] for r in rows] == [Status(int(c)).label for c in result.status]
    strain = point_quantities(result)["εeq"]  # the strain the View panel shows at the points
    np.testing.assert_allclose(column("equivalent_strain")[:, 0], strain, rtol=1e-8)
    np.testing.assert_allclose(column("ux_phys")[:, 0], result.u[:, 2] * 1.5, rtol=1e-8)
    for suffix in (".npz", ".tsv", ".disp", ".mat"):  # read back as the command line's files
        back = read_points(tmp_path / f"pois{suffix}")
        np.testing.assert_allclose(back.points, result.points, atol=1e-6)
        np.testing.assert_allclose(back.u, result.u, atol=1e-6)
        if suffix in (".npz", ".tsv"):  # (these two keep our exact status codes)
            np.testing.assert_array_equal(back.status, result.status)
    side = json.loads((tmp_path / "pois_provenance.json").read_text())
    assert side["source"] == "points" and side["status_counts"] == result.status_counts()
    vtk = pytest.importorskip("vtk")
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(tmp_path / "pois.vtu"))
    reader.Update()
    assert reader.GetOutput().GetNumberOfPoints() == result.n_points


def test_an_export_onto_the_scans_file_is_refused(correlated, tmp_path):
    # the scans opened from rock.npz, exported as NPZ to rock.npz: the scans were replaced
    viewer = correlated.viewer
    scans = tmp_path / "rock.npz"
    np.savez(scans, reference=np.asarray(viewer.layers[0].data)[:8])
    before = scans.read_bytes()
    viewer.open(str(scans), plugin="napari-dvc-correct")
    widget = _dock(viewer)
    widget.set_format(".npz")
    widget.path.setText(str(scans))
    assert widget.run() is None
    assert "the file of an open layer" in widget.message.text()
    assert scans.read_bytes() == before
