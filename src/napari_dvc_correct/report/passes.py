"""The self-correction passes of a field in words and rows: one wording for the Self-correct
panel, the command line and the report.

The paper promises the correction reuses "the same DVC parameters"; where the engine's
correcting matches use another shape-function order or subvolume
(:class:`..engine.correction.record.CorrectionPass` ``order``, ``subvolume``, ``method``), every
front end says so, with the engine's reason.
"""

from __future__ import annotations

from ..engine.correction.record import CorrectionPass, correction_table
from ..engine.fields.field import DisplacementField

_ORDER_NAMES = {1: "first", 2: "second"}


def order_text(order: int) -> str:
    """Shape-function order as a word ("first", "second"), "—" where not recorded (0)."""
    return _ORDER_NAMES.get(int(order), str(int(order))) if int(order) else "—"


def subvolume_text(subvolume: int) -> str:
    """Subvolume edge as ``"15³"`` (voxels), "—" where not recorded (0)."""
    return f"{int(subvolume)}³" if int(subvolume) else "—"


def first_run_parameters(field: DisplacementField) -> tuple[int, int]:
    """The (order, subvolume) the user chose for the run that made the field (0 if unknown)."""
    params = field.params or {}
    try:
        return int(params.get("order", 0)), int(params.get("subvolume", 0))
    except (TypeError, ValueError):
        return 0, 0


def method_lines(field: DisplacementField) -> list[str]:
    """Why the correcting matches used their order and subvolume, one line per run of passes
    with the same reason, e.g. ``"passes 1–2: second order on 15³ instead of ..."``.

    Falls back to ``metadata["correction"]["pass_method"]`` where the records carry none, and
    returns [] for a field that was not corrected (or an older file without the words).
    """
    groups: list[tuple[list[int], str]] = []
    for entry in correction_table(field):
        if entry.number == 0 or not entry.method:
            continue
        if groups and groups[-1][1] == entry.method:
            groups[-1][0].append(entry.number)
        else:
            groups.append(([entry.number], entry.method))
    if not groups:
        # no pass ran: the words alone (every caller names the correcting matches itself)
        method = field.metadata.get("correction", {}).get("pass_method")
        return [str(method)] if method else []
    lines = []
    for numbers, method in groups:
        span = f"pass {numbers[0]}" if len(numbers) == 1 else f"passes {numbers[0]}–{numbers[-1]}"
        lines.append(f"{span}: {method}")
    return lines


def changed_parameters(field: DisplacementField) -> bool:
    """True if some pass matched with another order or subvolume than the first run's."""
    order, subvolume = first_run_parameters(field)
    for entry in correction_table(field):
        if entry.number == 0 or not entry.order:
            continue
        if (order and entry.order != order) or (subvolume and entry.subvolume != subvolume):
            return True
    return False


def _row(entry: CorrectionPass) -> dict:
    first = entry.number == 0
    return {
        "pass": int(entry.number),
        "order": "—" if first else order_text(entry.order),
        "subvolume": "—" if first else subvolume_text(entry.subvolume),
        "mean_gray_residual": float(entry.mean_gray_residual),
        "applied": "—" if first else ("yes" if entry.accepted else "no"),
        "nodes_changed": float(entry.fraction_changed),
        "mean_change": float(entry.mean_change),
        "max_change": float(entry.max_change),
        "accepted_nodes": int(entry.accepted_nodes),
        "refused_nodes": int(entry.rejected_nodes),
        "noise_floor": float(entry.noise_floor),
        "matched_nodes": int(entry.matched_nodes),
    }


def pass_rows(field: DisplacementField) -> list[dict]:
    """One row per pass (pass 0 = the cleaned input): order, subvolume, residual, applied,
    nodes changed (fraction), mean and max change (voxels), accepted/refused nodes, noise
    floor, matches run. [] for a field that was not corrected."""
    return [_row(entry) for entry in correction_table(field)]


def gray_level_line(field: DisplacementField) -> str:
    """The gray-level map the correction judged by, in words ("" for a field without one):
    every residual of the correction is ``|map(F~) - G|`` in the reference's gray levels."""
    gray = field.metadata.get("gray_levels") or {}
    description = gray.get("description")
    if not description:
        return ""
    return (
        f"gray levels of the loaded scan mapped onto the reference's: {description}; "
        "residuals are in the reference's gray levels"
    )


def flag_line(field: DisplacementField) -> str:
    """What the correction flagged after its passes, in words ("" for an uncorrected field)."""
    info = field.metadata.get("correction") or {}
    if "flagged_after" not in info:
        return ""
    flagged = int(info.get("flagged_after", 0))
    crack = int(info.get("discontinuity_nodes", 0))
    shielded = int(info.get("shielded_nodes", 0))
    text = (
        f"flagged after the passes: {flagged - crack} nodes whose residual no small error "
        f"explains (outlier replaced), {crack} along a discontinuity (a crack: discontinuity)"
    )
    measured = info.get("measured_nodes")
    if measured:  # masked nodes (outside the user's region) are not measured, not flagged
        text += f"; {flagged / measured:.1%} of the {measured} measured nodes"
    if shielded:
        text += f"; {shielded} nodes near it kept their values"
    return text


def noise_fit_line(field: DisplacementField) -> str:
    """Where the correction replaced nodes by the fit over their noise-only neighbourhoods, in
    words ("" where it did not run)."""
    info = (field.metadata.get("correction") or {}).get("noise_fit")
    if not info:
        return ""
    if info.get("not_run"):
        return f"regularised: no node ({info['not_run']})"
    text = (
        f"regularised: {info['fitted_nodes']} nodes took the least-squares affine fit over "
        f"their {info['neighbourhood_nodes']}³ neighbourhood, where it held only matching noise "
        f"({info['eligible_nodes']} tested)"
    )
    if info.get("median_variance_ratio") is not None:
        text += f"; their variance x{info['median_variance_ratio']:.2f} (median)"
    return text


def oriented_line(field: DisplacementField) -> str:
    """The correction's oriented step in words ("" where it did not run): after the passes,
    nodes whose field varies across a plane re-matched on the original pair under windows
    narrow across that plane and wide along it (``metadata["correction"]["oriented"]``)."""
    info = (field.metadata.get("correction") or {}).get("oriented") or {}
    if not info.get("ran"):
        return ""
    text = (
        f"re-matched along the field's plane: {int(info.get('accepted_nodes', 0))} of "
        f"{int(info.get('planar_nodes', 0))} nodes whose field varies across a plane took a "
        "first-order match of the original pair under a window of std "
        f"{float(info.get('across', 0.0)):g} voxels across that plane and "
        f"{float(info.get('along', 0.0)):g} along it ({int(info.get('subvolume', 0))}³ boxes)"
    )
    if info.get("deblurred_nodes"):
        text += (
            f", the window's blur taken out of {int(info['deblurred_nodes'])} of them (a local "
            "quadratic of the matches across and along the plane)"
        )
    return text + ", where the field still bent the first run's first-order cubes after the passes"


def residual_frame(field: DisplacementField) -> str:
    """What the correction's mean gray residual is, as Evaluate states it (same definition:
    Evaluate in the same frame gives the same number, docs/evaluation.md)."""
    info = field.metadata.get("correction", {})
    mapped = bool(field.metadata.get("gray_levels"))
    f = "map(F)" if mapped else "F"
    levels = "reference gray levels" if mapped else "raw gray levels"
    if info.get("frame", "loaded") == "loaded":
        return f"|{f} − G'|, loaded frame, {levels}"
    return f"|{f}(X + u) − G(X)|, reference frame, {levels}"
