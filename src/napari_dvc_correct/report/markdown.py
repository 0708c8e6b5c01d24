"""A Markdown report of an accuracy evaluation that a person can open and read."""

from __future__ import annotations

import os
from pathlib import Path

from ..engine.evaluation.error_estimate import bounded_text
from ..engine.evaluation.results import Evaluation
from ..io.atomic import atomic_path
from .passes import (
    first_run_parameters,
    method_lines,
    order_text,
    oriented_line,
    pass_rows,
    subvolume_text,
)
from .tables import (
    background_rows,
    bin_rows,
    format_value,
    phase_number,
    phase_rows,
    summary_rows,
)


def markdown_table(rows: list[dict], columns: dict[str, str]) -> str:
    """A Markdown table of ``rows`` with ``columns`` mapping row keys to header texts."""
    lines = [
        "| " + " | ".join(columns.values()) + " |",
        "|" + "|".join("---" for _ in columns) + "|",
    ]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row[key]) for key in columns) + " |")
    return "\n".join(lines)


def _cell(value) -> str:
    """A table cell's text, its ``|`` escaped (``|g1 − g2|`` would split the cell)."""
    return format_value(value).replace("|", "\\|")


def _phase_section(evaluation: Evaluation) -> str:
    by_phase: dict[int, dict] = {}
    for row in phase_rows(evaluation):
        entry = by_phase.setdefault(row["phase"], {"phase": row["phase"]})
        prefix = "ref" if row["state"] == "reference" else "def"
        entry[f"{prefix}_range"] = f"{row['gray_lower']:.4g}–{row['gray_upper']:.4g}"
        entry[f"{prefix}_mean"] = row["mean_gray"]
        entry[f"{prefix}_fraction"] = row["fraction"]
    table = markdown_table(
        list(by_phase.values()),
        {
            "phase": "Phase",
            "ref_range": "Reference gray range",
            "ref_mean": "Reference mean gray",
            "ref_fraction": "Reference share",
            "def_range": "Deformed gray range",
            "def_mean": "Deformed mean gray",
            "def_fraction": "Deformed share",
        },
    )
    first, second = (phase_number(p) for p in evaluation.phase_pair)
    background = markdown_table(
        background_rows(evaluation),
        {
            "field": "Field",
            "phase": "Phase",
            "mean_residual": "Same-phase residual r0",
            "voxels": "Voxels",
        },
    )
    return (
        "## Phases (paper Table 1)\n\n"
        f"Thresholds: reference {_list(evaluation.thresholds_reference)}, deformed "
        f"{_list(evaluation.thresholds_deformed)}. Phases are numbered from 1, dark to bright, as "
        "in the Evaluate panel (the `labels_*.tif` volumes store phase k as k − 1)."
        f"\n\n{table}\n\n"
        f"The accuracy index uses phases {first} and {second}: gray contrast "
        f"|g1 − g2| = {evaluation.contrast:.4g} (mean of both states).\n\n"
        "### Background residual per phase (eq. 1)\n\n"
        'The residual inside regions of one phase, phase by phase and over all ("all" is r̄0 '
        f"of eq. 1).\n\n{background}"
    )


#: Columns of the self-correction table: row key -> header.
PASS_COLUMNS = {
    "pass": "Pass",
    "order": "Order",
    "subvolume": "Subvolume",
    "mean_gray_residual": "Mean gray residual",
    "applied": "Applied",
    "nodes_changed": "Nodes changed (fraction)",
    "accepted_nodes": "Accepted",
    "refused_nodes": "Refused",
    "noise_floor": "Noise floor",
}


def _correction_section(evaluation: Evaluation) -> str:
    """The self-correction passes of every corrected field: the order and subvolume of the
    correcting matches per pass, against the user's choice, and why ("" if none was corrected)."""
    parts = []
    for item in evaluation.fields:
        rows = pass_rows(item.field)
        if not rows:
            continue
        order, subvolume = first_run_parameters(item.field)
        chosen = (
            f"The run that made the field used {order_text(order)} order on "
            f"{subvolume_text(subvolume)} subvolumes. "
            if order and subvolume
            else ""
        )
        why = " ".join(f"Correcting matches, {line}." for line in method_lines(item.field))
        oriented = oriented_line(item.field)
        if oriented:
            why += f" Then {oriented}."
        parts.append(
            f"### {item.name}\n\n{markdown_table(rows, PASS_COLUMNS)}\n\n{chosen}{why}".rstrip()
        )
    if not parts:
        return ""
    return "## Self-correction passes\n\n" + "\n\n".join(parts)


def _list(values) -> str:
    return ", ".join(f"{v:.4g}" for v in values)


