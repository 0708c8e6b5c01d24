"""Per-stage profile of ``bench_real.py``'s plain run (issue 30): wall and CPU time per stage,
and the IC-GN calls behind them.

``correlate_iter`` on a real crop of ``../shared/data/real-rock`` (subvolume 21, step 8, the
volumes as float32, as ``bench_real.py`` passes them). Per stage (the ``Progress`` records'
names; the repair inside the initial guess counts in "initial guess"): wall time and the
process's CPU time (``time.process_time``, all threads: on a shared machine it moves less with
the load than the wall time). Per caller of ``PyramidLevel.match`` (the repair or not) and pyramid
factor: calls, POIs, IC-GN iterations, wall and CPU seconds. Run one checkout against another
with ``PYTHONPATH=/other/src`` and compare within one session, saying the load.

    python benchmarks/bench_real_stages.py [lower|upper]
"""

from __future__ import annotations

import collections
import os
import resource
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real import load_crop  # noqa: E402  (the crops as bench_real reads them)


def main() -> None:
    from napari_dvc_correct.engine.correlation import correlate as correlate_module
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    name = sys.argv[1] if len(sys.argv) > 1 else "lower"
    crop = load_crop(name)
    if crop is None:
        return
    reference, deformed = crop
    calls = collections.defaultdict(lambda: [0, 0, 0, 0.0, 0.0])
    original = correlate_module.PyramidLevel.match

    def match(self, centers, warps, order, params):
        stack = traceback.extract_stack(limit=6)
        caller = "repair" if any(frame.name == "repair" for frame in stack) else "match"
        wall, cpu = time.perf_counter(), time.process_time()
        result = original(self, centers, warps, order, params)
        entry = calls[(caller, self.factor)]
        entry[0] += 1
        entry[1] += len(centers)
        entry[2] += int(result[2].sum())
        entry[3] += time.perf_counter() - wall
        entry[4] += time.process_time() - cpu
        return result

    correlate_module.PyramidLevel.match = match
    stages = collections.defaultdict(lambda: [0.0, 0.0])
    params = CorrelationParams(subvolume=21, step=8)
    started, cpu_started = time.perf_counter(), time.process_time()
    stage, wall, cpu = "start", started, cpu_started
    run = correlate_module.correlate_iter(reference, deformed, params)
    try:
        while True:
            record = next(run)
            if record.stage != stage:
                stages[stage][0] += time.perf_counter() - wall
                stages[stage][1] += time.process_time() - cpu
                stage, wall, cpu = record.stage, time.perf_counter(), time.process_time()
    except StopIteration as stop:
        field = stop.value
    stages[stage][0] += time.perf_counter() - wall
    stages[stage][1] += time.process_time() - cpu
    total_wall, total_cpu = time.perf_counter() - started, time.process_time() - cpu_started
    print(f"rock_{name}: {field.n_points} nodes, wall {total_wall:.1f} s, CPU {total_cpu:.1f} s, "
          f"load {os.getloadavg()[0]:.1f}, max RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")  # fmt: skip
    print("| stage | wall s | CPU s |\n|---|---|---|")
    for key, (w, c) in stages.items():
        print(f"| {key} | {w:.2f} | {c:.2f} |")
    print(
        "| caller, factor | calls | POIs | iterations | wall s | CPU s |\n|---|---|---|---|---|---|"
    )
    for (caller, factor), (n, pois, its, w, c) in sorted(calls.items()):
        print(f"| {caller}, {factor} | {n} | {pois} | {its} | {w:.2f} | {c:.2f} |")
    timings = field.metadata["timings"]
    print("timings: " + ", ".join(
        f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in timings.items()))  # fmt: skip
    counts = dict(zip(*np.unique(field.status, return_counts=True)))
    print("statuses", {int(k): int(v) for k, v in counts.items()})


if __name__ == "__main__":
    main()
