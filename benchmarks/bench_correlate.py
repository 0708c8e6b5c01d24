"""Speed and memory of the CPU engine on standard workloads (issue 2).

Workload A (engine): a 160³ textured float32 pair with a small homogeneous strain, subvolume 31³,
step 8. Prints POIs/s, the IC-GN stage's voxel-iterations per second (per-POI set-up included),
the load average at the end of the run, the time of each stage and peak memory (as a multiple of the two volumes' float32 size), for 1 thread and all threads.

Workload B (command line): ``napari-dvc-correct correlate`` on a 100³ pair, subvolume 21³, step 8,
displacements up to 8 voxels, timed as a whole process (start-up included) with numba's cache warm.

Compile time (first call, cache cold) is reported separately. Run: ``make bench`` or
``python benchmarks/bench_correlate.py [--size 160] [--skip-cli]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def rss_bytes() -> int:
    with open("/proc/self/statm") as stream:
        return int(stream.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class PeakMemory:
    """Samples the resident set size every 5 ms in a background thread."""

    def __enter__(self):
        self.base = rss_bytes()
        self.peak = self.base
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes())
            time.sleep(0.005)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_bytes())


def make_pair(size: int, max_displacement: float, seed: int = 0):
    from napari_dvc_correct.engine import synthetic

    center = np.full(3, size / 2)
    strain = max_displacement / (size / 2) * 0.5
    gradient = np.array([[strain, 0.2 * strain, 0], [0, -strain, 0], [0, 0.3 * strain, strain]])
    shift = np.full(3, 0.5 * max_displacement)
    truth = synthetic.affine(gradient, center, shift)
    reference, deformed = synthetic.make_pair(
        lambda shape: synthetic.textured_volume(shape, 2.0, seed),
        (size,) * 3,
        truth,
        margin=int(max_displacement) + 4,
    )
    return reference, deformed, truth


def run_engine(size: int, threads: int | None) -> dict:
    import numba

    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    reference, deformed, truth = make_pair(size, 2.0)
    params = CorrelationParams(subvolume=31, step=8)
    numba.set_num_threads(threads or numba.config.NUMBA_NUM_THREADS)
    volume_bytes = 2 * reference.size * 4
    with PeakMemory() as memory:
        start = time.perf_counter()
        field = correlate(reference, deformed, params)
        wall = time.perf_counter() - start
    timings = field.metadata["timings"]
    error = field.u - truth(field.points).reshape(field.u.shape)
    good = field.valid
    return {
        "threads": numba.get_num_threads(),
        "load_average_1min": os.getloadavg()[0],  # other processes share the cores
        "pois": field.n_points,
        "wall_s": wall,
        "pois_per_s": field.n_points / wall,
        "voxel_iterations_per_s": timings["voxel_iterations"] / timings["icgn_s"],
        "mean_iterations": float(field.iterations[good].mean()),
        "stages": {k: round(v, 3) for k, v in timings.items() if k.endswith("_s")},
        "peak_extra_memory_x": (memory.peak - memory.base) / volume_bytes,
        "rmse_voxel": float(np.sqrt(np.mean(error[good] ** 2))),
        "converged": float(good.mean()),
    }


def run_cli(size: int = 100) -> dict:
    reference, deformed, _ = make_pair(size, 8.0, seed=1)
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        np.save(folder / "ref.npy", reference)
        np.save(folder / "def.npy", deformed)
        command = [
            sys.executable,
            "-m",
            "napari_dvc_correct.cli",
            "correlate",
            str(folder / "ref.npy"),
            str(folder / "def.npy"),
            "--subvolume",
            "21",
            "--step",
            "8",
            "--quiet",
            "--out",
            str(folder / "field.npz"),
        ]
        times = []
        for _ in range(3):  # the first run may fill numba's cache
            start = time.perf_counter()
            done = subprocess.run(command, capture_output=True, text=True)
            times.append(time.perf_counter() - start)
            if done.returncode:
                raise RuntimeError(done.stderr)
        summary = done.stdout.strip()
    return {"first_s": times[0], "warm_s": min(times[1:]), "summary": summary}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=160)
    parser.add_argument("--skip-cli", action="store_true")
    args = parser.parse_args()

    import numba

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"python {platform.python_version()}, numba {numba.__version__}, numpy {np.__version__}"
    )
    start = time.perf_counter()
    run_engine(48, None)  # compile (or load from cache) every kernel
    print(f"compile / cache load: {time.perf_counter() - start:.1f} s")
    for threads in (1, None):
        result = run_engine(args.size, threads)
        print(f"engine {args.size}^3, subvolume 31, step 8, threads={result['threads']}:")
        for key, value in result.items():
            print(f"  {key}: {value:.4g}" if isinstance(value, float) else f"  {key}: {value}")
    if not args.skip_cli:
        result = run_cli()
        print("command line, 100^3 pair, subvolume 21, step 8, displacements up to 8 voxels:")
        print(f"  first run {result['first_s']:.2f} s, warm {result['warm_s']:.2f} s")
        print(f"  {result['summary']}")
    usage = resource.getrusage(resource.RUSAGE_SELF)
    print(f"max RSS of this process: {usage.ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