def render_markdown(
    evaluation: Evaluation,
    files: dict[str, list[Path]] | None = None,
    inputs: dict | None = None,
    title: str = "DVC accuracy evaluation",
) -> str:
    """The report text.

    Parameters
    ----------
    evaluation : Evaluation
        From :func:`napari_dvc_correct.engine.evaluation.accuracy.evaluate_fields`.
    files : dict of str -> list of Path, optional
        Files written next to the report, by kind (``"plots"``, ``"tables"``, ``"volumes"``);
        plots are embedded, the rest listed, all by their name relative to the report.
    inputs : dict, optional
        What was evaluated (file names, shapes...), shown as a list at the top.
    """
    files = files or {}
    parts = [f"# {title}"]
    for item in evaluation.fields:
        if not item.meaningful:
            parts.append(
                f"> **Warning — {item.name}: only {item.measured_nodes} of "
                f"{item.field.n_points} nodes were measured**; the others were inpainted, so "
                "its accuracy index p is not meaningful (it judges values filled in from a few "
                "matches)."
            )
    if inputs:
        parts.append("\n".join(f"- **{key}**: {value}" for key, value in inputs.items()))
    options = evaluation.options
    residual_kind = (
        "r(X) = |F(X + u(X)) − G(X)| on reference voxels"
        if evaluation.mode == "reference"
        else "r(x) = |F(x) − G'(x)| on loaded-state voxels (the paper's form)"
    )
    pair = evaluation.pair
    parts.append(
        f"Every mean gray residual here is the mean of {evaluation.residual_text}. Gray levels: "
        f"{evaluation.gray_levels.describe()}, fitted once for the scan pair. Background "
        f"residual r̄0 = {pair.background.mean:.4g} (eq. 1, the pair's, measured with "
        f"'{pair.measured_with}'; a field's p does not depend on which others are evaluated)."
        + (f" {pair.noise_text()[0].upper()}{pair.noise_text()[1:]}." if pair.noise_text() else "")
    )
    parts.append(
        f"Residual: {residual_kind}, defined inside the box spanned by the grid nodes. "
        f"Strain: {options['strain_measure']} strain, {options['strain_method']} gradient"
        + (
            f" (window {options['strain_window']} nodes)"
            if options["strain_method"] == "least-squares"
            else ""
        )
        + ", equivalent (octahedral) strain of eq. 3."
    )

    summary = summary_rows(evaluation)
    for row, item in zip(summary, evaluation.fields):  # '< bound' where below the resolution
        for key in ("median", "p95"):
            row[f"error_{key}"] = bounded_text(item.error, key)
    parts.append(
        "## Summary\n\n"
        + markdown_table(
            summary,
            {
                "field": "Field",
                "mean_residual": "Mean residual r̄",
                "background_residual": "Own background r̄0 (eq. 1)",
                "background_used": "r̄0 used",
                "mean_corrected_residual": "Mean r' = r̄ − r̄0",
                "accuracy_index": "Accuracy index p (eq. 2)",
                "error_median": "Error estimate, median (voxels)",
                "error_p95": "95th percentile",
                "likely_bad_fraction": "Share of nodes likely > 0.5 voxel (P ≥ ½)",
                "possibly_bad_fraction": "Share possibly > 0.5 voxel (P ≥ 16 %)",
                "error_resolution": "Residual's resolution, median (voxels)",
                "below_resolution_fraction": "Share below the resolution (a bound: <)",
                "max_equivalent_strain": "Max equivalent strain",
                "valid_nodes": "Measured nodes",
                "nodes": "Nodes",
            },
        )
    )
    best = max(evaluation.fields, key=lambda item: (item.meaningful, item.accuracy))
    shared = "one shared" if options.get("shared_background") else "each field's own"
    parts.append(
        f"p = 1 means the residual is at the imaging-noise level; p falls by 0.1 for each tenth of "
        f"the phase contrast ({evaluation.contrast:.4g} gray levels) that the mean residual lies "
        f"above the noise. The paper takes p = 0.85 as acceptable. Highest p: **{best.name}** "
        f"({best.accuracy:.3f}). The index uses {shared} background r̄0 "
        "(see docs/evaluation.md)."
    )
    parts.append(
        "The error estimate is in voxels per node, from the gray residual around the node. "
        "Below the residual's resolution (its noise, per node) it is a bound, not a rank: a "
        "median or 95th percentile shown as `< x` means at least half (95 %) of the nodes are "
        "below it, and x is the median (95th percentile) of max(estimate, resolution). A node "
        "is *likely* > 0.5 voxel where P(error > 0.5) ≥ ½ and *possibly* where P ≥ 16 %, "
        "with the estimate's noise σ = resolution/√3 (docs/evaluation.md)."
    )
    parts.append(_phase_section(evaluation))
    corrections = _correction_section(evaluation)
    if corrections:
        parts.append(corrections)

    plots = {Path(p).name: Path(p) for p in files.get("plots", [])}
    curves = [
        "## Against equivalent strain (paper Figs. 10–11)",
        *(f"![{name}]({name})" for name in plots if "strain" in name),
        markdown_table(
            bin_rows(evaluation),
            {
                "field": "Field",
                "strain_lower": "Strain from",
                "strain_upper": "to",
                "voxels": "Voxels",
                "mean_residual": "Mean residual",
                "mean_corrected_residual": "Mean r'",
                "accuracy_index": "p",
            },
        ),
    ]
    parts.append("\n\n".join(curves))
    others = [name for name in plots if "strain" not in name]
    if others:
        parts.append(
            "## Residual maps and distribution (paper Figs. 8–9)\n\n"
            + "\n\n".join(f"![{name}]({name})" for name in others)
        )
    listed = [
        f"- {kind}: " + ", ".join(f"`{Path(p).name}`" for p in paths)
        for kind, paths in files.items()
        if paths and kind != "plots"
    ]
    if listed:
        parts.append("## Files\n\n" + "\n".join(listed))
    return "\n\n".join(parts) + "\n"


def write_markdown(text: str, path: str | os.PathLike) -> Path:
    """Write the report text to ``path`` atomically (UTF-8)."""
    path = Path(path)
    with atomic_path(path) as temp:
        temp.write_text(text, encoding="utf-8")
    return path
