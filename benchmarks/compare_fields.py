"""Plain ``correlate`` fields of the synthetic correction cases and the real rock crops, saved
and compared between two checkouts (issue 30: a speed change must not change the fields).

    PYTHONPATH=/path/to/before/src python benchmarks/compare_fields.py --save before.npz
    python benchmarks/compare_fields.py --save after.npz
    python benchmarks/compare_fields.py --compare before.npz after.npz

``--save`` runs :func:`correlate` on each case of ``bench_correction_cases.py`` and on the real
crops of ``../shared/data/real-rock`` (subvolume 21, step 8; skipped without ``../shared``) and
stores ``u``, ``status``, ``zncc``, ``iterations`` and ``uncertainty`` with the wall and CPU time
(``time.process_time``: all threads of this process) and the stage timings. ``--compare`` prints
per case the status counts that differ, the largest ``|Δu|`` over nodes good in both, and the
nodes whose status changed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

CASES = ["translation", "affine", "weak", "narrow", "narrow_noisy", "narrow_heavy", "gray", "fault"]
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-rock"


def _inputs(names):
    from bench_correction_cases import make_case

    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    for name in names:
        if name.startswith("rock_"):
            path = REAL / f"{name}.npz"
            if not path.exists():
                print(f"{path} is absent: skipped")
                continue
            data = np.load(path)
            yield name, data["reference"], data["deformed"], CorrelationParams(21, 8)
        else:
            reference, deformed, _, params, _ = make_case(name)
            yield name, reference, deformed, params


def save(path, names):
    from napari_dvc_correct.engine.correlation.correlate import correlate

    arrays, info = {}, {}
    for name, reference, deformed, params in _inputs(names):
        wall, cpu = time.perf_counter(), time.process_time()
        field = correlate(reference, deformed, params)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        for key in ("u", "status", "zncc", "iterations", "uncertainty"):
            arrays[f"{name}/{key}"] = getattr(field, key)
        timings = {k: v for k, v in field.metadata["timings"].items()}
        info[name] = {"wall_s": wall, "cpu_s": cpu, "timings": timings}
        print(f"{name}: wall {wall:.2f} s, cpu {cpu:.2f} s, load {os.getloadavg()[0]:.1f}; "
              + ", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in timings.items()))  # fmt: skip
    np.savez(path, info=json.dumps(info), **arrays)


def compare(before_path, after_path):
    from napari_dvc_correct.engine.fields.field import GOOD_STATUSES

    good_codes = [int(s) for s in GOOD_STATUSES]
    before, after = np.load(before_path), np.load(after_path)
    names = sorted({k.split("/")[0] for k in before.files if "/" in k})
    for name in names:
        if f"{name}/u" not in after.files:
            continue
        sb, sa = before[f"{name}/status"], after[f"{name}/status"]
        ub, ua = before[f"{name}/u"], after[f"{name}/u"]
        good = np.isin(sb, good_codes) & np.isin(sa, good_codes)
        du = float(np.max(np.abs(ub[good] - ua[good]), initial=0.0))
        counts_b = dict(zip(*np.unique(sb, return_counts=True)))
        counts_a = dict(zip(*np.unique(sa, return_counts=True)))
        changed = int(np.sum(sb != sa))
        same_u = bool(np.array_equal(ub, ua, equal_nan=True))
        print(f"{name}: max |du| over {int(good.sum())} good nodes {du:.3g} voxel, "
              f"identical u: {same_u}, status changed at {changed} nodes"
              + ("" if counts_b == counts_a else
                 f" (before {dict((int(k), int(v)) for k, v in counts_b.items())}, "
                 f"after {dict((int(k), int(v)) for k, v in counts_a.items())})"))  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--save")
    parser.add_argument("--compare", nargs=2)
    parser.add_argument("cases", nargs="*", default=CASES + ["rock_lower", "rock_upper"])
    args = parser.parse_args()
    if args.save:
        save(args.save, args.cases)
    if args.compare:
        compare(*args.compare)


if __name__ == "__main__":
    main()
