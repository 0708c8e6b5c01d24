"""``napari-dvc-correct series V0 V1 V2 ... --strategy incremental|total --out-dir DIR``.

Writes one field file per loaded state (``state_01.npz`` = ``U_0→1`` ...), the increments of
the incremental strategy (``increment_00_01.npz`` ...) and ``summary.csv`` (one row per state),
as one set (:func:`._common.output_set`): nothing is written if the run fails or is interrupted,
and a new run into the same folder replaces the earlier set whole.

The POIs are placed as for ``correlate`` (``--roi``, ``--cylinder``, ``--origin``, ``--points``;
:mod:`._grid_options`) and the fields written in any of its formats (``--out-format``, ``--xyz``;
:mod:`._field_formats`): the files take that format's suffix (``state_01.tsv`` for spam...);
the default is our ``.npz`` on a grid and a ``.csv`` table at ``--points``.

``--tiled`` (or any option of :func:`._tiled_options.add_tiled_arguments`) runs a series on a grid
out of core (:func:`napari_dvc_correct.tiled.series.series_tiled_iter`): the states are read
lazily, batch by batch and block by block; the same files and summary. A series at ``--points``
runs in memory only.

``--evaluate`` evaluates each state's total on its own pair (reference state, that state) and
writes ``series_report.md``, ``series_plot.png`` and ``series_evaluation.csv``
(:func:`napari_dvc_correct.report.series.write_series_report`); a self-corrected series gives two
curves, the uncorrected totals (:attr:`..engine.series.strategies.SeriesResult.uncorrected`) and
the corrected ones, under the names the panel gives them (:func:`series_curves`).
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

SUMMARY_COLUMNS = (
    "state",
    "volume",
    "field_file",
    "strategy",
    "valid_fraction",
    "mean_displacement",
    "max_displacement",
    "mean_zncc",
    "mean_gray_residual",
    "mean_gray_residual_uncorrected",
    "correction_passes",
)


def add_parser(subparsers) -> argparse.ArgumentParser:
    from . import _field_formats, _grid_options
    from ._tiled_options import add_tiled_arguments
    from .correct import add_self_correct_argument
    from .correlate import add_correlation_arguments

    parser = subparsers.add_parser(
        "series",
        help="displacement fields of a scan series (total or incremental strategy)",
        description="Correlate a series of states V0 V1 V2 ... either each against the first "
        "(total) or adjacent states merged by composition (incremental); optionally "
        "self-correct. Writes one field per state and a summary table into --out-dir. With "
        "--tiled (or --max-memory, --scheduler...) a series on a grid runs out of core: the "
        "states are read batch by batch, never whole.",
    )
    parser.add_argument("volumes", nargs="+", help="volumes of the states, in loading order")
    parser.add_argument(
        "--strategy",
        choices=("incremental", "total"),
        default="incremental",
        help="total: every state against the first; incremental: each state against the one "
        "before, the increments composed into the displacement from the first state (default: "
        "incremental)",
    )
    parser.add_argument("--out-dir", required=True, help="folder for the fields and summary.csv")
    parser.add_argument("--mask", help="mask volume in the first state (non-zero = material)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_correlation_arguments(parser)
    _grid_options.add_grid_arguments(parser)
    _field_formats.add_field_format_arguments(parser, field_input=False)
    for action in parser._actions:
        if action.dest == "out_format":
            action.help = (
                "format of the field files in --out-dir: npz (ours, state_01.npz...), spam "
                "(.tsv), aldvc (.mat), idvc (.disp) or table (.csv); default: npz on a grid, "
                "table at --points"
            )
    add_self_correct_argument(parser)
    parser.add_argument(
        "--correct",
        choices=("total", "increments", "both"),
        default="total",
        help="with --self-correct, what to correct in the incremental strategy: the merged "
        "totals (default), the increments, or both",
    )
    add_tiled_arguments(parser)
    group = parser.add_argument_group("series report")
    group.add_argument(
        "--evaluate",
        action="store_true",
        help="evaluate every state against its own pair and write series_report.md, "
        "series_plot.png (mean gray residual, accuracy index p and error estimate per state) "
        "and series_evaluation.csv into --out-dir (a grid series in memory); with "
        "--self-correct both the uncorrected and the corrected totals, two curves and two rows "
        "per state, named as in the panel ('total' and 'total, corrected')",
    )
    group.add_argument(
        "--loads",
        default=None,
        help="with --evaluate: the load of each deformed state, e.g. '0.5,1.0,1.5' (the x "
        "axis of the plots; default: the state index)",
    )
    group.add_argument(
        "--load-label",
        default=None,
        help="with --loads: the x axis label, e.g. 'force [kN]' (default 'load')",
    )
    parser.set_defaults(run=run)
    return parser


def evaluate_states(volumes, curves: dict, bar) -> list:
    """Each state against its own pair (``volumes[0]``, ``volumes[k]``): [(label, Evaluation)].

    ``curves`` maps a curve's name to its totals in state order (``{"total": uncorrected,
    "total, corrected": corrected}``); state ``k``'s evaluation holds one field per curve, named
    ``"state k (curve)"`` as the panel names them, all on that state's pair at once (one
    gray-level map and ``r0``, as the Evaluate panel measures a pair's fields). Progress stages
    say the state: ``"state k of n: ..."``."""
    from ..engine.evaluation.accuracy import evaluate_iter
    from ..engine.progress import forward_progress, state_of
    from ._common import drive
    from .evaluate import ready_for_evaluation

    results = []
    n = min(len(totals) for totals in curves.values())
    for k in range(1, n + 1):
        fields = {}
        for curve, totals in curves.items():
            name = f"state {k} ({curve})"
            fields[name], _ = ready_for_evaluation(totals[k - 1], name)
        job = forward_progress(evaluate_iter(volumes[0], volumes[k], fields), state_of(k, n))
        results.append((f"state {k}", drive(job, bar)))
    return results


def series_curves(result, strategy: str, correct_total: bool) -> dict:
    """The curves of a series' report: ``{name: totals}``, the uncorrected totals
    (``result.uncorrected``) as ``strategy`` and, where the run self-corrected, the corrected
    totals as ``"strategy, corrected"`` (``"strategy, corrected increments"`` where only the
    increments were corrected) — the names the panel gives a series and its self-correction."""
    curves = {strategy: result.uncorrected or result.totals}
    if result.self_corrected:
        corrected = "corrected" if correct_total else "corrected increments"
        curves[f"{strategy}, {corrected}"] = result.totals
    return curves


def _format(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def write_summary(rows: list[dict], path: Path) -> None:
    """Write the summary table (CSV, one row per state) atomically."""
    from ..io.atomic import atomic_path

    with atomic_path(path) as temp:
        with open(temp, "w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(SUMMARY_COLUMNS)
            for row in rows:
                writer.writerow([_format(row.get(column, "")) for column in SUMMARY_COLUMNS])


#: Files a series writes (an older series folder holding only these may be replaced).
SERIES_PATTERNS = ("state_*", "increment_*_*", "summary.csv", "series_*")


def field_suffix(args, at_points: bool) -> str:
    """The suffix of the series' field files for ``--out-format`` (refused before any work where
    it cannot hold the fields)."""
    from ._field_formats import OUTPUT_SUFFIXES

    chosen = getattr(args, "out_format", "auto") or "auto"
    fmt = ("table" if at_points else "npz") if chosen == "auto" else chosen
    if at_points and fmt == "npz":
        raise ValueError(
            "--out-format npz holds grids: write a series at --points as table, spam, idvc or aldvc"
        )
    suffixes = {}
    for suffix, name in OUTPUT_SUFFIXES.items():
        suffixes.setdefault(name, suffix)  # the first: ours stays .npz
    return suffixes.get(fmt, ".txt")


def run(args) -> int:
    from ..engine.pair_checks import check_pair
    from ..jobs.series import series_job
    from ..jobs.volumes import load_volume
    from . import _field_formats, _grid_options
    from ._common import (
        ProgressBar,
        check_output_dir,
        check_search,
        command_inputs,
        drive,
        output_set,
    )
    from ._tiled_options import _plan_reporter, run_options_from_args
    from .correct import correction_options_from_args
    from .correlate import params_from_args

    started = time.perf_counter()
    if len(args.volumes) < 2:
        raise ValueError(f"a series needs at least 2 volumes, got {len(args.volumes)}")
    out_dir = check_output_dir(args.out_dir, inputs=command_inputs(args), patterns=SERIES_PATTERNS)
    params = params_from_args(args)
    options = correction_options_from_args(args)
    at_points = bool(getattr(args, "points", None))
    suffix = field_suffix(args, at_points)
    run = run_options_from_args(args)
    tiled = run.out_of_core
    points = None
    if at_points:
        if args.self_correct:
            raise ValueError("--points does not combine with --self-correct")
        if any(getattr(args, name, None) for name in ("roi", "cylinder", "origin")):
            raise ValueError("give --points or --roi/--cylinder/--origin, not both")
        if tiled:
            raise ValueError(
                "a series at --points runs in memory only: leave out --tiled (and --max-memory, "
                "--batch, --workers, --scheduler, --temp-dir), or use a grid (--roi, --cylinder)"
            )
        points = _grid_options.load_points(args.points)
    evaluate = getattr(args, "evaluate", False)
    if evaluate and (at_points or tiled):
        raise ValueError(
            "--evaluate evaluates a grid series in memory: leave out --points and the "
            "out-of-core options (or run 'evaluate' on each state)"
        )
    if not evaluate and (getattr(args, "loads", None) or getattr(args, "load_label", None)):
        raise ValueError("--loads and --load-label go with --evaluate")
    if evaluate:
        from ..report.series import parse_loads

        parse_loads(args.loads, len(args.volumes) - 1)  # refused before any work
    correct_increments = args.self_correct and args.correct in ("increments", "both")
    correct_total = args.self_correct and args.correct in ("total", "both")
    strategy = dict(
        strategy=args.strategy,
        correct_increments=correct_increments,
        correct_total=correct_total,
        correction_options=options,
    )
    # out of core the states are opened lazily and read batch by batch (docs/scaling.md)
    volumes = [load_volume(path, run) for path in args.volumes]
    mask = load_volume(args.mask, run) if args.mask else None
    if not tiled:  # the tiled run checks each region as it reads it
        for k in range(1, len(volumes)):
            check_pair(volumes[0], volumes[k], mask, check_finite=False)  # read_volume did
    shape = tuple(volumes[0].shape)
    check_search(params, shape)
    grid = None if at_points else _grid_options.grid_from_args(args, shape, params)
    job = series_job(volumes, params, mask=mask, grid=grid, points=points, run=run, **strategy)
    result = drive(job, _plan_reporter(args, ProgressBar(args.quiet).update, "tiled series"))

    def placed(field):
        return field if at_points else _grid_options.finish_grid_field(args, field, shape)

    rows = result.summary()
    rows[0]["volume"] = args.volumes[0]
    with output_set(out_dir, SERIES_PATTERNS, {"command": "series"}) as temp:
        for k, total in enumerate(result.totals, start=1):
            total = placed(total)
            total.metadata["reference"] = str(args.volumes[0])
            total.metadata["deformed"] = str(args.volumes[k])
            name = f"state_{k:02d}{suffix}"
            _field_formats.write_output_field(args, total, str(temp / name))
            rows[k]["volume"] = args.volumes[k]
            rows[k]["field_file"] = name
        for k, increment in enumerate(result.increments, start=1):
            increment = placed(increment)
            increment.metadata["reference"] = str(args.volumes[k - 1])
            increment.metadata["deformed"] = str(args.volumes[k])
            name = f"increment_{k - 1:02d}_{k:02d}{suffix}"
            _field_formats.write_output_field(args, increment, str(temp / name))
        write_summary(rows, temp / "summary.csv")
        if evaluate:
            from ..report.series import write_series_report

            curves = series_curves(result, args.strategy, correct_total)
            states = evaluate_states(volumes, curves, ProgressBar(args.quiet))
            write_series_report(states, temp, args.loads, args.load_label)
    for row, total in zip(rows[1:], result.totals):
        before = row["mean_gray_residual_uncorrected"]
        uncorrected = (
            f" (uncorrected {before:.4f})" if result.self_corrected and before == before else ""
        )
        print(
            f"state {row['state']}: {total.node_counts().text()}; mean |u| "
            f"{row['mean_displacement']:.3f} voxels, mean gray residual "
            f"{row['mean_gray_residual']:.4f}{uncorrected}"
        )
    print(
        f"{len(result.totals)} states ({args.strategy}) in {time.perf_counter() - started:.2f} s; "
        f"wrote {out_dir}"
    )
    return 0
