"""PNG plots of an evaluation: one colour per field, the panel's; files written whole."""

from napari_dvc_correct.report import plots


def test_report_colours_are_the_panel_s(evaluation, tmp_path, monkeypatch):
    """Each field has one colour in the report and the Evaluate panel (first orange, then
    blue), not matplotlib's default cycle (which made the report's the reverse)."""
    from matplotlib.colors import to_hex

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


def test_the_plots_are_pngs_of_the_evaluation(evaluation, tmp_path):
    from matplotlib.image import imread

    written = [
        plots.plot_accuracy_vs_strain(evaluation, tmp_path / "accuracy.png"),
        plots.plot_residual_vs_strain(evaluation, tmp_path / "residual.png"),
    ]
    for path in written:
        image = imread(path)
        assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["accuracy.png", "residual.png"]
    assert plots.field_color(0) == "#f28e2b" and plots.field_color(1) == "#4e9fde"
