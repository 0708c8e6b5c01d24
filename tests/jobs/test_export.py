"""The export job (jobs/export.py), shared by the Export panel and ``export``: what it writes,
with known values, and what it refuses."""

import json

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.scattered import ScatteredField
from napari_dvc_correct.engine.progress import run_to_completion
from napari_dvc_correct.io.formats import read_field
from napari_dvc_correct.jobs.export import ExportRequest, check_request, provenance, run_export


def _field():
    field = DisplacementField.zeros((10.0, 10.0, 10.0), (5.0, 5.0, 5.0), (3, 4, 5))
    z, y, x = np.meshgrid(*(np.arange(n) for n in field.shape), indexing="ij")
    field.u[..., 0] = 0.25 * z
    field.u[..., 1] = -0.5 + 0.1 * y
    field.u[..., 2] = 0.01 * x * y
    return field


def test_a_csv_export_reads_back_with_its_values_and_a_provenance_side_file(tmp_path):
    field = _field()
    request = ExportRequest(field=field, path=tmp_path / "out.csv", source="my field")
    written = run_to_completion(run_export(request))
    assert (tmp_path / "out.csv") in [p for p in written]
    side = tmp_path / "out_provenance.json"
    assert side.is_file() and json.loads(side.read_text())["source"] == "my field"
    back = read_field(tmp_path / "out.csv")
    assert back.shape == field.shape
    np.testing.assert_allclose(back.origin, field.origin)
    np.testing.assert_allclose(back.step, field.step)
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)


def test_the_native_file_keeps_the_provenance_inside_and_no_side_file(tmp_path):
    request = ExportRequest(field=_field(), path=tmp_path / "out.dvcfield", source="a")
    run_to_completion(run_export(request))
    assert not (tmp_path / "out_provenance.json").exists()
    back = read_field(tmp_path / "out.dvcfield")
    assert back.metadata["provenance"]["source"] == "a"


def test_points_refuse_a_grid_format_and_a_strain_tiff(tmp_path):
    points = ScatteredField(points=np.array([[5.0, 6.0, 7.0], [9.0, 9.0, 9.0]]), u=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="no grid"):
        check_request(ExportRequest(field=points, path=tmp_path / "p.vti"))
    with pytest.raises(ValueError, match="needs a grid field"):
        check_request(ExportRequest(field=points, path=tmp_path / "p.csv", strain_tiff=True))
    check_request(ExportRequest(field=_field(), path=tmp_path / "g.vti"))  # a grid passes


def test_provenance_names_the_source():
    assert provenance(_field(), "state 2")["source"] == "state 2"


def test_formats_of_one_stem_share_a_provenance_that_lists_its_files(tmp_path):
    """The same field as VTK and CSV: one ``out_provenance.json`` naming both files."""
    field = _field()
    for name in ("out.vti", "out.csv"):
        run_to_completion(run_export(ExportRequest(field=field, path=tmp_path / name, source="a")))
    side = json.loads((tmp_path / "out_provenance.json").read_text())
    assert side["files"] == ["out.csv", "out.vti"] and side["source"] == "a"


def test_another_field_may_not_take_over_the_provenance_of_a_stem(tmp_path):
    """A second field written to the same stem in another format would leave ``out.vti``
    described by its provenance: refused before any file is written; the same format (it
    replaces ``out.vti`` too) or a gone ``out.vti`` is fine."""
    first, second = _field(), _field()
    second.u[...] += 1.0
    second.metadata["correction"] = {"passes_applied": 2}
    run_to_completion(run_export(ExportRequest(field=first, path=tmp_path / "out.vti", source="a")))
    before = (tmp_path / "out_provenance.json").read_text()
    request = ExportRequest(field=second, path=tmp_path / "out.csv", source="b")
    with pytest.raises(ValueError, match="describes out.vti, written from another field"):
        run_to_completion(run_export(request))
    assert not (tmp_path / "out.csv").exists()
    assert (tmp_path / "out_provenance.json").read_text() == before
    # the same format replaces the file and its provenance together
    again = ExportRequest(field=second, path=tmp_path / "out.vti", source="b")
    run_to_completion(run_export(again))
    side = json.loads((tmp_path / "out_provenance.json").read_text())
    assert side["source"] == "b" and side["corrected"] and side["files"] == ["out.vti"]
    # once out.vti is gone, another field may write the stem in any format
    (tmp_path / "out.vti").unlink()
    run_to_completion(run_export(ExportRequest(field=first, path=tmp_path / "out.csv", source="a")))
    side = json.loads((tmp_path / "out_provenance.json").read_text())
    assert side["source"] == "a" and side["files"] == ["out.csv"]
    np.testing.assert_allclose(read_field(tmp_path / "out.csv").u, first.u, atol=1e-6)


def test_a_failed_side_file_leaves_the_old_field_and_its_provenance(tmp_path, monkeypatch):
    """The field and its side file are renamed into place together: a failure writing the
    provenance leaves the earlier ``out.vti`` and ``out_provenance.json`` as they were."""
    from napari_dvc_correct.io import report_file

    first, second = _field(), _field()
    second.u[...] += 1.0
    run_to_completion(run_export(ExportRequest(field=first, path=tmp_path / "out.vti", source="a")))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def broken(report, path):
        raise OSError("disk full")

    monkeypatch.setattr(report_file, "export_report", broken)
    with pytest.raises(OSError, match="disk full"):
        run_to_completion(
            run_export(ExportRequest(field=second, path=tmp_path / "out.vti", source="b"))
        )
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_two_exports_into_one_stem_at_once_take_turns(tmp_path):
    """Two threads export different fields to ``out.vti`` and ``out.csv`` at the same time:
    one wins, the other is refused, and the side file describes the file that is there."""
    import threading

    fields = [_field(), _field()]
    fields[1].u[...] += 1.0
    errors = []

    def export(field, name, source):
        try:
            request = ExportRequest(field=field, path=tmp_path / name, source=source)
            run_to_completion(run_export(request))
        except ValueError as error:
            errors.append(error)

    threads = [
        threading.Thread(target=export, args=(fields[0], "out.vti", "a")),
        threading.Thread(target=export, args=(fields[1], "out.csv", "b")),
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(errors) == 1 and "written from another field" in str(errors[0])
    side = json.loads((tmp_path / "out_provenance.json").read_text())
    written = [name for name in ("out.vti", "out.csv") if (tmp_path / name).exists()]
    assert side["files"] == written and len(written) == 1
    assert side["source"] == ("a" if written == ["out.vti"] else "b")
