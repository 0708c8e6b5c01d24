"""CSV tables of an accuracy evaluation: phases (paper Table 1), summary, strain bins, background.

Every table is a list of dicts (one per row, same keys) so the Markdown report and the CSV files
show the same numbers; :func:`write_csv` writes one atomically. Phases are numbered from 1, dark
to bright, as the Evaluate panel numbers them (:func:`phase_number`; the engine's labels and the
``labels_*.tif`` volumes hold phase ``k`` as ``k - 1``).
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

from ..engine.evaluation.results import Evaluation
from ..io.atomic import atomic_path


def _number(value):
    """Plain Python number (NaN stays NaN), for CSV and Markdown."""
    if isinstance(value, (np.integer, int)) and not isinstance(value, bool):
        return int(value)
    return float(value)


def phase_number(label: int) -> int:
    """The phase number people read (1, 2, ...) of the engine's phase label (0, 1, ...)."""
    return int(label) + 1


def phase_rows(evaluation: Evaluation) -> list[dict]:
    """One row per state and phase: gray range, mean gray, voxels (paper Table 1)."""
    rows = []
    for state, table in (
        ("reference", evaluation.phases_reference),
        ("deformed", evaluation.phases_deformed),
    ):
        for stats in table:
            rows.append(
                {
                    "state": state,
                    "phase": phase_number(stats.phase),
                    "gray_lower": stats.lower,
                    "gray_upper": stats.upper,
                    "mean_gray": stats.mean_gray,
                    "voxels": stats.voxels,
                    "fraction": stats.fraction,
                }
            )
    return rows


def summary_rows(evaluation: Evaluation) -> list[dict]:
    """One row per field: mean residual, background (eq. 1), accuracy index (eq. 2), strain."""
    rows = []
    for item in evaluation.fields:
        strain = item.equivalent_strain[np.isfinite(item.equivalent_strain)]
        error = item.error
        rows.append(
            {
                "field": item.name,
                "residual": evaluation.residual_text,
                "mean_residual": item.mean_residual,
                "background_residual": item.background.mean,
                "background_used": item.background_used,
                "mean_corrected_residual": item.mean_corrected_residual,
                "phase_contrast": evaluation.contrast,
                "accuracy_index": item.accuracy,
                "accuracy_meaningful": "yes" if item.meaningful else "no",
                "error_median": error["median"],
                "error_p95": error["p95"],
                "error_median_is_bound": "yes" if error["median_is_bound"] else "no",
                "error_median_bound": error["median_bound"],
                "error_p95_is_bound": "yes" if error["p95_is_bound"] else "no",
                "error_p95_bound": error["p95_bound"],
                "likely_bad_fraction": error["likely_bad"],
                "possibly_bad_fraction": error["possibly_bad"],
                "error_resolution": error["resolution"],
                "below_resolution_fraction": error["below_resolution"],
                "residual_voxels": item.voxels,
                "same_phase_voxels": item.background.voxels,
                "valid_nodes": item.measured_nodes,
                "nodes": item.field.n_points,
                "mean_equivalent_strain": float(strain.mean()) if strain.size else math.nan,
                "max_equivalent_strain": float(strain.max()) if strain.size else math.nan,
            }
        )
    return rows


def bin_rows(evaluation: Evaluation) -> list[dict]:
    """One row per field and equivalent-strain bin (paper Figs. 10 and 11)."""
    rows = []
    for item in evaluation.fields:
        bins = item.bins
        for b in range(bins.voxels.size):
            rows.append(
                {
                    "field": item.name,
                    "strain_lower": float(bins.edges[b]),
                    "strain_upper": float(bins.edges[b + 1]),
                    "strain_center": float(bins.centers[b]),
                    "voxels": int(bins.voxels[b]),
                    "mean_residual": float(bins.mean_residual[b]),
                    "mean_corrected_residual": float(bins.mean_residual[b] - item.background_used),
                    "accuracy_index": float(item.bin_accuracy[b]),
                }
            )
    return rows


def background_rows(evaluation: Evaluation) -> list[dict]:
    """One row per field and phase: the same-phase residual of eq. 1, phase by phase."""
    rows = []
    for item in evaluation.fields:
        for phase, mean, voxels in item.background.per_phase:
            rows.append(
                {
                    "field": item.name,
                    "phase": phase_number(phase),
                    "mean_residual": mean,
                    "voxels": voxels,
                }
            )
        rows.append(
            {
                "field": item.name,
                "phase": "all",
                "mean_residual": item.background.mean,
                "voxels": item.background.voxels,
            }
        )
    return rows


def format_value(value) -> str:
    """Text for a table cell: integers as they are, floats with 6 significant digits."""
    if isinstance(value, str):
        return value
    value = _number(value)
    if isinstance(value, int):
        return str(value)
    if math.isnan(value):
        return "nan"
    return f"{value:.6g}"


def write_csv(rows: list[dict], path: str | os.PathLike) -> Path:
    """Write ``rows`` (dicts with the same keys) as a CSV file with a header, atomically."""
    path = Path(path)
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    columns = list(rows[0])
    with atomic_path(path) as temp:
        with open(temp, "w", newline="", encoding="utf-8") as stream:
            writer = csv.writer(stream)
            writer.writerow(columns)
            for row in rows:
                writer.writerow([format_value(row[c]) for c in columns])
    return path
