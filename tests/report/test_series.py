"""The series figure and table (report/series.py): names, load values, what each axis holds."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.report.series import (
    QUANTITIES,
    curve_name,
    draw_series,
    parse_loads,
    series_markdown,
    state_tick,
    x_values,
)


def _rows(loads=(np.nan, np.nan, np.nan)):
    rows = []
    for state, load in zip((1, 2, 3), loads):
        for k, name in enumerate(("total", "total, corrected")):
            rows.append(
                {
                    "state": state,
                    "tick": f"state {state}",
                    "load": load,
                    "field": name,
                    "mean_residual": 10.0 * state + k,
                    "accuracy": 0.8 + 0.05 * k - 0.01 * state,
                    "meaningful": True,
                    "error_median": 0.1 * state / (k + 1),
                    "error_p95": 0.3 * state,
                    "likely_bad": 0.01 * state,
                }
            )
    return rows


def test_names_ticks_and_loads():
    assert curve_name("state 2 (total, corrected)") == "total, corrected"
    assert curve_name("State 12") == "field"
    assert curve_name("uncorrected") == "uncorrected"
    assert state_tick("state 3", 3) == "state 3"
    assert state_tick("scan0 → scan2", 2) == "scan2"
    assert state_tick("", 1, deformed="scan1") == "scan1"
    assert state_tick("", 4) == "state 4"
    assert parse_loads("", 2) is None and parse_loads(None, 2) is None
    assert parse_loads("0.5, 1e1;3", 3) == [0.5, 10.0, 3.0]
    assert parse_loads("0 1", 2) == [0.0, 1.0]
    with pytest.raises(ValueError, match="one load value per deformed state: 3 state"):
        parse_loads("1, 2", 3)
    with pytest.raises(ValueError, match="numbers separated by commas"):
        parse_loads("1, two", 2)
    with pytest.raises(ValueError, match="finite"):
        parse_loads([1.0, np.inf], 2)


def _drawn(rows):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure()
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, 3)
    draw_series(list(axes), rows)
    figure.canvas.draw()
    return axes


def test_every_state_is_ticked_and_each_curve_holds_its_values():
    rows = _rows()
    axes = _drawn(rows)
    for ax, (key, _, _) in zip(axes, QUANTITIES):
        assert [t.get_text() for t in ax.get_xticklabels()] == ["state 1", "state 2", "state 3"]
        np.testing.assert_array_equal(ax.get_xticks(), [1, 2, 3])
        assert ax.get_xlabel() == "state"
        lines = [
            line for line in ax.get_lines() if line.get_label() in ("total", "total, corrected")
        ]
        assert [line.get_label() for line in lines] == ["total", "total, corrected"]
        for line, name in zip(lines, ("total", "total, corrected")):
            expected = [row[key] for row in rows if row["field"] == name]
            np.testing.assert_allclose(line.get_xdata(), [1, 2, 3])
            np.testing.assert_allclose(line.get_ydata(), expected)
    # the paper's 0.85 line on the accuracy axes only, where p comes near it
    assert any(np.allclose(line.get_ydata(), 0.85) for line in axes[1].get_lines())
    assert not any(np.allclose(line.get_ydata(), 0.85) for line in axes[0].get_lines())
    high = [dict(row, accuracy=0.99) for row in rows]
    assert not any(np.allclose(line.get_ydata(), 0.85) for line in _drawn(high)[1].get_lines())


def test_load_values_place_the_states_and_stay_ticked():
    rows = _rows(loads=(0.0, 2.5, 10.0))
    positions, ticks, label = x_values(rows)
    np.testing.assert_array_equal(positions, [0.0, 2.5, 10.0])
    assert ticks == ["0\nstate 1", "2.5\nstate 2", "10\nstate 3"] and label == "load"
    axes = _drawn(rows)
    np.testing.assert_array_equal(axes[2].get_xticks(), [0.0, 2.5, 10.0])
    np.testing.assert_allclose(axes[2].get_lines()[0].get_xdata(), [0.0, 2.5, 10.0])


def test_markdown_table_has_a_row_per_state_and_field():
    text = series_markdown(_rows(loads=(1.0, 2.0, 3.0)), "series_plot.png")
    body = [
        line for line in text.splitlines() if line.startswith("| state ") and "load" not in line
    ]
    assert len(body) == 6
    assert body[3] == "| state 2 | 2 | total, corrected | 21.000 | 0.8300 | 0.100 | 0.600 | 2 % |"
