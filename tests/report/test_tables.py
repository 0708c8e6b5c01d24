"""CSV tables of an evaluation: the numbers of the evaluation, written atomically."""

import csv

import pytest

from napari_dvc_correct.report import tables
from napari_dvc_correct.report.tables import write_csv


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


def test_summary_rows_are_the_evaluation_s_numbers(evaluation, tmp_path):
    rows = tables.summary_rows(evaluation)
    assert [row["field"] for row in rows] == ["exact", "no band"]
    for row, item in zip(rows, evaluation.fields):
        assert row["accuracy_index"] == pytest.approx(item.accuracy)
        assert row["mean_residual"] == pytest.approx(item.mean_residual)
    path = write_csv(rows, tmp_path / "summary.csv")
    with open(path, newline="") as stream:
        back = list(csv.DictReader(stream))
    assert [float(r["accuracy_index"]) for r in back] == pytest.approx(
        [r["accuracy_index"] for r in rows], rel=1e-5
    )


def test_phase_rows_and_numbers(evaluation):
    rows = tables.phase_rows(evaluation)
    assert rows, "the two-phase pair has phases"
    # the engine's labels 0, 1 are the phases 1, 2 people read
    assert tables.phase_number(0) == 1 and tables.phase_number(1) == 2
    states = [row["state"] for row in rows]
    assert set(states) == {"reference", "deformed"}


def test_cells_are_integers_or_six_significant_digits():
    assert tables.format_value(7) == "7" and tables.format_value(2.0) == "2"
    assert tables.format_value(1 / 3) == "0.333333" and tables.format_value(float("nan")) == "nan"
    assert tables.format_value("text") == "text"
