"""``napari-dvc-correct correlate REF DEF --out FIELD.npz``: local DVC of one pair."""

from __future__ import annotations

import argparse
import time

import numpy as np

from ..engine.correlation.params import MIN_SUBVOLUME
from ..engine.run_options import DEVICES, RunOptions
from . import _field_formats, _grid_options
from ._common import (
    ProgressBar,
    check_output_path,
    check_search,
    command_inputs,
    correlation_defaults,
    drive,
)
from ._tiled_options import add_tiled_arguments
from .correct import add_self_correct_argument

__all__ = ["ProgressBar", "add_correlation_arguments", "check_output_path", "drive", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "correlate",
        help="correlate a reference and a deformed volume",
        description="Local subvolume DVC (IC-GN) of a reference volume REF and a deformed volume "
        "DEF; writes the displacement field (our .npz or .dvcfield, or another tool's format: "
        "see --out-format).",
    )
    parser.add_argument(
        "reference", help="reference volume (TIFF, folder of TIFF slices, .npy, .npz)"
    )
    parser.add_argument("deformed", help="deformed volume, same shape as the reference")
    add_correlation_arguments(parser)
    parser.add_argument("--mask", help="reference-space mask volume (non-zero = material)")
    parser.add_argument(
        "--out", required=True, help="output field file (.npz, .dvcfield; see --out-format)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--device",
        choices=DEVICES,
        default=RunOptions.device,
        help="where IC-GN runs: auto = a CUDA GPU when numba sees one that works, else the CPU; "
        "cuda without a usable GPU falls back to the CPU with a warning (default: %(default)s)",
    )
    add_self_correct_argument(parser)
    add_tiled_arguments(parser)
    _grid_options.add_grid_arguments(parser)
    _field_formats.add_field_format_arguments(parser, field_input=False)
    parser.set_defaults(run=run)
    return parser


def add_correlation_arguments(parser: argparse.ArgumentParser) -> None:
    """The DVC parameters, shared by every subcommand that correlates (defaults: CorrelationParams)."""
    d = correlation_defaults()
    group = parser.add_argument_group("DVC parameters")
    group.add_argument(
        "--subvolume",
        type=int,
        default=d["subvolume"],
        help=f"odd subvolume edge (voxels, >= {MIN_SUBVOLUME}; default %(default)s)",
    )
    group.add_argument(
        "--step", type=int, default=d["step"], help="POI spacing (voxels; default %(default)s)"
    )
    group.add_argument(
        "--order",
        type=int,
        choices=(1, 2),
        default=d["order"],
        help="shape function order: 1 affine, 2 quadratic (default %(default)s)",
    )
    group.add_argument(
        "--search",
        type=int,
        default=d["search_radius"],
        help="search radius around the rigid shift (voxels; default: max(8, subvolume // 2); "
        "radii beyond a few voxels search on a binned pyramid)",
    )
    group.add_argument(
        "--max-iterations",
        type=int,
        default=d["max_iterations"],
        help="IC-GN iterations per POI at most (default %(default)s)",
    )
    group.add_argument(
        "--tolerance",
        type=float,
        default=d["tolerance"],
        help="convergence: largest move of the subvolume's corners in an iteration (voxels; "
        "default %(default)s)",
    )
    group.add_argument(
        "--min-zncc",
        type=float,
        default=d["min_zncc"],
        help="flag a match LOW_ZNCC when its ZNCC is below this fraction of what a perfect "
        "match reaches through the scans' noise (e.g. 0.9: noise allows 0.96, the match has "
        "0.85 < 0.9 x 0.96); on noise-free scans, and for the initial guess's seeds, it bounds "
        "the ZNCC itself (default %(default)s)",
    )


def params_from_args(args):
    from ..engine.correlation.params import CorrelationParams

    values = dict(
        subvolume=args.subvolume,
        step=args.step,
        order=args.order,
        search_radius=args.search,
        max_iterations=args.max_iterations,
        tolerance=args.tolerance,
    )
    if getattr(args, "min_zncc", None) is not None:
        values["min_zncc"] = args.min_zncc
    return CorrelationParams(**values)


def summary(field, seconds: float) -> str:
    """The run's line: the grid, the usable nodes with the counts by status (one definition:
    :class:`..engine.fields.field.NodeCounts`), the mean ZNCC of the matched nodes, the time."""
    from ..engine.fields.field import GOOD_STATUSES

    matched = field.valid & np.isin(field.status, [int(s) for s in GOOD_STATUSES])
    zncc = field.zncc[matched]
    mean_zncc = float(np.mean(zncc)) if zncc.size else float("nan")
    return (
        f"POIs: {field.n_points} on a {field.shape[0]}x{field.shape[1]}x{field.shape[2]} grid; "
        f"{field.node_counts().text()}; mean ZNCC of the matched {mean_zncc:.4f}; "
        f"time {seconds:.2f} s"
    )


def run(args) -> int:
    from ..engine.backend import select_device
    from ..engine.pair_checks import check_pair
    from ..jobs.correlate import correlate_job
    from ..jobs.volumes import load_volume
    from ._tiled_options import _plan_reporter, run_options_from_args

    started = time.perf_counter()
    params = params_from_args(args)
    run = run_options_from_args(args)
    out = check_output_path(args.out, suffixes=None, inputs=command_inputs(args))
    _field_formats.output_format(args, out)  # refuses a bad --out before any work
    if getattr(args, "self_correct", False):
        from .correct import correction_options_from_args

        correction_options_from_args(args)  # refuses bad correction options before any work
    if getattr(args, "points", None):
        return _field_formats.run_points(args, params, out, started, run)
    if run.out_of_core and _grid_options.wants_placement(args):
        raise ValueError("--roi, --cylinder and --origin do not apply to tiled runs yet")
    # out of core (docs/scaling.md) the volumes are opened lazily and read batch by batch
    reference = load_volume(args.reference, run)
    deformed = load_volume(args.deformed, run)
    mask = load_volume(args.mask, run) if args.mask else None
    if not run.out_of_core:  # the tiled run checks each region as it reads it
        check_pair(reference, deformed, mask, check_finite=False)  # read_volume did
    check_search(params, reference.shape)
    if not run.out_of_core:  # each batch's worker chooses its own
        print(f"device: {select_device(run.device, warn=False).description}", flush=True)
    grid = _grid_options.grid_from_args(args, reference.shape, params)
    job = correlate_job(reference, deformed, params, mask=mask, grid=grid, run=run)
    field = drive(job, _plan_reporter(args, ProgressBar(args.quiet).update, "tiled"))
    field = _grid_options.finish_grid_field(args, field, reference.shape)
    field.metadata["reference"] = str(args.reference)
    field.metadata["deformed"] = str(args.deformed)
    if getattr(args, "self_correct", False):
        from .correct import apply_self_correction

        field = apply_self_correction(args, field, reference, deformed)
    _field_formats.write_output_field(args, field, out)
    print(summary(field, time.perf_counter() - started))
    region_given = bool(args.mask or getattr(args, "roi", None) or getattr(args, "cylinder", None))
    hint = field.node_counts().region_hint(region_given)
    if hint:
        print(f"hint: {hint} (--mask, --cylinder or --roi)")
    return 0
