"""``napari-dvc-correct evaluate REF DEF --field FIELD.npz --out-dir DIR``: accuracy report.

Gray residual, phases, background residual (eq. 1), accuracy index (eq. 2) and curves against
equivalent strain (eq. 3) for one field, or several side by side (``--compare``), written as CSV
tables, PNG plots, TIFF volumes and a Markdown report (see docs/evaluation.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..engine.evaluation.options import (
    GRADIENT_METHODS,
    MAX_PHASES,
    RESIDUAL_MODES,
    STRAIN_MEASURES,
)
from ..engine.evaluation.options import EvaluationOptions as E
from ._common import UserError
from ._field_formats import add_field_format_arguments, read_input_field
from ._tiled_options import add_tiled_evaluation_arguments, wants_tiled_evaluation


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "evaluate",
        help="evaluate the accuracy of displacement fields (residuals, strain, accuracy index)",
        description="Accuracy evaluation without ground truth (Li & Liu, eqs. 1-3): gray residual "
        "of each field, background (imaging-noise) residual from the phases, accuracy index, "
        "and both against equivalent strain. Writes tables (CSV), plots (PNG), volumes (TIFF) and "
        "report.md into --out-dir.",
    )
    parser.add_argument(
        "reference",
        help="reference volume G (TIFF, folder of TIFF slices, .npy, .npz; one array of an .npz "
        "as FILE.npz:NAME)",
    )
    parser.add_argument("deformed", help="deformed volume F")
    parser.add_argument(
        "--field",
        required=True,
        help="displacement field to evaluate: ours (.npz, .dvcfield) or another tool's (see --format)",
    )
    parser.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="OTHER.npz",
        help="another field to evaluate side by side (repeatable), e.g. the corrected field",
    )
    parser.add_argument(
        "--names",
        help="comma-separated names of --field then each --compare (default: the file names)",
    )
    group = parser.add_argument_group("phases")
    group.add_argument(
        "--phases",
        default=E.phases,
        help="'auto' (multi-Otsu) or the N-1 gray thresholds T1,T2,... of N phases (default "
        "%(default)s)",
    )
    group.add_argument(
        "--phases-deformed",
        default=E.phases_deformed,
        help="thresholds of the deformed volume when they differ (default: as --phases)",
    )
    group.add_argument(
        "--n-phases",
        type=int,
        default=E.n_phases,
        help=f"number of phases for --phases auto, 2 to {MAX_PHASES} (default %(default)s)",
    )
    group.add_argument(
        "--phase-pair",
        default=E.phase_pair,
        help="the two phases A,B whose gray contrast is used in eq. 2 (default: most abundant)",
    )
    group.add_argument(
        "--background-field",
        action="append",
        default=[],
        metavar="OTHER.npz",
        help="another field known on this pair, not evaluated (repeatable): the pair's "
        "gray-level map and background residual r0 are measured with the best of all the fields "
        "given, so a field's r0 and p do not depend on which are evaluated",
    )
    group.add_argument(
        "--raw-gray-levels",
        action="store_true",
        help="no gray-level map: the raw residual |F~ - G| (default: the loaded scan's gray "
        "levels are mapped onto the reference's first)",
    )
    group.add_argument(
        "--own-background",
        action="store_true",
        help="use each field's own background residual instead of one shared (smallest) value",
    )
    group = parser.add_argument_group(
        "specimen region (phases, r0 and every residual statistic use only its voxels)"
    )
    group.add_argument("--mask", help="reference-space mask volume (non-zero = specimen)")
    group.add_argument(
        "--roi",
        default=None,
        metavar="Z0:Z1,Y0:Y1,X0:X1",
        help="box of the specimen (voxels, half-open like numpy slices; empty = volume edge)",
    )
    group.add_argument(
        "--cylinder",
        default=None,
        metavar="Y,X,R[,Z0:Z1]",
        help="cylindrical specimen along z: centre (y, x), radius, optional z range",
    )
    group = parser.add_argument_group("residual and strain")
    group.add_argument(
        "--mode",
        choices=RESIDUAL_MODES,
        default=E.mode,
        help="residual |F(X+u)-G(X)| on reference voxels, or the paper's |F-G'| in the loaded "
        "state (default %(default)s)",
    )
    group.add_argument(
        "--strain",
        choices=STRAIN_MEASURES,
        default=E.strain_measure,
        help="strain measure (default %(default)s)",
    )
    group.add_argument(
        "--gradient",
        choices=GRADIENT_METHODS,
        default=E.strain_method,
        help="displacement gradient estimator on the grid (default %(default)s)",
    )
    group.add_argument(
        "--strain-window",
        type=int,
        default=E.strain_window,
        help="least-squares window (odd, nodes; default %(default)s)",
    )
    group.add_argument(
        "--bins", type=int, default=E.n_bins, help="equivalent-strain bins (default %(default)s)"
    )
    group.add_argument(
        "--bin-by", default=E.bin_by, help="bin every field by the strain of the field of this name"
    )
    parser.add_argument("--no-volumes", action="store_true", help="do not write TIFF volumes")
    parser.add_argument("--out-dir", required=True, help="folder for the report (created)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_field_format_arguments(parser, output=False)
    add_tiled_evaluation_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def parse_thresholds(text: str | None, option: str):
    """``"auto"`` -> ``"auto"``; ``"120,180"`` -> ``[120.0, 180.0]``; None stays None."""
    if text is None:
        return None
    if text.strip().lower() == "auto":
        return "auto"
    try:
        values = [float(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise UserError(
            f"{option} must be 'auto' or comma-separated gray values like 120,180; got {text!r}"
        ) from None
    if not values:
        raise UserError(f"{option} holds no threshold: give 'auto' or values like 120,180")
    return values


def _names(args) -> list[str]:
    paths = [args.field, *args.compare]
    if args.names:
        names = [n.strip() for n in args.names.split(",")]
        if len(names) != len(paths) or not all(names):
            raise UserError(
                f"--names gives {len(names)} names for {len(paths)} fields (--field + --compare)"
            )
        if len(set(names)) != len(names):
            raise UserError(f"--names must be unique, got {args.names!r}")
        return names
    from ..report import unique_names

    return unique_names([Path(path).stem for path in paths], "{name} ({k})")


def _phase_pair(text: str | None):
    if text is None:
        return None
    try:
        pair = tuple(int(p) for p in text.split(","))
    except ValueError:
        pair = ()
    if len(pair) != 2:
        raise UserError(f"--phase-pair must be two phase numbers like 0,1; got {text!r}")
    return pair


#: Files an evaluation writes (an older report folder holding only these may be replaced).
REPORT_PATTERNS = ("*.md", "*.csv", "*.png", "*.tif", "*.json")


def ready_for_evaluation(field, name: str):
    """``(field, note)``: a field with failed or masked nodes cleaned first, as the panel does.

    The evaluation densifies the field, which needs a finite value at every node; failed and
    masked nodes are refilled by :func:`~napari_dvc_correct.engine.correction.cleaning.clean` (paper step
    b, ``fill_masked=True``). ``note`` says what was done (None when nothing was needed).
    """
    if field.valid.all():
        return field, None
    from ..engine.correction.cleaning import clean
    from .clean import counts_text

    cleaned = clean(field, fill_masked=True)
    return cleaned, f"{name}: cleaned before evaluating: {counts_text(cleaned)}"


def run(args) -> int:
    from ..engine.evaluation.error_estimate import bounded_text, likely_text
    from ..engine.fields.absurd_nodes import flag_absurd_nodes
    from ..engine.pair_checks import check_pair_and_fields
    from ..jobs.evaluate import evaluate_job
    from ..jobs.volumes import load_volume
    from ..report import write_report
    from ._common import (
        ProgressBar,
        check_output_dir,
        command_inputs,
        drive,
        output_set,
        warn,
    )
    from ._tiled_options import _plan_reporter, run_options_from_args

    phases = parse_thresholds(args.phases, "--phases")
    phases_deformed = parse_thresholds(args.phases_deformed, "--phases-deformed")
    pair = _phase_pair(args.phase_pair)
    evaluation_options = E(  # checked before any file is read
        phases=phases,
        phases_deformed=phases_deformed,
        n_phases=args.n_phases,
        phase_pair=pair,
        mode=args.mode,
        strain_measure=args.strain,
        strain_method=args.gradient,
        strain_window=args.strain_window,
        n_bins=args.bins,
        bin_by=args.bin_by,
        shared_background=not args.own_background,
        gray_levels=not args.raw_gray_levels,
    )
    names = _names(args)
    paths = [args.field, *args.compare]
    out_dir = check_output_dir(
        args.out_dir,
        inputs=(*command_inputs(args), *paths, *args.background_field),
        patterns=REPORT_PATTERNS,
    )
    loaded = {  # --format is --field's; the --compare fields' formats are sniffed
        name: read_input_field(args, path, sniff=k > 0).field
        for k, (name, path) in enumerate(zip(names, paths))
    }
    # out of core (--tiled, --block...) the volumes are opened lazily and read block by block
    run = run_options_from_args(args)
    reference = load_volume(args.reference, run)
    deformed = load_volume(args.deformed, run)
    for name in loaded:  # a tool's few diverged nodes (|u| > the volume) are failed matches
        loaded[name], note = flag_absurd_nodes(loaded[name], reference.shape, f"field {name!r}")
        warn(args, note)
    if not run.out_of_core:  # the tiled run checks each block as it reads it
        check_pair_and_fields(reference, deformed, loaded, check_finite=False)  # read_volume did
    region = _specimen_region(args, reference)
    fields = {}
    for name, field in loaded.items():
        fields[name], note = ready_for_evaluation(field, name)
        if note:
            print(note)
    known = dict(fields)
    for k, path in enumerate(args.background_field):
        name = f"background {k + 1}: {Path(path).stem}"
        known[name], _ = ready_for_evaluation(read_input_field(args, path, sniff=True).field, name)
    options = dict(background_fields=known)
    if region is not None:
        options["region"] = region
    inputs = {
        "reference": f"{args.reference} {tuple(reference.shape)}",
        "deformed": f"{args.deformed} {tuple(deformed.shape)}",
        **{
            f"field {name!r}": f"{path} (grid {fields[name].shape}, step {fields[name].step})"
            for name, path in zip(names, paths)
        },
    }
    with output_set(out_dir, REPORT_PATTERNS, {"command": "evaluate"}) as temp:
        # out of core the volumes are written into the set as they are made
        job = evaluate_job(
            reference, deformed, fields, evaluation_options, outputs=_outputs(args, fields, temp),
            run=run, **options,
        )  # fmt: skip
        evaluation = drive(job, _plan_reporter(args, ProgressBar(args.quiet).update, "tiled"))
        files = write_report(evaluation, temp, inputs=inputs, volumes=not args.no_volumes)
    print(
        f"mean gray residual: mean of {evaluation.residual_text}; gray levels "
        f"{evaluation.gray_levels.describe()}; background r0 {evaluation.pair.background.mean:.4g}"
        f" (the pair's, measured with '{evaluation.pair.measured_with}')"
    )
    if evaluation.pair.noise_text():
        print(evaluation.pair.noise_text())
    for item in evaluation.fields:
        error = item.error
        if not item.meaningful:
            print(
                f"WARNING {item.name}: only {item.measured_nodes} of {item.field.n_points} nodes "
                "were measured (the rest inpainted): its accuracy index is not meaningful"
            )
        print(
            f"{item.name}: mean residual {item.mean_residual:.3f}, background "
            f"{item.background_used:.3f}, accuracy index {item.accuracy:.4f}, "
            f"local accuracy index {item.local_accuracy_index:.4f}, error estimate median "
            f"{bounded_text(error, 'median')} voxel (95 % {bounded_text(error, 'p95')}, "
            f"{likely_text(error)}; resolution {error['resolution']:.3f} voxel, "
            f"{100 * error['below_resolution']:.0f} % of nodes below it), measured nodes "
            f"{item.measured_nodes}/{item.field.n_points}"
        )
    count = sum(len(paths) for paths in files.values())
    print(f"wrote {count} files to {out_dir} (open {out_dir / 'report.md'})")
    return 0


def _specimen_region(args, reference):
    """The specimen region of ``--mask``, ``--roi`` or ``--cylinder`` (a boolean volume), or
    None (``--mask`` with ``--tiled``: opened lazily, read block by block). Refused when more
    than one is given."""
    given = [name for name in ("mask", "roi", "cylinder") if getattr(args, name, None)]
    if not given:
        return None
    if len(given) > 1:
        raise UserError(f"give one specimen region, not {' and '.join('--' + g for g in given)}")
    from ..engine.evaluation.accuracy import check_region, specimen_mask
    from ._grid_options import parse_cylinder, parse_roi

    shape = tuple(reference.shape)
    try:
        if args.mask and wants_tiled_evaluation(args):
            from ..io.lazy import open_volume

            mask = open_volume(args.mask)
            if tuple(mask.shape) != shape:
                raise ValueError(f"the mask {tuple(mask.shape)} must have the shape {shape}")
            return mask
        if args.mask:
            from ..io.volumes import read_volume

            return check_region(read_volume(args.mask), shape)
        shape_region = parse_roi(args.roi, shape) if args.roi else parse_cylinder(args.cylinder)
        return check_region(specimen_mask(shape, shape_region), shape)
    except ValueError as error:
        raise UserError(f"the specimen region: {error}") from None


def _outputs(args, fields, out_dir) -> dict:
    """Where an evaluation out of core writes its volumes as it makes them: the names
    :func:`..report.write_report` gives them in ``out_dir`` (none with ``--no-volumes``)."""
    from ..report import file_stem, unique_names

    if args.no_volumes:
        return {}
    outputs = {
        "labels_reference": out_dir / "labels_reference.tif",
        "labels_deformed": out_dir / "labels_deformed.tif",
    }
    for name, stem in zip(fields, unique_names([file_stem(n) for n in fields])):
        outputs["residual", name] = out_dir / f"residual_{stem}.tif"
        outputs["labels_mapped", name] = out_dir / f"labels_mapped_{stem}.tif"
    return outputs
