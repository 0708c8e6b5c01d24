"""Does a cheaper correction decide the same? The default self-correction against a variant.

A cut in the correction's cost may keep its decisions (which nodes each pass accepts, which it
flags) and its field, or not. This runs both on the cases of ``bench_correction_cases.py``
(64³) and the two shear bands of ``bench_pipeline.py`` (100³), from the same plain field, and
prints per case: the largest node difference of the final fields (voxels), the nodes whose
status or provenance differ, each pass's accepted / improved node counts, the RMSE against the
truth and the seconds of each. A variant passes when no decision differs and the fields agree
within 0.002 voxel.

Variants (``--variant``):

* ``tolerance:K``: the correcting matches stop at ``K`` times the first run's IC-GN tolerance
  (the passes start from an almost-right field, so a looser stop should cost little accuracy);
* ``sweeps:K``: the local acceptance re-checks the mixed field at most ``K`` times per pass
  (each re-check is a whole pull-back of ``F``) instead of
  :data:`~napari_dvc_correct.engine.correction.acceptance.ACCEPTANCE_SWEEPS`.

    python benchmarks/bench_correction_decisions.py [--variant tolerance:5|sweeps:1] [case ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_correction_cases  # noqa: E402
import bench_pipeline  # noqa: E402

from napari_dvc_correct.engine.correction import acceptance, self_correction  # noqa: E402
from napari_dvc_correct.engine.correlation.correlate import correlate  # noqa: E402
from napari_dvc_correct.engine.correlation.params import CorrelationParams  # noqa: E402

SMALL = ["translation", "affine", "weak", "narrow_clean", "narrow_noisy", "narrow_heavy", "gray"]
SMALL += ["fault"]
LARGE = ["shear band", "noisy band"]
FIELD_TOLERANCE = 0.002  # voxel


def make(case: str):
    """``(reference, deformed, truth, params)`` of a case of either benchmark."""
    if case in LARGE:
        reference, deformed, truth = bench_pipeline.make_case(case, 100)
        return reference, deformed, truth, CorrelationParams(subvolume=21, step=8)
    reference, deformed, truth, params, _ = bench_correction_cases.make_case(case)
    return reference, deformed, truth, params


class Variant:
    """Swaps the correction's pass parameters or acceptance sweeps for the variant's while
    active."""

    def __init__(self, spec: str):
        kind, _, value = spec.partition(":")
        if kind not in ("tolerance", "sweeps") or not value:
            raise ValueError(f"unknown variant {spec!r} (known: tolerance:K, sweeps:K)")
        self.kind, self.value = kind, float(value)
        self.original = (self_correction.pass_method, acceptance.ACCEPTANCE_SWEEPS)

    def __enter__(self):
        original, factor = self.original[0], self.value

        def pass_method(field, params):
            chosen, method = original(field, params)
            return chosen.replace(tolerance=chosen.tolerance * factor), method

        if self.kind == "tolerance":
            self_correction.pass_method = pass_method
        else:
            acceptance.ACCEPTANCE_SWEEPS = int(self.value)
        return self

    def __exit__(self, *exc):
        self_correction.pass_method, acceptance.ACCEPTANCE_SWEEPS = self.original


def _passes(field) -> list[tuple[int, int]]:
    return [
        (p["accepted_nodes"], p["improved_nodes"]) for p in field.metadata["correction_passes"][1:]
    ]


def _rmse(field, truth) -> float:
    error = np.linalg.norm(field.displacement - truth(field.points), axis=1)
    return float(np.sqrt(np.mean(error[np.isfinite(error)] ** 2)))


def compare(case: str, variant: Variant) -> bool:
    reference, deformed, truth, params = make(case)
    plain = correlate(reference, deformed, params)
    started = time.perf_counter()
    default = self_correction.correct(reference, deformed, plain, params)
    default_s = time.perf_counter() - started
    with variant:
        started = time.perf_counter()
        cheaper = self_correction.correct(reference, deformed, plain, params)
        cheaper_s = time.perf_counter() - started
    difference = np.linalg.norm(default.u - cheaper.u, axis=-1)
    both = np.isfinite(difference)
    largest = float(difference[both].max()) if both.any() else 0.0
    finite_differs = int(
        np.count_nonzero(np.isfinite(default.u[..., 0]) != np.isfinite(cheaper.u[..., 0]))
    )
    status = int(np.count_nonzero(default.status != cheaper.status))
    provenance = int(np.count_nonzero(default.provenance != cheaper.provenance))
    same = (
        largest <= FIELD_TOLERANCE
        and finite_differs == 0
        and status == 0
        and provenance == 0
        and _passes(default) == _passes(cheaper)
    )
    print(
        f"| {case} | {largest:.5f} | {status} / {provenance} | {_passes(default)} | "
        f"{_passes(cheaper)} | {_rmse(default, truth):.4f} / {_rmse(cheaper, truth):.4f} | "
        f"{default_s:.2f} / {cheaper_s:.2f} | {'same' if same else 'DIFFERENT'} |",
        flush=True,
    )
    return same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", default=SMALL + LARGE)
    parser.add_argument("--variant", default="tolerance:5")
    args = parser.parse_args()
    variant = Variant(args.variant)
    print(f"variant {args.variant}")
    print(
        "| case | max node difference (voxel) | status / provenance differ | passes: accepted, "
        "improved (default) | (variant) | RMSE default / variant | seconds default / variant "
        "| decisions |"
    )
    print("|---|---|---|---|---|---|---|---|")
    results = [compare(case, variant) for case in args.cases]
    print(f"{sum(results)} of {len(results)} cases decide the same")


if __name__ == "__main__":
    main()
