"""Single-thread CPU seconds of a plain ``correlate`` and of its stages, with the fields kept
for a bit-for-bit comparison between two checkouts (issue 30).

Cases: ``upper`` and ``lower`` (the real crops of ``../shared/data/real-rock`` with the specimen
mask, as ``bench_real.py`` runs them) and ``bench_pipeline.py``'s 100³ pairs (``noisy_band``,
``shear_band``, ``translation``; ``:seed`` picks another texture and noise, e.g.
``noisy_band:1``). Subvolume 21, step 8. Run with ``NUMBA_NUM_THREADS=1
OPENBLAS_NUM_THREADS=1``: ``time.process_time`` of the whole ``correlate`` call, best of
``--repeat``, and the engine's own stage timings of that best run. ``--save DIR`` writes each
field's arrays; ``--compare DIR`` says whether ``u``, ``uncertainty``, ``status``, ``zncc``,
``iterations`` and ``gradient`` equal the saved ones bit for bit. Compare one checkout with
another (``PYTHONPATH=/other/src``) in the same minutes and say the load. ``--on-demand``
computes each subvolume's ``∇G`` from ``G``'s coefficients at every size (as large volumes do:
``pyramid.GRADIENT_ON_DEMAND_FROM``), to measure what that costs and that it changes nothing.

    NUMBA_NUM_THREADS=1 python benchmarks/bench_plain_cpu.py upper lower noisy_band [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import make_case  # noqa: E402
from bench_real import load_crop, specimen_of  # noqa: E402

ARRAYS = ("u", "uncertainty", "status", "zncc", "iterations", "gradient")


def load_case(name: str):
    """``(reference, deformed, mask)`` of a case, or None where its data is absent."""
    if name in ("upper", "lower"):
        crop = load_crop(name)
        return None if crop is None else (*crop, specimen_of(crop[0]))
    case, _, seed = name.partition(":")
    reference, deformed, _ = make_case(case.replace("_", " "), 100, int(seed or 0))
    return reference, deformed, None


def main() -> None:
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="+")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--save", type=Path)
    parser.add_argument("--compare", type=Path)
    parser.add_argument("--on-demand", action="store_true")
    args = parser.parse_args()
    if args.on_demand:
        from napari_dvc_correct.engine.correlation import pyramid

        pyramid.GRADIENT_ON_DEMAND_FROM = 0
    params = CorrelationParams(subvolume=21, step=8)
    for name in args.cases:
        data = load_case(name)
        if data is None:
            continue
        reference, deformed, mask = data
        correlate(reference, deformed, params, mask=mask)  # numba's cache loaded
        best, field = np.inf, None
        for _ in range(args.repeat):
            started = time.process_time()
            result = correlate(reference, deformed, params, mask=mask)
            seconds = time.process_time() - started
            if seconds < best:
                best, field = seconds, result
        stages = {k: round(v, 2) for k, v in field.metadata["timings"].items() if k.endswith("_s")}
        print(f"{name}: CPU {best:.2f} s (best of {args.repeat}), load {os.getloadavg()[0]:.1f}, "
              f"stages (wall) {stages}")  # fmt: skip
        arrays = {key: getattr(field, key) for key in ARRAYS}
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(args.save / f"{name.replace(':', '_')}.npz", **arrays)
        if args.compare:
            saved = np.load(args.compare / f"{name.replace(':', '_')}.npz")
            same = {
                key: bool(np.array_equal(saved[key], arrays[key], equal_nan=True)) for key in ARRAYS
            }
            print(f"  identical to {args.compare}: {all(same.values())} {same}")


if __name__ == "__main__":
    main()
