"""The evaluation report: CSV tables, PNG plots, TIFF volumes and report.md."""

import csv
import subprocess
import sys

import numpy as np
import pytest

from napari_dvc_correct.report import file_stem, unique_names, write_report

SHAPE = (32, 32, 32)


def read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def test_write_report_writes_readable_files(tmp_path, evaluation):
    import tifffile
    from matplotlib.image import imread

    out = tmp_path / "evaluation"
    files = write_report(evaluation, out, inputs={"reference": "G.tif"})
    names = sorted(p.name for p in out.iterdir())
    assert not [n for n in names if n.startswith(".")]  # no temporary files left behind
    for kind in ("tables", "plots", "volumes", "report"):
        assert files[kind], kind
        assert all(p.exists() and p.stat().st_size > 0 for p in files[kind])

    summary = read_csv(out / "summary.csv")
    assert [row["field"] for row in summary] == ["exact", "no band"]
    for row, item in zip(summary, evaluation.fields):
        assert float(row["accuracy_index"]) == pytest.approx(item.accuracy, rel=1e-5)
        assert float(row["mean_residual"]) == pytest.approx(item.mean_residual, rel=1e-5)
    assert float(summary[0]["accuracy_index"]) > float(summary[1]["accuracy_index"])
    bins = read_csv(out / "strain_bins.csv")
    assert len(bins) == 2 * 3
    assert (
        sum(int(r["voxels"]) for r in bins if r["field"] == "exact") == evaluation.fields[0].voxels
    )
    phases = read_csv(out / "phases.csv")
    assert {(r["state"], r["phase"]) for r in phases} == {
        ("reference", "1"),  # numbered from 1, as the Evaluate panel numbers them
        ("reference", "2"),
        ("deformed", "1"),
        ("deformed", "2"),
    }
    assert len(read_csv(out / "background.csv")) == 2 * 3

    for png in files["plots"]:
        image = imread(png)
        assert image.ndim == 3 and image.shape[0] > 200 and image.std() > 0.01  # not blank
    assert {p.name for p in files["plots"]} == {
        "residual_vs_strain.png",
        "accuracy_vs_strain.png",
        "residual_slices.png",
        "residual_histogram.png",
    }

    residual = tifffile.imread(out / "residual_exact.tif")
    assert residual.shape == SHAPE and residual.dtype == np.float32
    assert np.allclose(residual, evaluation.fields[0].residual, equal_nan=True)
    labels = tifffile.imread(out / "labels_reference.tif")
    assert np.array_equal(labels, evaluation.labels_reference)
    strain = tifffile.imread(out / "equivalent_strain_no_band.tif")
    assert strain.shape == evaluation.fields[1].field.shape
    assert (out / "labels_mapped_no_band.tif").exists()

    text = (out / "report.md").read_text()
    assert text.startswith("# DVC accuracy evaluation")
    assert "![accuracy_vs_strain.png](accuracy_vs_strain.png)" in text
    assert "Highest p: **exact**" in text
    assert f"{evaluation.fields[0].accuracy:.6g}" in text
    assert "`residual_exact.tif`" in text and "**reference**: G.tif" in text


def test_report_lists_the_self_correction_passes(tmp_path, evaluation, changed_method_field):
    """Every pass's order and subvolume, the user's choice and the engine's reason."""
    import dataclasses

    corrected, method = changed_method_field
    first = evaluation.fields[0]
    field = first.field.copy()
    field.params = corrected.params
    field.metadata.update(corrected.metadata)
    fields = [dataclasses.replace(first, name="corrected", field=field), *evaluation.fields[1:]]
    files = write_report(dataclasses.replace(evaluation, fields=fields), tmp_path, volumes=False)
    text = files["report"][0].read_text(encoding="utf-8")
    section = text[text.index("## Self-correction passes") :]
    assert "### corrected" in section and "### no band" not in section
    assert "| Pass | Order | Subvolume |" in section
    assert "| 1 | second | 15³ |" in section and "| 2 | second | 15³ |" in section
    assert "used first order on 21³ subvolumes" in section
    assert f"passes 1–2: {method}" in section


def test_report_without_volumes(tmp_path, evaluation):
    files = write_report(evaluation, tmp_path / "light", volumes=False)
    assert files["volumes"] == []
    assert not list((tmp_path / "light").glob("*.tif"))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_report(evaluation, tmp_path / "missing" / "deeper")


def test_file_stems_and_lazy_matplotlib():
    assert file_stem("field 1") == "field_1"
    assert file_stem("corrected (pass 2)") == "corrected_pass_2"
    assert file_stem("///") == "field"
    assert unique_names(["a", "a", "b", "a"]) == ["a", "a_2", "b", "a_3"]
    assert unique_names(["f", "f"], "{name} ({k})") == ["f", "f (2)"]
    code = "import sys, napari_dvc_correct.report; print('matplotlib' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stdout.strip() == "False", result.stderr


def test_the_pass_table_loads_no_report_writer():
    # `correct` prints its pass table through report.passes: the Markdown, table and plot
    # modules and the evaluation's results load only when a report is written
    code = (
        "import sys, napari_dvc_correct.report.passes, napari_dvc_correct.report as r; "
        "print(sorted(m for m in sys.modules if m.startswith('napari_dvc_correct.report'))); "
        "print('napari_dvc_correct.engine.evaluation.results' in sys.modules); "
        "print(r.render_markdown.__module__)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    loaded, results, markdown = result.stdout.strip().splitlines()
    assert loaded == str(["napari_dvc_correct.report", "napari_dvc_correct.report.passes"])
    assert results == "False"
    assert markdown == "napari_dvc_correct.report.markdown"  # still there when asked for


def test_the_report_gives_the_error_estimate_s_resolution_and_marks_bounds(tmp_path, evaluation):
    """summary.csv: the resolution, whether median and 95th percentile are bounds and their
    bound, the shares likely and possibly > 0.5 voxel; report.md shows a bound as "< x"; the
    resolution is written on the grid beside the estimate."""

    import tifffile

    from napari_dvc_correct.engine.evaluation.error_estimate import bounded_text

    files = write_report(evaluation, tmp_path)
    assert any(p.name == "error_resolution_exact.tif" for p in files["volumes"])
    grid = tifffile.imread(tmp_path / "error_resolution_exact.tif")
    np.testing.assert_allclose(grid, evaluation["exact"].error_resolution, rtol=1e-6)
    with open(tmp_path / "summary.csv", newline="") as stream:
        rows = {row["field"]: row for row in csv.DictReader(stream)}
    text = (tmp_path / "report.md").read_text(encoding="utf-8")
    for item in evaluation.fields:
        row, error = rows[item.name], item.error
        assert float(row["error_resolution"]) == pytest.approx(error["resolution"], rel=1e-5)
        assert float(row["possibly_bad_fraction"]) == pytest.approx(error["possibly_bad"])
        assert row["error_median_is_bound"] == ("yes" if error["median_is_bound"] else "no")
        assert float(row["error_median_bound"]) == pytest.approx(error["median_bound"], rel=1e-5)
        assert f"| {bounded_text(error, 'median')} |" in text
    assert rows["exact"]["error_median_is_bound"] == "yes"  # the exact field: nothing resolved
    assert "< " in text and "P(error > 0.5) ≥ ½" in text
