"""Does a cheaper correction decide the same? The default self-correction against a variant.

A cut in the correction's cost may keep its decisions (which nodes each pass accepts, which it
flags) and its field, or not. This runs both on the cases of ``bench_correction_cases.py``
(64³) and the two shear bands of ``bench_pipeline.py`` (100³), from the same plain field, and
prints per case: the largest node difference of the final fields (voxels), the nodes whose
status or provenance differ, each pass's accepted / improved node counts, the RMSE against the
truth, the flagged nodes and the CPU seconds of each (``time.process_time``: run with
NUMBA_NUM_THREADS=1 for single-thread figures). A variant passes when no decision differs and the fields agree
within 0.002 voxel.

Variants (``--variant``):

* ``tolerance:K``: the correcting matches stop at ``K`` times the first run's IC-GN tolerance
  (the passes start from an almost-right field, so a looser stop should cost little accuracy);
* ``sweeps:K``: the local acceptance re-checks the mixed field at most ``K`` times per pass
  (each re-check is a whole pull-back of ``F``) instead of
  :data:`~napari_dvc_correct.engine.correction.acceptance.ACCEPTANCE_SWEEPS`;
* ``first:all``: the first pass matches and judges every node, as before the first pass was
  selective (:func:`~napari_dvc_correct.engine.correction.rematch_region.first_selection`): the
  variant is then the *dearer* one, the default's former behaviour;
* ``contract:off``: the stop rule takes each pass's node changes as what the next pass can still
  remove, without the passes' measured contraction
  (:func:`~napari_dvc_correct.engine.correction.rematch_region.expected_change`): the former
  behaviour, dearer;
* ``hint:off``: the correcting runs get no noise hint
  (:func:`~napari_dvc_correct.engine.correction.volumes.noise_hint`), so the judge measures every
  noisy node's uncertainty in a second pass over its subvolume: the former behaviour, dearer;
* ``cg:columns``: the inpainting's conjugate gradients run column by column with
  ``scipy.sparse.linalg.cg`` (the former behaviour; only grids with more than
  :data:`~napari_dvc_correct.engine.correction.cleaning.DIRECT_SOLVE_LIMIT` nodes to fill use them);
* ``window:off``: the second-order correcting matches on a uniform subvolume, without the Gaussian
  window the default chooses (:func:`~napari_dvc_correct.engine.correction.pass_method.pass_window`):
  the former behaviour;
* ``gray:once``: the gray-level map is fitted with one trimmed pass over the volumes (trimmed by
  the lattice's first guess) instead of two (the second trimmed by the first fit): one whole-
  volume pass of per-cell sums less, a map that differs by more than the last bits.

``--seed S`` makes the 64³ cases with seed ``S`` (default 4, as ``bench_correction_cases.py``)
and the 100³ bands with seed ``S - 4`` (default 0, as ``bench_pipeline.py``).

    python benchmarks/bench_correction_decisions.py
        [--variant tolerance:5|sweeps:1|first:all|contract:off|hint:off|cg:columns|window:off|
                   gray:once]
        [--seed 4] [case ...]
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

from napari_dvc_correct.engine.correction import (  # noqa: E402
    acceptance,
    cleaning,
    rematch_region,
    self_correction,
    volumes,
)
from napari_dvc_correct.engine.correlation.correlate import correlate  # noqa: E402
from napari_dvc_correct.engine.correlation.params import CorrelationParams  # noqa: E402
from napari_dvc_correct.engine.evaluation import gray_levels  # noqa: E402

SMALL = ["translation", "affine", "weak", "narrow_clean", "narrow_noisy", "narrow_heavy", "gray"]
SMALL += ["fault"]
LARGE = ["shear band", "noisy band"]
FIELD_TOLERANCE = 0.002  # voxel


def make(case: str, seed: int = 4):
    """``(reference, deformed, truth, params)`` of a case of either benchmark."""
    if case in LARGE:
        reference, deformed, truth = bench_pipeline.make_case(case, 100, seed=seed - 4)
        return reference, deformed, truth, CorrelationParams(subvolume=21, step=8)
    reference, deformed, truth, params, _ = bench_correction_cases.make_case(case, seed=seed)
    return reference, deformed, truth, params


# What a variant may replace, restored after its run: (module, attribute).
PATCHED = (
    (self_correction, "pass_method"),
    (acceptance, "ACCEPTANCE_SWEEPS"),
    (self_correction, "first_selection"),
    (rematch_region, "expected_change"),
    (volumes, "noise_hint"),
    (cleaning, "jacobi_cg"),
    (gray_levels, "fit_from_passes"),
)


class Variant:
    """Swaps the correction's pass parameters or acceptance sweeps for the variant's while
    active."""

    def __init__(self, spec: str):
        kind, _, value = spec.partition(":")
        words = {"first": "all", "contract": "off", "hint": "off", "cg": "columns", "window": "off"}
        words["gray"] = "once"
        known = {"tolerance", "sweeps", *words}
        if kind not in known or not value or words.get(kind, value) != value:
            raise ValueError(
                f"unknown variant {spec!r} (known: tolerance:K, sweeps:K, first:all, "
                "contract:off, hint:off, cg:columns, window:off, gray:once)"
            )
        self.kind = kind
        self.value = 0.0 if kind in words else float(value)
        self.original = [getattr(module, name) for module, name in PATCHED]

    def __enter__(self):
        original, factor = self_correction.pass_method, self.value

        def pass_method(field, params):
            chosen, method = original(field, params)
            return chosen.replace(tolerance=chosen.tolerance * factor), method

        def uniform(field, params):
            chosen, method = original(field, params)
            return chosen.replace(window=None), method

        if self.kind == "tolerance":
            self_correction.pass_method = pass_method
        elif self.kind == "window":
            self_correction.pass_method = uniform
        elif self.kind == "sweeps":
            acceptance.ACCEPTANCE_SWEEPS = int(self.value)
        elif self.kind == "first":
            self_correction.first_selection = lambda *args, **kwargs: None
        elif self.kind == "hint":
            volumes.noise_hint = lambda field: None
        elif self.kind == "cg":
            cleaning.jacobi_cg = _cg_by_column
        elif self.kind == "gray":
            gray_levels.fit_from_passes = _fit_once
        else:
            rematch_region.expected_change = lambda change, *args: np.nan_to_num(change)
        return self

    def __exit__(self, *exc):
        for (module, name), value in zip(PATCHED, self.original):
            setattr(module, name, value)


def _cg_by_column(normal, rhs, start, rtol, max_iterations):
    """The inpainting's former solve: ``scipy.sparse.linalg.cg`` once per column."""
    from scipy.sparse import linalg as sparse_linalg

    diagonal = normal.diagonal()
    jacobi = sparse_linalg.LinearOperator(normal.shape, matvec=lambda x: x / diagonal)
    columns = [
        sparse_linalg.cg(
            normal, rhs[:, c], x0=start[:, c], rtol=rtol, maxiter=max_iterations, M=jacobi
        )[0]
        for c in range(rhs.shape[1])
    ]
    return np.stack(columns, axis=1)


