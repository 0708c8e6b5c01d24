"""The Self-correct panel without Qt: the run and the per-pass table."""

from __future__ import annotations

from dataclasses import dataclass

from ..engine.correction.options import CorrectionOptions
from ..engine.fields.field import DisplacementField
from ..engine.run_options import RunOptions
from .regions_model import whole

FRAMES = {  # the panel's default is CorrectionOptions.frame: the engine's measured best
    "loaded": "warp G to the loaded state (paper, default)",
    "reference": "pull F back to the reference (no inversion)",
}
UPDATES = {
    "exact": "compose D with ΔD (exact)",
    "sum": "add ΔD to D node by node (paper)",
}


def corrected_source(source: str) -> str:
    """Name of the corrected field of the field ``source``: ``"uncorrected"`` (the field the
    Correlate panel made) -> ``"corrected"``, ``"series (total)"`` -> ``"series (total,
    corrected)"``, a field opened from a file, ``"aldvc"`` -> ``"aldvc, corrected"``; so
    correcting one field never replaces the corrected layers of another."""
    if source == "uncorrected":
        return "corrected"
    if source.endswith(")"):
        return source[:-1] + ", corrected)"
    return source + ", corrected"


def is_corrected(source: str) -> bool:
    """True for a name :func:`corrected_source` gives (such fields are not offered again)."""
    return source == "corrected" or source.endswith((", corrected)", ", corrected"))


def before_after_pair(sources: list[str], visible: list[str]) -> tuple[str, str] | None:
    """The field on view and its corrected one (or the other way round), as the View panel's
    *Before ⇄ after* toggles them: ``(shown, target)``; ``("uncorrected", "corrected")`` when
    neither of a pair is alone on view; None without a pair."""
    for shown in visible[:1] if len(visible) == 1 else []:
        partner = corrected_source(shown)
        if partner in sources:
            return shown, partner
        before = [s for s in sources if not is_corrected(s) and corrected_source(s) == shown]
        if before:
            return shown, before[0]
    if "uncorrected" in sources and "corrected" in sources:
        return (
            ("uncorrected", "corrected")
            if visible != ["corrected"]
            else ("corrected", "uncorrected")
        )
    return None


@dataclass
class CorrectionResult:
    """The corrected field and where to show it."""

    field: DisplacementField
    voxel_size: tuple
    offset: tuple


def run_correction(
    reference,
    deformed,
    field: DisplacementField,
    *,
    options: CorrectionOptions | None = None,
    mask=None,
    tiled: bool = False,
    max_memory: str | None = None,
):
    """Generator for the panel's worker: the self-correction of ``field``, then its strain.

    The DVC parameters are those that produced ``field`` (the paper's point: no new
    parameter); ``options`` (:class:`CorrectionOptions`, default: its defaults) say how the
    passes run. With ``tiled`` the correction runs out of core
    (:func:`..tiled.correction.correct_tiled_iter`: the volumes read and warped block by block
    into temporary Zarr arrays, removed at the end or on cancel), within ``max_memory``
    (``"4GB"``...; None = automatic). Returns a :class:`CorrectionResult`.
    """
    from ..jobs.correct import correct_job
    from ..tiled.memory import parse_memory

    # in memory, the region as one array, made here in the worker
    limit = parse_memory(max_memory) if max_memory else None
    run = RunOptions(tiled=bool(tiled), device="cpu", max_memory=limit)
    mask = mask if run.out_of_core else whole(mask)
    corrected = yield from correct_job(
        reference, deformed, field, options=options, mask=mask, run=run
    )
    for key in ("voxel_size", "offset", "reference_layer", "deformed_layer"):
        if key in field.metadata:
            corrected.metadata[key] = field.metadata[key]
    return CorrectionResult(
        field=corrected,
        voxel_size=tuple(field.metadata.get("voxel_size", (1.0, 1.0, 1.0))),
        offset=tuple(field.metadata.get("offset", (0.0, 0.0, 0.0))),
    )


#: Column headers of :func:`pass_rows`.
PASS_HEADERS = ["pass", "order", "subvolume", "residual", "applied", "moved"]


def pass_rows(field: DisplacementField) -> list[tuple[str, ...]]:
    """One row per pass for the dock's table (:data:`PASS_HEADERS`): pass (0: the cleaned
    input), the correcting matches' shape-function order and subvolume, mean gray residual,
    applied, share of the nodes moved by more than 0.1 voxel."""
    from ..report.passes import pass_rows as report_rows

    rows = []
    for row in report_rows(field):
        number = row["pass"]
        label = "0 (input)" if number == 0 else str(number)
        changed = f"{100 * row['nodes_changed']:.0f} %"
        residual = f"{row['mean_gray_residual']:.3f}"
        rows.append((label, row["order"], row["subvolume"], residual, row["applied"], changed))
    return rows


