"""The Markdown report: tables whose cells survive a ``|``, the evaluation's numbers in it."""

from napari_dvc_correct.report import markdown


def test_a_markdown_table_escapes_bars_in_cells():
    table = markdown.markdown_table(
        [{"a": 1, "b": "|g1 − g2|"}, {"a": 2.5, "b": "x"}], {"a": "A", "b": "B"}
    )
    assert table.splitlines() == [
        "| A | B |",
        "|---|---|",
        "| 1 | \\|g1 − g2\\| |",
        "| 2.5 | x |",
    ]


def test_the_report_names_every_field_and_its_accuracy(evaluation, tmp_path):
    text = markdown.render_markdown(evaluation)
    assert text.startswith("#")
    for item in evaluation.fields:
        assert item.name in text
        assert f"{item.accuracy:.6g}" in text
    path = markdown.write_markdown(text, tmp_path / "report.md")
    assert path.read_text(encoding="utf-8") == text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.md"]
