"""Plain against self-corrected DVC on a real loaded CT pair (issue 25): ``../shared/data/real-rock``.

Two 200³ crops of an x-ray CT pair of a notched rock cylinder, intact and fractured (the README
there): ``upper`` far from the fracture, ``lower`` crossed by the open crack, with air outside the
cylinder. No true field exists, so a field is judged the way the paper judges one, by how well it
explains the images, with a judge that is not ours:

* **residual**: ``F(X + u(X))`` pulled back with the field's grid values as a user receives
  them (nodes without a value filled in from their neighbours), a least-squares gray-level
  line ``G ≈ a F~ + b`` fitted over the whole crop (global, unlike the correction's local map),
  the mean ``|G - a F~ - b|`` over the voxels where the field is defined, as a fraction of the
  zero field's; the same with an errors-in-variables line (``a = cov / (var F~ - σ²(F~))``, the
  loaded scan's noise measured as the correction's map measures it, :mod:`.gray_noise`) in the
  column "EIV line": the judge's least-squares line is diluted by that noise and stays so that
  the numbers compare with earlier runs;
* **ZNCC**: the median ZNCC of the nodes with a good status;
* **the specimen mask**: as a user gives it (the Regions panel's threshold with holes filled,
  the command line's ``--mask``): the scan smoothed over 2 voxels, thresholded half-way between
  air and rock, holes filled slice by slice; both runs get it (``--no-mask``: none). Nodes whose
  subvolume lies mostly in the air are then ``MASKED``: the user said there is nothing to
  measure there, so they are not counted as flagged. A flagged fraction is the share of the
  *measured* nodes (not ``MASKED``) without a good status: what the user must distrust of what
  they asked for;
* **flagged**: nodes without a good status, of the measured nodes and of the nodes whose
  centre is inside the specimen, and ``DISCONTINUITY`` nodes;
* **where the flags are**: the crack is taken as the 2 % of the specimen's voxels the plain
  field explains worst (after the gray-level line); a flagged node is "at the crack" when such a
  voxel lies within its subvolume's half-width;
* **seconds** per stage (the plain run's and the correction's own timings).

Run: ``python benchmarks/bench_real.py [--subvolume 21] [--step 8] [--compare-noise-fit] [upper]
[lower]``. The machine
is shared (2 cores): compare seconds within one run only, and say the load.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from napari_dvc_correct.engine.correction.cleaning import clean
from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation.gray_noise import pair_noise, scan_noises
from napari_dvc_correct.engine.evaluation.residual import moved_and_residual
from napari_dvc_correct.engine.fields.field import GOOD_STATUSES, DisplacementField, Status

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-rock"


def judge_residual(reference, deformed, field: DisplacementField):
    """Independent residual: pull-back with the field's grid values as they are (only the
    nodes without a value filled in, whatever the statuses say), global least-squares gray
    line. Returns the mean residual, the residual volume and the mean residual with a global
    errors-in-variables line instead."""
    as_given = field.copy()
    as_given.status[np.all(np.isfinite(field.u), axis=-1)] = int(Status.CONVERGED)
    # masked nodes (air, outside the user's mask) are filled from their neighbours, as a user's
    # exported, densified field is
    moved, _ = moved_and_residual(reference, deformed, clean(as_given, fill_masked=True))
    ok = np.isfinite(moved)
    design = np.column_stack([moved[ok], np.ones(int(ok.sum()))])
    line, *_ = np.linalg.lstsq(design, reference[ok], rcond=None)
    residual = np.full(reference.shape, np.nan, np.float32)
    residual[ok] = np.abs(reference[ok] - design @ line)
    noise = pair_noise(*scan_noises(reference, deformed), field.displacement)
    f, g = moved[ok].astype(np.float64), reference[ok].astype(np.float64)
    slope = np.mean((f - f.mean()) * (g - g.mean())) / (np.var(f) - noise.moved)
    eiv = float(np.mean(np.abs(g - g.mean() - slope * (f - f.mean()))))
    return float(np.nanmean(residual)), residual, eiv


def specimen_of(reference: np.ndarray) -> np.ndarray:
    """The specimen (not the air around it): above the mid-gray between air and material,
    closed pores filled slice by slice (as the Regions panel's threshold with holes filled)."""
    smooth = ndimage.gaussian_filter(reference, 2.0)
    low, high = np.percentile(smooth, [2, 98])
    solid = smooth > 0.5 * (low + high)
    return np.stack([ndimage.binary_fill_holes(plane) for plane in solid])


def good(field: DisplacementField) -> np.ndarray:
    return np.isin(field.status, [int(s) for s in GOOD_STATUSES])


def load_crop(name: str):
    """``(reference, deformed)`` of a crop as float32, or None (said) where ../shared is absent."""
    path = DATA / f"rock_{name}.npz"
    if not path.exists():
        print(f"{path} is absent (a user's clone without ../shared): skipped")
        return None
    data = np.load(path)
    return data["reference"].astype(np.float32), data["deformed"].astype(np.float32)


def run(
    name: str, params: CorrelationParams, use_mask: bool = True, compare_fit: bool = False
) -> None:
    crop = load_crop(name)
    if crop is None:
        return
    reference, deformed = crop
    specimen = specimen_of(reference)
    mask = specimen if use_mask else None
    started = time.perf_counter()
    plain = correlate(reference, deformed, params, mask=mask)
    plain_seconds = time.perf_counter() - started
    started = time.perf_counter()
    corrected = correct(reference, deformed, plain, params, mask=mask)
    correction_seconds = time.perf_counter() - started
    unfitted = None
    if compare_fit:  # the same correction without the regularised estimate
        unfitted = correct(reference, deformed, plain, params, mask=mask, noise_fit=False)

    zero = plain.copy()
    zero.u[:] = 0.0
    zero.status[:] = int(Status.CONVERGED)
    zero_residual, _, zero_eiv = judge_residual(reference, deformed, zero)
    plain_residual, plain_map, plain_eiv = judge_residual(reference, deformed, plain)
    corrected_residual, _, corrected_eiv = judge_residual(reference, deformed, corrected)
    rows = [
        ("plain", plain, plain_residual, plain_eiv, plain_seconds),
        (
            "corrected", corrected, corrected_residual, corrected_eiv,
            plain_seconds + correction_seconds,
        ),
    ]  # fmt: skip
    if unfitted is not None:
        residual, _, eiv = judge_residual(reference, deformed, unfitted)
        rows.append(("corrected, no noise fit", unfitted, residual, eiv, float("nan")))

    crack = np.zeros(reference.shape, bool)
    inside = specimen & np.isfinite(plain_map)
    crack[inside] = plain_map[inside] > np.percentile(plain_map[inside], 98.0)
    # a node is "at the crack" when a crack voxel lies within its subvolume's half-width
    near_crack = ndimage.maximum_filter(crack, size=2 * params.half + 1)
    nodes = np.clip(np.rint(plain.points).astype(int), 0, np.asarray(reference.shape) - 1)
    node_in_specimen = specimen[tuple(nodes.T)].reshape(plain.shape)
    node_at_crack = near_crack[tuple(nodes.T)].reshape(plain.shape)

    measured = plain.status != int(Status.MASKED)
    print(
        f"\n## {name} ({plain.n_points} nodes, {int(measured.sum())} measured, subvolume "
        f"{params.subvolume}, step {params.step}, specimen mask: {'yes' if use_mask else 'no'})"
    )
    gray = corrected.metadata.get("gray_levels", {}).get("description", "")
    print(f"gray-level map of the correction: {gray}")
    print(f"correction: {corrected.metadata['correction']['stop_reason']}")
    print(f"oriented step: {corrected.metadata['correction'].get('oriented')}")
    for record in corrected.metadata["correction_passes"][1:]:
        print(
            f"  pass {record['pass']}: order {record['order']}, {record['subvolume']}³, "
            f"{record['accepted_nodes']} kept, {record['rejected_nodes']} refused "
            f"({record['failed_match_nodes']} failed matches, {record['noise_refused_nodes']} "
            f"within the noise), {record['improved_nodes']} improved above the floor"
        )
    print(
        "| field | residual / zero field's | EIV line: residual / zero field's | median ZNCC "
        "(good) | flagged (measured) | flagged (specimen) | of the flagged: at the crack | "
        "DISCONTINUITY | seconds |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for label, field, residual, eiv, seconds in rows:
        flagged = ~good(field) & measured
        in_specimen = flagged & node_in_specimen
        at_crack = f"{np.mean(node_at_crack[flagged]):.0%}" if flagged.any() else "— (none flagged)"
        zncc = float(np.median(field.zncc[good(field)])) if good(field).any() else float("nan")
        print(
            f"| {label} | {residual / zero_residual:.5f} ({residual:.4f} gray levels) | "
            f"{eiv / zero_eiv:.5f} ({eiv:.4f}) | {zncc:.4f} | {flagged.sum() / max(1, measured.sum()):.1%} | "
            f"{in_specimen.sum() / max(1, node_in_specimen.sum()):.1%} | {at_crack} | "
            f"{int(np.sum(field.status == int(Status.DISCONTINUITY)))} | {seconds:.1f} |"
        )
    timings = plain.metadata.get("timings", {})
    stages = corrected.metadata["correction"]["stages"]
    print(
        "plain stages (s): "
        + ", ".join(f"{k} {v:.1f}" for k, v in timings.items() if isinstance(v, float))
    )
    print("correction stages (s): " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()))
    fit = corrected.metadata["correction"].get("noise_fit")
    if fit:
        print(
            f"noise fit: {fit['fitted_nodes']} of {fit['eligible_nodes']} eligible nodes fitted "
            f"(median variance ratio {fit['median_variance_ratio']})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("crops", nargs="*", default=["upper", "lower"])
    parser.add_argument("--subvolume", type=int, default=21)
    parser.add_argument("--step", type=int, default=8)
    parser.add_argument(
        "--no-mask", action="store_true", help="run without the specimen mask a user would give"
    )
    parser.add_argument(
        "--compare-noise-fit",
        action="store_true",
        help="also correct without the regularised estimate (one more correction per crop)",
    )
    args = parser.parse_args()
    params = CorrelationParams(subvolume=args.subvolume, step=args.step)
    for name in args.crops:
        run(name, params, use_mask=not args.no_mask, compare_fit=args.compare_noise_fit)


if __name__ == "__main__":
    main()
