"""``napari-dvc-correct clean FIELD.npz --out CLEANED.npz``: replace failed and outlying nodes.

The paper's step b on its own (:func:`napari_dvc_correct.engine.correction.cleaning.clean`): nodes whose
match failed, or that fail the normalised median test, are refilled by thin-plate inpainting
from the good ones. With ``--fill-masked`` the nodes outside the mask are filled too (as the
evaluation needs: every node finite); they keep provenance ``MASKED``.
"""

from __future__ import annotations

import argparse

from ._common import check_output_path, command_inputs
from .correct import add_cleaning_options


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "clean",
        help="replace failed and outlying nodes of a field (before evaluate, or on its own)",
        description="Replace the failed and outlying nodes of a displacement field by thin-plate "
        "inpainting from the good nodes (normalised median test); writes the cleaned field.",
    )
    parser.add_argument("field", help="field file (.npz or .dvcfield) from 'correlate'")
    parser.add_argument("--out", required=True, help="output field file (.npz or .dvcfield)")
    parser.add_argument(
        "--fill-masked",
        action="store_true",
        help="also fill the nodes outside the mask (every node finite, as 'evaluate' needs)",
    )
    add_cleaning_options(parser.add_argument_group("cleaning"))
    parser.set_defaults(run=run)
    return parser


def counts_text(field) -> str:
    """What a cleaning did, from ``field.metadata["cleaning"]``, as one phrase."""
    c = field.metadata.get("cleaning", {})
    masked = "filled" if c.get("fill_masked") else "kept"
    return (
        f"replaced {c.get('rejected', 0)} of {field.n_points} nodes ({c.get('failed', 0)} failed, "
        f"{c.get('low_zncc', 0)} low ZNCC, {c.get('median_test', 0)} outliers); "
        f"{c.get('masked', 0)} masked nodes {masked}"
    )


def run(args) -> int:
    from ..engine.correction.cleaning import clean
    from ..io.npz import load_field, save_field

    out = check_output_path(args.out, (".npz", ".dvcfield"), inputs=command_inputs(args))
    field = load_field(args.field)
    cleaned = clean(
        field,
        threshold=args.outlier_threshold,
        smoothing=args.smoothing,
        fill_masked=args.fill_masked,
    )
    cleaned.metadata["cleaned_from"] = str(args.field)
    save_field(cleaned, out)
    print(f"{counts_text(cleaned)}; wrote {out}")
    return 0
