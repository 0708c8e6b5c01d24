"""``napari-dvc-correct correct REF DEF --field FIELD.npz --out CORRECTED.npz``: self-correction.

Also provides the ``--self-correct`` option of ``correlate`` (:func:`add_self_correct_argument`,
:func:`apply_self_correction`) and of ``series``.
"""

from __future__ import annotations

import argparse
import math
import time

from ..engine.correction.options import FRAMES, UPDATES
from . import _field_formats, _grid_options
from ._common import (
    check_output_path,
    check_side_file,
    command_inputs,
    correction_defaults,
    drive,
    warn,
)
from ._tiled_options import add_tiled_arguments


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "correct",
        help="self-correct a displacement field (the paper's strategy)",
        description="Self-correct the DVC displacement field of a pair: clean it, warp the "
        "volumes with it, correlate again and update the field. The correcting matches reuse "
        "the field's DVC parameters, or second order on a smaller subvolume where the field "
        "bends inside a subvolume and that predicts a smaller error (the table says which). A "
        "node keeps its correction only where its local gray residual does not rise by more "
        "than the imaging noise explains. Passes repeat, up to --max-passes, while the last one "
        "removed more than --min-improvement of the local residual above the noise floor, "
        "still improved a share of the nodes above that floor, and moved enough nodes by "
        "enough to change in another pass (which then matches again only near them; the "
        "shares are in docs/method.md). Writes the "
        "corrected field and prints every pass: order, subvolume, residual, and why it stopped.",
    )
    parser.add_argument(
        "reference", help="reference volume (TIFF, folder of TIFF slices, .npy, .npz)"
    )
    parser.add_argument("deformed", help="deformed volume, same shape as the reference")
    parser.add_argument(
        "--field", required=True, help="field file: ours (.npz) or another tool's (see --format)"
    )
    parser.add_argument(
        "--out", required=True, help="output field file (.npz, or see --out-format)"
    )
    parser.add_argument("--mask", help="reference-space mask volume (non-zero = material)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_correction_options(parser)
    _field_formats.add_field_format_arguments(parser)
    _field_formats.add_correction_field_arguments(parser)
    _grid_options.add_grid_arguments(parser, points=False)
    add_tiled_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def _nonnegative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return value


def _positive(text: str) -> float:
    value = _nonnegative(text)
    if value == 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def add_correction_options(parser: argparse.ArgumentParser) -> None:
    """Options of the self-correction (all optional: the DVC parameters are reused).

    Defaults are those of :class:`~napari_dvc_correct.engine.correction.options.CorrectionOptions`
    and :class:`~napari_dvc_correct.engine.correction.options.CleaningOptions`.
    """
    d = correction_defaults()
    group = parser.add_argument_group("self-correction")
    group.add_argument(
        "--max-passes",
        type=int,
        default=d["max_passes"],
        help="most correction passes (default %(default)s)",
    )
    group.add_argument(
        "--min-improvement",
        type=_nonnegative,
        default=d["min_improvement"],
        help="stop when a pass removes at most this fraction of the local gray residual above "
        "the imaging-noise floor (mean over the nodes; default %(default)s)",
    )
    group.add_argument(
        "--frame",
        choices=FRAMES,
        default=d["frame"],
        help="warp the reference to the loaded state (paper) or pull the deformed volume back "
        "to the reference (default %(default)s)",
    )
    group.add_argument(
        "--update",
        choices=UPDATES,
        default=d["update"],
        help="compose the correction with the field (exact) or add it node by node (sum, "
        "paper); default %(default)s",
    )
    group.add_argument(
        "--noise-fit",
        action=argparse.BooleanOptionalAction,
        default=d["noise_fit"],
        help="after the passes, replace a node by the generalised-least-squares affine fit over "
        "its 3x3x3 neighbourhood where a chi-square test says that neighbourhood holds only "
        "matching noise (default %(default)s)",
    )
    add_cleaning_options(group, d)


def add_cleaning_options(group, defaults: dict | None = None) -> None:
    """``--outlier-threshold`` and ``--smoothing`` (defaults: those of ``clean``)."""
    d = correction_defaults() if defaults is None else defaults
    group.add_argument(
        "--outlier-threshold",
        type=_positive,
        default=d["threshold"],
        help="normalised median test threshold for cleaning (default %(default)s)",
    )
    group.add_argument(
        "--smoothing",
        type=_nonnegative,
        default=d["smoothing"],
        help="Gaussian smoothing of the cleaned field, sigma in grid nodes (default "
        "%(default)s: none)",
    )


def add_self_correct_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--self-correct`` and the correction options to a correlating command's parser."""
    parser.add_argument(
        "--self-correct",
        action="store_true",
        help="self-correct the field before writing it (same DVC parameters)",
    )
    add_correction_options(parser)


def correction_records_from_args(args):
    """``(CorrectionOptions, CleaningOptions)`` of the arguments, checked by the records before
    any work, not after the correlation."""
    from ..engine.correction.options import CleaningOptions, CorrectionOptions

    try:
        options = CorrectionOptions(
            frame=args.frame,
            update=args.update,
            max_passes=args.max_passes,
            min_improvement=args.min_improvement,
            noise_fit=args.noise_fit,
        )
    except ValueError as error:
        raise ValueError(
            f"--max-passes / --min-improvement / --frame / --update: {error}"
        ) from None
    try:
        cleaning = CleaningOptions(threshold=args.outlier_threshold, smoothing=args.smoothing)
    except ValueError as error:
        raise ValueError(f"--smoothing / --outlier-threshold: {error}") from None
    return options, cleaning


def correction_options_from_args(args) -> dict:
    """Keyword arguments for :func:`napari_dvc_correct.engine.correction.self_correction.correct_iter`
    (:func:`correction_records_from_args`)."""
    options, cleaning = correction_records_from_args(args)
    return {**options.as_dict(), "clean_options": cleaning.as_dict()}


def pass_table(field) -> str:
    """The per-pass report of a corrected field as aligned text lines: the correcting matches'
    order and subvolume per pass, and why (:func:`..report.passes.method_lines`)."""
    from ..engine.correction.self_correction import correction_table
    from ..report.passes import (
        flag_line,
        gray_level_line,
        method_lines,
        noise_fit_line,
        order_text,
        oriented_line,
        residual_frame,
        subvolume_text,
    )

    lines = [
        "pass  order   subvolume  mean gray residual  applied  nodes changed  mean change"
        "  max change  accepted  refused  noise floor  matched"
    ]
    table = correction_table(field)
    for entry in table:
        first = entry.number == 0
        order = "—" if first else order_text(entry.order)
        subvolume = "—" if first else subvolume_text(entry.subvolume)
        lines.append(
            f"{entry.number:>4}  {order:<6}  {subvolume:>9}  {entry.mean_gray_residual:>18.4f}  "
            f"{'yes' if entry.accepted else 'no':>7}  {entry.fraction_changed:>13.3f}  "
            f"{entry.mean_change:>11.3f}  {entry.max_change:>10.3f}"
            f"  {entry.accepted_nodes:>8}  {entry.rejected_nodes:>7}  {entry.noise_floor:>11.4f}"
            f"  {entry.matched_nodes:>7}"
        )
    if table:  # the two residual columns are not on one scale: say what each is
        lines.append(
            f"mean gray residual: mean of {residual_frame(field)}, over the grid's hull; "
            "noise floor: the local acceptance's, node windows in the reference frame"
        )
    params = field.params or {}
    if table and params.get("order") and params.get("subvolume"):
        lines.append(
            f"you chose: {order_text(params['order'])} order, "
            f"{subvolume_text(params['subvolume'])} subvolume"
        )
    lines.extend(f"correcting matches, {line}" for line in method_lines(field))
    words = (gray_level_line(field), oriented_line(field), flag_line(field), noise_fit_line(field))
    for line in words:
        lines.extend([line] if line else [])
    if table and table[-1].stop:
        lines.append(f"stopped: {table[-1].stop}")
    return "\n".join(lines)


def _correct(args, field, params=None, reference=None, deformed=None):
    """The correction job of the pair in ``args`` (:func:`..jobs.correct.correct_job`), in
    memory or out of core as the arguments ask; the volumes not given are loaded for it."""
    from ..jobs.correct import correct_job
    from ..jobs.volumes import load_volume
    from ._tiled_options import _plan_reporter, run_options_from_args

    run = run_options_from_args(args)
    options, cleaning = correction_records_from_args(args)
    reference = load_volume(args.reference, run) if reference is None else reference
    deformed = load_volume(args.deformed, run) if deformed is None else deformed
    mask_path = getattr(args, "mask", None)
    mask = load_volume(mask_path, run) if mask_path else None
    job = correct_job(
        reference, deformed, field, params, options=options, cleaning=cleaning, mask=mask, run=run
    )
    # out of core, the plan's memory estimate is printed first
    return drive(job, _plan_reporter(args, None, "tiled correction"))


def apply_self_correction(args, field, reference, deformed):
    """Self-correct ``field`` of the pair with the options in ``args``; return the new field.

    Used by ``correlate --self-correct``: call it after the correlation, before saving, with
    the pair the correlation used (read, or opened lazily out of core; None: loaded here).
    Reads ``args.mask`` (a path) if the parser has one; prints the per-pass table on stdout.
    """
    corrected = _correct(args, field, None, reference, deformed)
    print(pass_table(corrected))
    return corrected


def run(args) -> int:
    from ..jobs.volumes import load_volume
    from ._tiled_options import run_options_from_args

    started = time.perf_counter()
    inputs = command_inputs(args)
    out = check_output_path(args.out, suffixes=None, inputs=inputs)
    fmt = _field_formats.output_format(args, out)  # refuses a bad --out before any work
    if fmt not in ("vti", "vtu"):  # a field on points also writes a side file next to --out
        check_side_file(_field_formats.side_path(out, fmt), inputs, out)
    correction_records_from_args(args)  # refuses bad options before any work
    reference = load_volume(args.reference, run_options_from_args(args))
    imported, params = _field_formats.prepare_correction_field(args, reference.shape)
    print(f"field: {imported.describe()}")
    warn(args, imported.note)
    corrected = _correct(args, imported.field, params, reference)
    corrected.metadata["reference"] = str(args.reference)
    corrected.metadata["deformed"] = str(args.deformed)
    corrected.metadata["corrected_from"] = str(args.field)
    written = _field_formats.write_output_field(
        args, corrected, out, points=imported.points, rows=imported.rows
    )
    out = ", ".join(str(p) for p in written)
    print(pass_table(corrected))
    info = corrected.metadata["correction"]
    print(
        f"mean gray residual {info['mean_gray_residual_before']:.4f} -> "
        f"{info['mean_gray_residual_after']:.4f} in {info['passes_applied']} pass(es); "
        f"time {time.perf_counter() - started:.2f} s; wrote {out}"
    )
    return 0
