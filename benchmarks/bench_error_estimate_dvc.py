"""The error estimate on our DVC's own fields of imposed-field band cases, plain and corrected.

What a user evaluates: the plain field of a pair whose true field holds a shear band (it misses a
narrow band's core by 0.5-0.9 voxel) and that field after our self-correction. Cases:
``bench_correction_cases.py``'s band cases (``narrow_clean``, ``narrow_noisy``, ``narrow_heavy``,
``weak``; texture seed ``--seed``) and ``bench_pipeline.py``'s 100³ ``shear band`` and ``noisy
band`` (subvolume 21, step 8). Per field, as ``bench_error_estimate.py``'s ``measure``: the true
and estimated medians and their ratio, the Spearman rank correlation, the nodes truly more than
0.5 voxel off caught as likely / possibly above it, the other nodes flagged (false flags), the
median resolution; and the CPU seconds the evaluation took (both fields; the process's first
evaluation, kernels loaded from numba's cache included: set ``NUMBA_NUM_THREADS=1`` for one thread).

``--single-window`` reads every node in the largest window alone and leaves the node's departure
unbounded (the estimate before the windows of several sizes, :mod:`.error_scales`), for a side by
side on the same fields.

    python benchmarks/bench_error_estimate_dvc.py [--seed 4] [--single-window] [--apply-correlation] [case ...]

Cases by name: ``narrow_clean narrow_noisy narrow_heavy weak "shear band" "noisy band"`` (default
all). Results in docs/evaluation.md ("Windows of several sizes").
"""

from __future__ import annotations

import argparse
import time

import bench_pipeline
import numpy as np
from bench_correction_cases import make_case
from bench_error_estimate import measure

from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation import error_estimate, error_scales, noise_correlation
from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.evaluation.error_estimate import noise_error

CASES = ("narrow_clean", "narrow_noisy", "narrow_heavy", "weak", "shear band", "noisy band")
PIPELINE = ("shear band", "noisy band")


def case_fields(name: str, seed: int):
    """``(reference, deformed, truth, node selector, {"plain": ..., "corrected": ...})``."""
    if name in PIPELINE:
        reference, deformed, truth = bench_pipeline.make_case(name, 100)
        params, selector = CorrelationParams(subvolume=21, step=8), None
    else:
        reference, deformed, truth, params, selector = make_case(name, seed)
    plain = correlate(reference, deformed, params)
    corrected = correct(reference, deformed, plain)
    return reference, deformed, truth, selector, {"plain": plain, "corrected": corrected}


def single_window() -> None:
    """The estimate before the windows of several sizes: the largest window, ``d`` unbounded."""
    error_scales.window_ladder = lambda coarse: (int(coarse),)
    error_estimate.node_error_bound = lambda *args: np.inf


def run(name: str, seed: int):
    reference, deformed, truth, selector, fields = case_fields(name, seed)
    started = time.process_time()
    result = evaluate_fields(reference, deformed, fields, keep_volumes=False)
    seconds = time.process_time() - started
    rows = []
    for item in result.fields:
        f = item.field
        error = np.linalg.norm(f.u.reshape(-1, 3) - truth(f.points), axis=1).reshape(f.shape)
        inside = np.ones(f.shape, bool) if selector is None else selector(f.points)
        inside = np.asarray(inside).reshape(f.shape)
        sigma = noise_error(f) if f.uncertainty is not None else None
        numbers = measure(item.error_estimate, error, inside, item.error_resolution, None, sigma)
        rows.append((name, item.name, numbers, seconds))
    return rows


def percent(value) -> str:
    return "—" if np.isnan(value) else f"{100 * value:.0f} %"


def main(argv=None) -> list:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", default=list(CASES))
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--single-window", action="store_true")
    parser.add_argument("--apply-correlation", action="store_true")
    args = parser.parse_args(argv)
    if args.single_window:
        single_window()
    if args.apply_correlation:  # the pair's measured noise correlation in the estimate
        noise_correlation.NOISE_CORRELATION_APPLIED = True
    rows = []
    for name in args.cases:
        rows += run(name, args.seed)
    print(
        "| case | field | true median | estimated median (ratio) | Spearman | nodes > 0.5 "
        "| caught likely / possibly | false likely / possibly | resolution | CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, field, m, seconds in rows:
        print(
            f"| {name} | {field} | {m['true_median']:.3f} | {m['estimated_median']:.3f} "
            f"({m['ratio']:.2f}) | {m['rho']:.2f} | {m['n_bad']} | {percent(m['caught'])} / "
            f"{percent(m['caught_possibly'])} | {percent(m['false'])} / "
            f"{percent(m['false_possibly'])} | {m['resolution']:.3f} | {seconds:.2f} |"
        )
    return rows


if __name__ == "__main__":
    main()
