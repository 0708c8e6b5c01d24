"""Single-thread CPU seconds of the self-correction of a plain field, where they go, and the
corrected fields kept for a bit-for-bit comparison between two checkouts (issue 30).

Cases as :mod:`bench_plain_cpu` (``upper`` / ``lower``: the real crops with the specimen mask;
``shear_band``, ``noisy_band``, ``translation``: ``bench_pipeline.py``'s 100³ pairs, ``:seed``
for another texture and noise). Subvolume 21, step 8. The plain field is computed once; then
``correct`` of that field is timed with ``time.process_time`` (best of ``--repeat``; run with
``NUMBA_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1``, numba's cache warm after an untimed run).
``--profile`` adds one run under cProfile with the CPU clock and prints the stages
(:data:`STAGES`: the functions the time is charged to, cumulative, so a stage includes what it
calls) and the functions with the most own time. ``--save DIR`` writes the corrected field's
arrays; ``--compare DIR`` says whether they equal the saved ones bit for bit. Compare one
checkout with another (``PYTHONPATH=/other/src``) in the same minutes and say the load.

    NUMBA_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_correction_cpu.py \
        upper shear_band [--repeat 3] [--profile] [--save DIR | --compare DIR]
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_plain_cpu import load_case  # noqa: E402

ARRAYS = ("u", "uncertainty", "status", "zncc", "iterations", "gradient", "provenance")

#: (label, file suffix, function name): cumulative CPU of these functions under the profiler.
STAGES = (
    ("cleaning (both; inpainting inside)", "cleaning.py", "clean"),
    ("  of which inpainting CG", "cleaning.py", "jacobi_cg"),
    ("gray-level fit (set-up)", "volumes.py", "fit_gray_levels"),
    # every Judge.local: the set-up's first residual (which reuses the gray fit's pull-back)
    # and the acceptance's candidate and mixed fields (one pull-back each)
    ("local residuals (set-up + acceptance)", "acceptance.py", "local"),
    ("forward warps of G (align)", "volumes.py", "align"),
    ("warped mask (matching pair)", "volumes.py", "matching_pair"),
    ("correcting DVC (IC-GN, statistics)", "correlate.py", "correlate_iter"),
    ("  of which IC-GN matches", "pyramid.py", "match"),
    ("acceptance (accept_locally)", "acceptance.py", "accept_locally"),
    ("  pull-backs of F (acceptance)", "warp.py", "pull_back"),
    ("  gray-level map applied", "gray_levels.py", "apply"),
    ("field splines (from_field)", "field_spline.py", "from_field"),
    ("first selection", "rematch_region.py", "first_selection"),
    ("noise-only / support", "acceptance.py", "noise_only_corrections"),
    ("flag and refill (set-up)", "acceptance.py", "flag_and_refill"),
    ("discontinuous", "acceptance.py", "discontinuous"),
    ("prefilter", "interpolation.py", "prefilter"),
)


def _stage_table(stats: pstats.Stats, total: float) -> None:
    cumulative = {}
    for (filename, _, name), (_, _, _, cum, _) in stats.stats.items():
        for label, suffix, function in STAGES:
            if name == function and filename.endswith(suffix):
                cumulative[label] = max(cumulative.get(label, 0.0), cum)
    print(f"  profiled correction {total:.2f} s CPU")
    for label, _, _ in STAGES:
        if label in cumulative:
            print(f"    {label:40s} {cumulative[label]:6.2f}")


def main() -> None:
    from napari_dvc_correct.engine.correction.self_correction import correct, correction_table
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="+")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--save", type=Path)
    parser.add_argument("--compare", type=Path)
    args = parser.parse_args()
    params = CorrelationParams(subvolume=21, step=8)
    for name in args.cases:
        data = load_case(name)
        if data is None:
            continue
        reference, deformed, mask = data
        plain = correlate(reference, deformed, params, mask=mask)
        correct(reference, deformed, plain, params, mask=mask)  # numba's cache loaded
        best, field = np.inf, None
        for _ in range(args.repeat):
            started = time.process_time()
            result = correct(reference, deformed, plain, params, mask=mask)
            seconds = time.process_time() - started
            if seconds < best:
                best, field = seconds, result
        stages = {k: round(v, 2) for k, v in field.metadata["correction"]["stages"].items()}
        print(f"{name}: correction CPU {best:.2f} s (best of {args.repeat}), load "
              f"{os.getloadavg()[0]:.1f}, stages (wall) {stages}")  # fmt: skip
        for row in correction_table(field)[1:]:
            print(f"  pass {row.number}: matched {row.matched_nodes}, judged {row.judged_nodes}, "
                  f"accepted {row.accepted_nodes}, improved {row.improved_nodes}; {row.stop}")  # fmt: skip
        if args.profile:
            profiler = cProfile.Profile(time.process_time)
            started = time.process_time()
            profiler.runcall(correct, reference, deformed, plain, params, mask=mask)
            stats = pstats.Stats(profiler)
            _stage_table(stats, time.process_time() - started)
            stats.sort_stats("tottime").print_stats(args.top)
        arrays = {key: getattr(field, key) for key in ARRAYS}
        # the recorded residuals and noise floor of every pass, and the gray-level map
        arrays["passes"] = np.array(
            [
                (p.mean_gray_residual, p.noise_floor, p.local_residual_before,
                 p.local_residual_after, p.accepted_nodes, p.improved_nodes)
                for p in correction_table(field)
            ]
        )  # fmt: skip
        gray = field.metadata["gray_levels"]
        arrays["gray_levels"] = np.concatenate(
            [np.ravel(gray.get(k) if gray.get(k) is not None else np.nan)
             for k in ("contrast", "offset", "rms", "local_contrast", "local_offset")]
        )  # fmt: skip
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(args.save / f"{name.replace(':', '_')}.npz", **arrays)
        if args.compare:
            saved = np.load(args.compare / f"{name.replace(':', '_')}.npz")
            same = {
                key: bool(np.array_equal(saved[key], arrays[key], equal_nan=True))
                for key in arrays
                if key in saved
            }
            print(f"  identical to {args.compare}: {all(same.values())} {same}")


if __name__ == "__main__":
    main()
