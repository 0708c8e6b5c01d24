"""Which correcting subvolume each zone of a band case wants: an upper bound for choosing it per node.

For a case of ``bench_correction_cases.py`` (default ``gray``) the correction is run with its
correcting matches forced to each way (the default choice, second order on 17³ and on 21³, for
every pass; then the default for pass 1 and another way for the later passes), and the RMSE of
the corrected field against the truth is printed by zone: the grid's faces and interior, and the
distance of a node from the band's mid-plane (voxels). The column ``bound`` takes, at every node,
the smallest error of the forced whole-field runs: no choice of the correcting subvolume per node
among them can do better (it is optimistic: it picks the luckiest of three noisy matches at
each node and ignores that neighbours share the warp). See docs/method.md.

Run: ``python benchmarks/bench_pass_regions.py [--seed N] [case ...]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_correction_cases import CENTER, make_case, node_errors  # noqa: E402

import napari_dvc_correct.engine.correction.self_correction as self_correction  # noqa: E402
from napari_dvc_correct.engine.correction.volumes import InMemoryVolumes  # noqa: E402
from napari_dvc_correct.engine.correlation.correlate import correlate  # noqa: E402


def forced_run(reference, deformed, plain, first=None, later=None) -> np.ndarray:
    """Node errors' field of the correction with its correcting matches forced: ``first`` for
    every pass (None: the default choice), ``later`` for passes 2 and on (None: as pass 1)."""
    chosen = self_correction.pass_method
    correlate_volumes = InMemoryVolumes.correlate
    passes = []

    def pass_method(field, params):
        return (first, "forced") if first is not None else chosen(field, params)

    def correlate_pass(volumes, params, pair=None, **options):
        if pair is not None:
            passes.append(params)
            if later is not None and len(passes) >= 2:
                params = later
        return correlate_volumes(volumes, params, pair, **options)

    self_correction.pass_method = pass_method
    InMemoryVolumes.correlate = correlate_pass
    try:
        return self_correction.correct(reference, deformed, plain)
    finally:
        self_correction.pass_method = chosen
        InMemoryVolumes.correlate = correlate_volumes


def zones(field) -> dict:
    """Node masks by zone: faces, interior, distance from the band's mid-plane (normal (1, 0, 1)
    through the centre, as in ``synthetic.band_rotation_bending``)."""
    points = field.points.reshape(*field.shape, 3)
    distance = np.abs(points[..., 0] + points[..., 2] - 2 * CENTER) / np.sqrt(2.0)
    face = np.zeros(field.shape, bool)
    face[[0, -1]] = face[:, [0, -1]] = face[:, :, [0, -1]] = True
    masks = {"all": np.ones(field.shape, bool), "faces": face, "interior": ~face}
    edges = [0, 3, 6, 10, 15, np.inf]
    for lo, hi in zip(edges[:-1], edges[1:]):
        masks[f"{lo}-{hi} from the band" if np.isfinite(hi) else f"> {lo}"] = (distance >= lo) & (
            distance < hi
        )
    return masks


def run(case: str, seed: int) -> None:
    reference, deformed, truth, params, _ = make_case(case, seed)
    plain = correlate(reference, deformed, params)
    second = params.replace(order=2)
    variants = {
        "default": (None, None),
        "2nd 17³": (second.replace(subvolume=17), None),
        "2nd 21³": (second, None),
        "later 2nd 17³": (None, second.replace(subvolume=17)),
        "later 2nd 21³": (None, second),
        "later 1st 21³": (None, params),
    }
    errors = {}
    for name, (first, later) in variants.items():
        field = forced_run(reference, deformed, plain, first, later)
        errors[name] = node_errors(field, truth).reshape(plain.shape)
    bound = np.min(np.stack([errors[k] for k in ("default", "2nd 17³", "2nd 21³")]), axis=0)
    errors["bound"] = bound
    print(f"\n{case}, seed {seed} (first run {params.subvolume}³, step {params.step})")
    print("| zone | nodes | " + " | ".join(errors) + " |")
    print("|---" * (len(errors) + 2) + "|")
    for zone, mask in zones(plain).items():
        if not mask.any():
            continue
        cells = " | ".join(f"{np.sqrt(np.mean(e[mask] ** 2)):.4f}" for e in errors.values())
        print(f"| {zone} | {int(mask.sum())} | {cells} |", flush=True)


if __name__ == "__main__":
    arguments = sys.argv[1:]
    chosen_seed = 4
    if arguments[:1] == ["--seed"]:
        chosen_seed, arguments = int(arguments[1]), arguments[2:]
    for name in arguments or ["gray"]:
        run(name, chosen_seed)
