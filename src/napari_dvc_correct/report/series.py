"""A scan series evaluated state by state: the mean gray residual, the accuracy index p and the
voxel error estimate against the load state, as rows, a figure and a Markdown table.

The same drawing (:func:`draw_series`) serves the Evaluate panel (on its dark Qt canvas) and the
command line's series report (:func:`write_series_report`, PNG through Agg). By default the x
axis is the state's position in the series and every state is a tick named after it; with the
user's load values (one per deformed state) the states sit at those values, still ticked.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .plots import PAPER_ACCEPTANCE, _figure, _save, field_color

#: The quantities plotted, in panel order: row key, axes title, y label.
QUANTITIES = (
    ("mean_residual", "mean gray residual", "gray levels"),
    ("accuracy", "accuracy index p", "p"),
    ("error_median", "error estimate (median)", "voxel"),
)
#: The columns of :func:`series_rows`, in the order the CSV writes them.
COLUMNS = (
    "state",
    "tick",
    "load",
    "field",
    "mean_residual",
    "accuracy",
    "meaningful",
    "error_median",
    "error_p95",
    "error_median_shown",
    "error_p95_shown",
    "error_resolution",
    "likely_bad",
    "possibly_bad",
)
_STATE = re.compile(r"^\s*state\s+\d+\s*", re.IGNORECASE)


def curve_name(field_name: str) -> str:
    """The curve a field belongs to across states: its name without the leading ``state N``
    and the brackets (``"state 2 (total, corrected)"`` -> ``"total, corrected"``; ``"field"``
    when nothing is left)."""
    rest = _STATE.sub("", field_name).strip()
    if rest.startswith("(") and rest.endswith(")"):
        rest = rest[1:-1].strip()
    return rest or "field"


def state_tick(label: str, position: int, deformed: str | None = None) -> str:
    """The tick of a state: its label ``"state k"`` as it is, the deformed volume of a pair
    label ``"a → b"``, else ``deformed`` (the panel's pair) or ``"state <position>"``."""
    label = (label or "").strip()
    if "→" in label:
        return label.split("→", 1)[1].strip()
    if label:
        return label
    return deformed or f"state {position}"


def parse_loads(text: str | Sequence[float] | None, n_states: int) -> list[float] | None:
    """The user's load values, one per deformed state (commas or spaces between them), or None
    for an empty text.

    Raises
    ------
    ValueError
        A value that is not a finite number, or not exactly ``n_states`` of them.
    """
    if text is None:
        return None
    if isinstance(text, str):
        parts = [p for p in re.split(r"[,;\s]+", text.strip()) if p]
        if not parts:
            return None
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(
                f"load values must be numbers separated by commas, got {text!r}"
            ) from None
    else:
        values = [float(v) for v in text]
    if not all(np.isfinite(values)):
        raise ValueError(f"load values must be finite numbers, got {values}")
    if len(values) != n_states:
        raise ValueError(
            f"give one load value per deformed state: {n_states} state(s) evaluated, "
            f"{len(values)} value(s) given"
        )
    return values


def series_rows(results, loads=None, deformed: str | None = None) -> list[dict]:
    """One row per state and field, in the order of ``results``.

    Parameters
    ----------
    results : list of (label, Evaluation)
        Each deformed state's evaluation against its own pair, in loading order.
    loads : sequence of float, optional
        The load value of each state (:func:`parse_loads`); default: none (x is the state).
    deformed : str, optional
        The tick of a state whose label is empty (the Evaluate panel's own pair).

    Returns
    -------
    list of dict
        Keys :data:`COLUMNS`: ``state`` (1, 2, ... in order), ``tick``, ``load`` (NaN when not
        given), ``field`` (:func:`curve_name`), ``mean_residual`` (gray levels), ``accuracy``
        (p), ``meaningful``, ``error_median``/``error_p95`` (voxel), the same as shown
        (``error_median_shown``/``error_p95_shown``: ``"< x"`` where the residual's resolution
        bounds them), ``error_resolution`` (its median, voxel), ``likely_bad`` and
        ``possibly_bad`` (shares of nodes off by more than 0.5 voxel with a probability of at
        least ½ and 16 %: :func:`..engine.evaluation.error_estimate.error_summary`).
    """
    from ..engine.evaluation.error_estimate import bounded_text

    loads = parse_loads(loads, len(results)) if loads is not None else None
    rows = []
    for position, (label, evaluation) in enumerate(results, start=1):
        for item in evaluation.fields:
            error = item.error
            rows.append(
                {
                    "state": position,
                    "tick": state_tick(label, position, deformed),
                    "load": float(loads[position - 1]) if loads else float("nan"),
                    "field": curve_name(item.name),
                    "mean_residual": float(item.mean_residual),
                    "accuracy": float(item.accuracy),
                    "meaningful": bool(item.meaningful),
                    "error_median": float(error["median"]),
                    "error_p95": float(error["p95"]),
                    "error_median_shown": bounded_text(error, "median"),
                    "error_p95_shown": bounded_text(error, "p95"),
                    "error_resolution": float(error["resolution"]),
                    "likely_bad": float(error["likely_bad"]),
                    "possibly_bad": float(error["possibly_bad"]),
                }
            )
    return rows


def curves(rows: list[dict]) -> dict[str, list[dict]]:
    """The rows of each curve (field name), in state order."""
    grouped: dict[str, list[dict]] = {}
    for row in rows:
        grouped.setdefault(row["field"], []).append(row)
    return grouped


def x_values(rows: list[dict]) -> tuple[np.ndarray, list[str], str]:
    """The states' x positions, their tick labels and the axis label: the load values where
    given (ticks ``"<load>"``), else the state positions 1, 2, ... (ticks = state names)."""
    states = {}
    for row in rows:
        states.setdefault(row["state"], row)
    ordered = [states[k] for k in sorted(states)]
    with_loads = ordered and all(np.isfinite(r["load"]) for r in ordered)
    if with_loads:
        return (
            np.array([r["load"] for r in ordered]),
            [f"{r['load']:g}\n{r['tick']}" for r in ordered],
            "load",
        )
    return np.array([float(r["state"]) for r in ordered]), [r["tick"] for r in ordered], "state"


def draw_series(axes, rows: list[dict], x_label: str | None = None, colors=None) -> None:
    """Draw the three quantities of :data:`QUANTITIES` on ``axes`` (three matplotlib axes),
    one curve per field, every state ticked on x."""
    positions, ticks, default_label = x_values(rows)
    by_state = {row["state"]: x for row, x in zip(_first_per_state(rows), positions)}
    for index, (name, group) in enumerate(curves(rows).items()):
        color = colors[index % len(colors)] if colors else field_color(index)
        xs = [by_state[row["state"]] for row in group]
        for ax, (key, _, _) in zip(axes, QUANTITIES):
            ax.plot(xs, [row[key] for row in group], "o-", color=color, markersize=4, label=name)
    for ax, (key, title, unit) in zip(axes, QUANTITIES):
        ax.set_title(title, fontsize=9)
        ax.set_ylabel(unit, fontsize=8)
        ax.set_xlabel(x_label or default_label, fontsize=8)
        ax.set_xticks(positions, ticks, fontsize=7)
        values = [row[key] for row in rows if np.isfinite(row[key])]
        if key == "accuracy" and values and min(values) < PAPER_ACCEPTANCE + 0.05:
            # the paper's line, where p comes near it (else it would flatten the curves)
            ax.axhline(PAPER_ACCEPTANCE, color="0.5", linestyle=":", linewidth=1)
    figure = axes[0].figure
    for legend in list(figure.legends):  # a redraw replaces the legend
        legend.remove()
    if rows:  # one legend above the three panels, clear of the curves
        handles, labels = axes[0].get_legend_handles_labels()
        figure.legend(
            handles,
            labels,
            loc="outside upper center",
            ncols=len(labels),
            fontsize=7,
            frameon=False,
        )


def _first_per_state(rows: list[dict]) -> list[dict]:
    seen, first = set(), []
    for row in sorted(rows, key=lambda r: r["state"]):
        if row["state"] not in seen:
            seen.add(row["state"])
            first.append(row)
    return first


def plot_series(rows: list[dict], path: str | os.PathLike, x_label: str | None = None) -> Path:
    """The series figure as a PNG (three panels side by side), written atomically."""
    figure = _figure(11.0, 3.6)
    axes = figure.subplots(1, len(QUANTITIES))
    draw_series(list(axes), rows, x_label)
    return _save(figure, path)


def series_markdown(rows: list[dict], image: str | None = None) -> str:
    """A Markdown page: what is plotted, the figure and one table row per state and field."""
    lines = [
        "# Series: residual, accuracy index and error estimate per state",
        "",
        "Each deformed state evaluated against its own pair (reference state, that state): the "
        "mean gray residual (gray levels), the accuracy index p (0.85: the paper's line) and "
        "the median of the per-node error estimate (voxel).",
        "",
    ]
    if image:
        lines += [f"![series]({image})", ""]
    lines += [
        "| state | load | field | mean residual | p | error median (voxel) | 95 % "
        "| likely > 0.5 voxel (P ≥ ½) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        load = f"{row['load']:g}" if np.isfinite(row["load"]) else ""
        p = f"{row['accuracy']:.4f}" + ("" if row["meaningful"] else " (not meaningful)")
        tick = row["tick"].replace("|", "\\|")
        lines.append(
            f"| {tick} | {load} | {row['field'].replace('|', chr(92) + '|')} | "
            f"{row['mean_residual']:.3f} | {p} | {_shown(row, 'error_median')} | "
            f"{_shown(row, 'error_p95')} | {100 * row['likely_bad']:.0f} % |"
        )
    return "\n".join(lines) + "\n"


def _shown(row: dict, key: str) -> str:
    """The error estimate's value as shown (``"< x"`` below the resolution), else its number."""
    return row.get(f"{key}_shown") or f"{row[key]:.3f}"


def write_series_report(
    results, out_dir: str | os.PathLike, loads=None, x_label: str | None = None
) -> list[Path]:
    """Write ``series_evaluation.csv``, ``series_plot.png`` and ``series_report.md`` into
    ``out_dir`` (each atomically); returns the files."""
    from ..io.atomic import atomic_path
    from .tables import write_csv

    out_dir = Path(out_dir)
    rows = series_rows(results, loads)
    table = write_csv(
        [{k: row[k] for k in COLUMNS} for row in rows], out_dir / "series_evaluation.csv"
    )
    image = plot_series(rows, out_dir / "series_plot.png", x_label)
    page = out_dir / "series_report.md"
    with atomic_path(page) as temp:
        temp.write_text(series_markdown(rows, image.name), encoding="utf-8")
    return [table, image, page]
