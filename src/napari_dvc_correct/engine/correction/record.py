"""The record of a self-correction pass (:mod:`.self_correction`), as stored in a field's metadata."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

from ..fields.field import DisplacementField

#: A node counts as "changed" by a pass when its displacement moves by more than this (voxels).
CHANGE_THRESHOLD = 0.1


@dataclass(frozen=True)
class CorrectionPass:
    """The record of one correction pass (pass 0 = the cleaned input field).

    Attributes
    ----------
    number : int
        Pass number, 0 for the cleaned input.
    mean_gray_residual : float
        Mean gray residual of the field after the pass, in the pass's frame (gray levels).
    noise_floor : float
        The imaging-noise floor the pass is judged against (gray levels): eq. 1's background
        residual ``r0`` or the lower quartile of the nodes' cell residuals, whichever is smaller,
        the smallest seen so far (:class:`.acceptance.Judge`).
    residual_before : float
        Mean gray residual before the pass (gray levels; pass 0: same as after).
    local_residual_before, local_residual_after : float
        Mean over the nodes of the local residual (reference frame, over each node's cell)
        before and after the pass (gray levels).
    accepted : bool
        Whether the pass changed the field at all (some node accepted).
    accepted_nodes, rejected_nodes : int
        Nodes whose correction was kept / refused (local residual rose by more than the noise
        allows; they keep their previous value).
    improved_nodes : int
        Accepted nodes whose residual over their subvolume fell by more than the noise allows
        (and more than a 0.01-voxel change explains): the regions that "improve above the
        floor", which decide whether another pass runs.
    fraction_changed : float
        Fraction of the (unmasked) nodes moved by more than :data:`CHANGE_THRESHOLD` voxels.
    mean_change, max_change : float
        Node displacement change of the pass (voxels).
    converged_fraction : float
        Usable fraction of the pass's correcting matches (matched or filled in, of all its
        nodes: :class:`..fields.field.NodeCounts`).
    seconds : float
        Wall time of the pass.
    unsupported_nodes : int
        Of the refused nodes, those refused because their update would read ``ΔD`` more than a
        step beyond the good correcting matches (:func:`.acceptance.unsupported_updates`).
    matched_nodes : int
        Correcting matches run in this pass (after the first pass, only those near the nodes
        the previous pass changed: :mod:`.rematch_region`; the others are reused).
    judged_nodes : int
        Nodes whose update was proposed and judged (the others kept their value unjudged).
    stop : str
        Why the loop stopped after this pass ("" where another pass ran).
    failed_match_nodes : int
        Of the refused nodes, good nodes whose correcting match failed (they keep their value
        and status).
    noise_refused_nodes : int
        Of the refused nodes, those whose correction the correcting match's own noise explains
        (:func:`.acceptance.shrink_to_support`), or whose whole neighbourhood holds only noise
        (:func:`.acceptance.noise_only_corrections`).
    order, subvolume : int
        Shape-function order and subvolume edge (voxels) of the pass's correcting matches
        (0 for pass 0 and for records of older files).
    method : str
        Why the correcting matches used that order and subvolume, in words (the user chose
        the first run's parameters; the correction may change them, and says so here).
    """

    number: int
    mean_gray_residual: float
    noise_floor: float
    residual_before: float
    local_residual_before: float
    local_residual_after: float
    accepted: bool
    accepted_nodes: int
    rejected_nodes: int
    improved_nodes: int
    fraction_changed: float
    mean_change: float
    max_change: float
    converged_fraction: float
    seconds: float
    unsupported_nodes: int = 0
    matched_nodes: int = 0
    judged_nodes: int = 0
    stop: str = ""
    failed_match_nodes: int = 0
    noise_refused_nodes: int = 0
    order: int = 0
    subvolume: int = 0
    method: str = ""

    def to_dict(self) -> dict:
        """Plain dict for the field's JSON metadata (``number`` stored as ``"pass"``, the key
        older files and readers use)."""
        values = dataclasses.asdict(self)
        return {"pass": values.pop("number"), **values}

    @classmethod
    def from_dict(cls, values: dict) -> CorrectionPass:
        """Read a record back from metadata (also the string-keyed records of older files)."""
        values = dict(values)
        if "pass" in values and "number" not in values:
            values["number"] = values.pop("pass")
        nan = float("nan")
        defaults = {
            "noise_floor": nan,
            "residual_before": values.get("mean_gray_residual", nan),
            "local_residual_before": nan,
            "local_residual_after": nan,
            "accepted_nodes": 0,
            "rejected_nodes": 0,
            "improved_nodes": 0,
            "unsupported_nodes": 0,
        }
        names = {f.name for f in dataclasses.fields(cls)}
        merged = {**defaults, **{k: v for k, v in values.items() if k in names}}
        return cls(**merged)


def correction_table(field: DisplacementField) -> list[CorrectionPass]:
    """The per-pass records of a corrected field (``metadata["correction_passes"]``), or []."""
    return [
        entry if isinstance(entry, CorrectionPass) else CorrectionPass.from_dict(entry)
        for entry in field.metadata.get("correction_passes", [])
    ]


def add_stages(stages: dict, delta, **seconds) -> None:
    """Add wall times to ``stages`` (with the correcting DVC's IC-GN and statistics)."""
    for key, value in seconds.items():
        stages[key] = stages.get(key, 0.0) + float(value)
    timings = {} if delta is None else delta.metadata.get("timings", {})
    timings = timings.get("task_s", timings)  # a tiled run sums its batches' stages there
    for key, name in (("icgn_s", "correcting_icgn_s"), ("noise_s", "correcting_statistics_s")):
        stages[name] = stages.get(name, 0.0) + float(timings.get(key, 0.0))
    if "uncertainty_s" in timings:
        stages["correcting_statistics_s"] += float(timings["uncertainty_s"])


def failed_pass(
    number: int, converged: float, started: float, previous: CorrectionPass
) -> CorrectionPass:
    """The record of a pass whose correcting field could not be used (cleaning failed):
    nothing applied, the previous residuals carried."""
    return CorrectionPass(
        number=number,
        mean_gray_residual=float("nan"),
        noise_floor=previous.noise_floor,
        residual_before=previous.mean_gray_residual,
        local_residual_before=previous.local_residual_after,
        local_residual_after=float("nan"),
        accepted=False,
        accepted_nodes=0,
        rejected_nodes=0,
        improved_nodes=0,
        fraction_changed=0.0,
        mean_change=0.0,
        max_change=0.0,
        converged_fraction=converged,
        seconds=time.perf_counter() - started,
    )


def distinct_values(before: float, after: float, digits: int = 4) -> tuple[str, str]:
    """``before`` and ``after`` written with ``digits`` significant digits, or with more (up to
    10) until they read apart: a pass refused for raising the residual 2.61471 -> 2.61478 must
    not say "2.615 -> 2.615"."""
    while digits < 10 and f"{before:.{digits}g}" == f"{after:.{digits}g}" and before != after:
        digits += 1
    return f"{before:.{digits}g}", f"{after:.{digits}g}"