def _fit_once(sums_with, start, shape, cell=gray_levels.DEFAULT_CELL, *, noise=None, fit=None):
    """The gray-level map from one pass trimmed by ``start`` (as ``fit_from_passes``'s first)."""
    sums = yield from sums_with(start)
    fitted = gray_levels.map_from_sums(sums, shape, cell, noise=noise, fit=fit)
    if fitted.fitted_voxels < 2 or not np.isfinite(fitted.rms):
        return fitted if start.is_identity else start
    return fitted


def _passes(field) -> list[tuple[int, int]]:
    return [
        (p["accepted_nodes"], p["improved_nodes"]) for p in field.metadata["correction_passes"][1:]
    ]


def _rmse(field, truth) -> float:
    error = np.linalg.norm(field.displacement - truth(field.points), axis=1)
    return float(np.sqrt(np.mean(error[np.isfinite(error)] ** 2)))


def _flagged(field) -> int:
    return int(field.metadata["correction"]["flagged_after"])


def compare(case: str, variant: Variant, seed: int = 4) -> bool:
    reference, deformed, truth, params = make(case, seed)
    plain = correlate(reference, deformed, params)
    started = time.process_time()
    default = self_correction.correct(reference, deformed, plain, params)
    default_s = time.process_time() - started
    with variant:
        started = time.process_time()
        cheaper = self_correction.correct(reference, deformed, plain, params)
        cheaper_s = time.process_time() - started
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
        f"{_flagged(default)} / {_flagged(cheaper)} | "
        f"{default_s:.2f} / {cheaper_s:.2f} | {'same' if same else 'DIFFERENT'} |",
        flush=True,
    )
    return same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", default=SMALL + LARGE)
    parser.add_argument("--variant", default="tolerance:5")
    parser.add_argument("--seed", type=int, default=4)
    args = parser.parse_args()
    variant = Variant(args.variant)
    print(f"variant {args.variant}, seed {args.seed}")
    print(
        "| case | max node difference (voxel) | status / provenance differ | passes: accepted, "
        "improved (default) | (variant) | RMSE default / variant | flagged default / variant "
        "| CPU seconds default / variant | decisions |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    results = [compare(case, variant, args.seed) for case in args.cases]
    print(f"{sum(results)} of {len(results)} cases decide the same")


if __name__ == "__main__":
    main()