def method_message(field: DisplacementField) -> str:
    """What the correcting matches were, against what the user chose, and why (the engine's
    words, :func:`..report.passes.method_lines`); "" for a field without those records."""
    from ..report.passes import (
        changed_parameters,
        first_run_parameters,
        method_lines,
        order_text,
        subvolume_text,
    )

    lines = method_lines(field)
    if not lines:
        return ""
    order, subvolume = first_run_parameters(field)
    head = "Correcting matches"
    if order and subvolume:
        chosen = f"{order_text(order)} order, {subvolume_text(subvolume)}"
        head += (
            f" changed from your {chosen}"
            if changed_parameters(field)
            else f" as you chose ({chosen})"
        )
    return head + ": " + "; ".join(lines) + "."


def summary_message(field: DisplacementField) -> str:
    """The panel's line after a correction: the mean gray residual before → after, the passes
    applied, why the loop stopped (``metadata["correction"]["stop_reason"]``), and the
    correcting matches' order and subvolume with the reason (:func:`method_message`)."""
    from ..report.passes import residual_frame

    info = field.metadata.get("correction", {})
    before = float(info.get("mean_gray_residual_before", float("nan")))
    after = float(info.get("mean_gray_residual_after", float("nan")))
    text = (
        f"Mean gray residual ({residual_frame(field)}) {before:.3f} → {after:.3f} "
        f"({int(info.get('passes_applied', 0))} pass(es) applied)."
    )
    reason = info.get("stop_reason")
    if reason:
        text += f" Stopped: {reason}."
    method = method_message(field)
    if method:
        text += " " + method
    from ..report.passes import flag_line, gray_level_line, noise_fit_line, oriented_line

    lines = (gray_level_line(field), oriented_line(field), flag_line(field), noise_fit_line(field))
    for line in lines:
        if line:
            text += " " + line[0].upper() + line[1:] + "."
    return text


@dataclass
class SeriesCorrection:
    """A self-corrected series: one :class:`CorrectionResult` per state after the first, in
    order, and ``series``, the corrected fields as the 4-D layers show them (state 0 without
    displacement first, :func:`..layers.series_fields`), made in the worker so the quantity on
    view is computed there for every state, state 0 included."""

    results: list
    series: list


def run_series_correction(pairs, fields, **options):
    """Self-correct every state of a series: ``pairs[k]`` = (G, F_k) for ``fields[k]``.

    Returns a :class:`SeriesCorrection`. ``options`` are those of :func:`run_correction`.
    """
    from ..engine.progress import Progress, forward_progress, state_of
    from ..layers import series_fields

    results = []
    if not options.get("tiled"):  # the region as one array, once for every state
        options["mask"] = whole(options.get("mask"))
    for k, ((reference, deformed), field) in enumerate(zip(pairs, fields), start=1):
        label = state_of(k, len(fields))  # every stage line says the state (and how many)
        yield Progress(label, 0, 1, "self-correcting")
        result = yield from forward_progress(
            run_correction(reference, deformed, field, **options), label
        )
        results.append(result)
    return SeriesCorrection(results, series_fields([r.field for r in results]))


#: Column headers of :func:`series_rows`.
SERIES_HEADERS = ["state", "mean residual", "passes", "matches", "nodes moved"]


def series_rows(results) -> list[tuple[str, ...]]:
    """One row per state for the dock's table (:data:`SERIES_HEADERS`): state, residual
    before → after, passes, the correcting matches' order and subvolume, nodes moved."""
    rows = []
    for k, result in enumerate(results, start=1):
        info = result.field.metadata.get("correction", {})
        before = info.get("mean_gray_residual_before", float("nan"))
        after = info.get("mean_gray_residual_after", float("nan"))
        table = pass_rows(result.field)
        moved = table[-1][5] if table else "—"
        matches = f"{table[-1][1]}, {table[-1][2]}" if len(table) > 1 else "—"
        passes = str(info.get("passes_applied", 0))
        rows.append((f"state {k}", f"{before:.3f} → {after:.3f}", passes, matches, moved))
    return rows


def series_method_message(results) -> str:
    """:func:`method_message` of every state of a series, each sentence led by the states it is
    for (``State 2: ...``, ``States 1 and 3: ...``); "" when no state has one."""
    states: dict[str, list[int]] = {}
    for k, result in enumerate(results, start=1):
        text = method_message(result.field)
        if text:
            states.setdefault(text, []).append(k)
    parts = []
    for text, numbers in states.items():
        names = [str(n) for n in numbers]
        label = (
            f"State {names[0]}"
            if len(names) == 1
            else f"States {', '.join(names[:-1])} and {names[-1]}"
        )
        parts.append(f"{label}: {text}")
    return " ".join(parts)
