"""The evaluation report: CSV tables, PNG plots, TIFF volumes and report.md."""

import csv
import subprocess
import sys

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    deform_volume,
    sample_displacement,
    shear_band,
    two_phase_volume,
)
from napari_dvc_correct.report import file_stem, unique_names, write_report
from napari_dvc_correct.report.tables import write_csv

SHAPE = (32, 32, 32)


@pytest.fixture(scope="module")
def evaluation():
    clean = two_phase_volume(SHAPE, seed=1)
    truth = shear_band(center=(16.0, 16.0, 16.0), width=4.0, slip=3.0)
    reference = add_noise(clean, 3.0, seed=2)
    deformed = add_noise(deform_volume(clean, truth), 3.0, seed=3)
    origin, step, shape = grid_for_volume(SHAPE, 9, 4)
    base = DisplacementField.zeros(origin, step, shape)
    exact = base.replace(u=sample_displacement(truth, base.points).reshape((*shape, 3)))
    rigid = base.replace(u=np.zeros_like(exact.u))  # ignores the band: a poor field
    return evaluate_fields(reference, deformed, {"exact": exact, "no band": rigid}, n_bins=3)


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


def test_failed_write_keeps_the_earlier_file(tmp_path):
    target = tmp_path / "table.csv"
    write_csv([{"a": 1, "b": 2.5}], target)
    before = target.read_text()
    with pytest.raises(KeyError):
        write_csv([{"a": 1, "b": 2.5}, {"a": 2}], target)  # second row lacks "b"
    assert target.read_text() == before == "a,b\n1,2.5\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    with pytest.raises(ValueError, match="no rows"):
        write_csv([], target)


def test_file_stems_and_lazy_matplotlib():
    assert file_stem("field 1") == "field_1"
    assert file_stem("corrected (pass 2)") == "corrected_pass_2"
    assert file_stem("///") == "field"
    assert unique_names(["a", "a", "b", "a"]) == ["a", "a_2", "b", "a_3"]
    assert unique_names(["f", "f"], "{name} ({k})") == ["f", "f (2)"]
    code = "import sys, napari_dvc_correct.report; print('matplotlib' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.stdout.strip() == "False", result.stderr


def test_report_colours_are_the_panel_s(evaluation, tmp_path, monkeypatch):
    """Each field has one colour in the report and the Evaluate panel (first orange, then
    blue), not matplotlib's default cycle (which made the report's the reverse)."""
    from matplotlib.colors import to_hex

    from napari_dvc_correct.report import plots

    figures = []
    monkeypatch.setattr(plots, "_save", lambda figure, path: figures.append(figure) or path)
    plots.plot_accuracy_vs_strain(evaluation, tmp_path / "a.png")
    plots.plot_residual_vs_strain(evaluation, tmp_path / "r.png")
    accuracy, residual = (figure.axes[0] for figure in figures)
    lines = [
        to_hex(line.get_color()) for line in accuracy.lines if line.get_label() != "0.85 (paper)"
    ]
    assert lines[:2] == ["#f28e2b", "#4e9fde"]
    bars = [to_hex(c.patches[0].get_facecolor()) for c in residual.containers]
    assert bars[:2] == ["#f28e2b", "#4e9fde"]
