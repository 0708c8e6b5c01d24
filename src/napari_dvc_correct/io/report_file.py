"""A report of values written as a file: JSON for ``.json``, readable Markdown otherwise (atomic)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .npz import _json_default


# -- reports -----------------------------------------------------------------------------------
def to_json(report, **options) -> str:
    """``report`` as JSON text, numpy scalars and arrays converted as :func:`export_report`
    writes them (``options``: those of :func:`json.dumps`, e.g. ``sort_keys=True``)."""
    return json.dumps(report, default=_json_default, **options)


def export_report(report: dict, path: str | os.PathLike) -> Path:
    """Write an evaluation report: JSON for ``.json``, readable Markdown otherwise.

    Parameters
    ----------
    report : dict
        JSON-serialisable values (numpy scalars and arrays are converted); nested dicts become
        sections in Markdown.
    """
    path = Path(path)
    with atomic_path(path) as temp:
        if path.suffix.lower() == ".json":
            text = to_json(report, indent=2)
        else:
            text = _markdown(report)
        temp.write_text(text + "\n", encoding="utf-8")
    return path


def _markdown(report: dict, level: int = 1) -> str:
    lines = []
    title = report.get("title", "DVC evaluation report") if level == 1 else None
    if title:
        lines.append(f"# {title}\n")
    scalars = {k: v for k, v in report.items() if not isinstance(v, dict) and k != "title"}
    if scalars:
        lines += ["| quantity | value |", "|---|---|"]
        for key, value in scalars.items():
            if isinstance(value, (float, np.floating)):
                value = f"{value:.6g}"
            elif isinstance(value, (list, tuple, np.ndarray)):
                value = ", ".join(
                    f"{v:.4g}" if isinstance(v, (float, np.floating)) else str(v)
                    for v in np.asarray(value).ravel()[:50]
                )
            lines.append(f"| {key} | {value} |")
        lines.append("")
    for key, value in report.items():
        if isinstance(value, dict):
            lines.append(f"{'#' * min(level + 1, 6)} {key}\n")
            lines.append(_markdown(value, level + 1))
    return "\n".join(lines)
