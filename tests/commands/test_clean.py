"""``napari-dvc-correct clean``: a failed node and an outlier replaced, the count said."""

import numpy as np

from napari_dvc_correct.cli import main
from napari_dvc_correct.commands import clean
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.io.npz import load_field, save_field


def test_clean_replaces_a_failed_node_and_an_outlier(tmp_path, capsys):
    field = DisplacementField.zeros((10.0, 10.0, 10.0), (5.0, 5.0, 5.0), (5, 5, 5))
    field.u[:] = (0.5, -0.25, 1.0)
    field.u[2, 2, 2] = (9.0, 9.0, 9.0)  # an outlier among uniform neighbours
    field.u[1, 1, 1] = np.nan
    field.status[1, 1, 1] = Status.DIVERGED
    save_field(field, tmp_path / "raw.npz")
    assert main(["clean", str(tmp_path / "raw.npz"), "--out", str(tmp_path / "clean.npz")]) == 0
    cleaned = load_field(tmp_path / "clean.npz")
    np.testing.assert_allclose(cleaned.u[2, 2, 2], (0.5, -0.25, 1.0), atol=1e-9)
    np.testing.assert_allclose(cleaned.u[1, 1, 1], (0.5, -0.25, 1.0), atol=1e-9)
    assert cleaned.provenance[2, 2, 2] == Provenance.REPLACED
    assert cleaned.metadata["cleaned_from"] == str(tmp_path / "raw.npz")
    said = capsys.readouterr().out
    assert said.startswith("replaced 2 of 125 nodes (1 failed") and "1 outliers" in said
    assert said == f"{clean.counts_text(cleaned)}; wrote {tmp_path / 'clean.npz'}\n"


def test_clean_reads_and_writes_our_dvcfield(tmp_path):
    field = DisplacementField.zeros((10.0, 10.0, 10.0), (5.0, 5.0, 5.0), (5, 5, 5))
    field.u[:] = (0.5, -0.25, 1.0)
    save_field(field, tmp_path / "raw.dvcfield")
    out = tmp_path / "clean.dvcfield"  # was refused: "--out ... must end with .npz"
    assert main(["clean", str(tmp_path / "raw.dvcfield"), "--out", str(out)]) == 0
    np.testing.assert_allclose(load_field(out).u, field.u)
