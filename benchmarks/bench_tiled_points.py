"""Points of interest out of core (``tiled.points``): time and peak memory on a pair on disk.

The pair is ``bench_tiled.py``'s (uint16 TIFF stacks written slab by slab, a known smooth field
up to about 3.5 voxels). ``--points`` random points are correlated with
:func:`napari_dvc_correct.tiled.points.correlate_points_tiled` under ``--max-memory``, sampling
the resident memory every 5 ms; with ``--compare`` the same points are correlated in memory
(:func:`napari_dvc_correct.engine.correlation.correlate_points.correlate_points`, the volumes read whole)
for the time, the memory and the largest difference. Run::

    python benchmarks/bench_tiled_points.py --size 384 --points 2000 --compare
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_correlate import PeakMemory
from bench_tiled import displacement, warm_up, write_pair


def _row(label, result, seconds, peak, base, size):
    good = result.valid
    error = np.linalg.norm(result.u[good] - displacement(result.points[good], size), axis=1)
    print(
        f"{label:10s} {seconds:7.1f} s  {len(result.points) / seconds:7.1f} points/s  "
        f"peak {(peak - base) / 2**30:5.2f} GiB above start  good {good.mean():.3f}  "
        f"RMSE {np.sqrt(np.mean(error**2)):.4f} voxel",
        flush=True,
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--points", type=int, default=2000)
    parser.add_argument("--subvolume", type=int, default=31)
    parser.add_argument("--step", type=int, default=16, help="the guide grid's step")
    parser.add_argument("--max-memory", default="1GB")
    parser.add_argument("--compare", action="store_true", help="also run in memory")
    args = parser.parse_args(argv)

    from napari_dvc_correct.engine.correlation.correlate_points import correlate_points
    from napari_dvc_correct.engine.correlation.params import CorrelationParams
    from napari_dvc_correct.io.lazy import open_volume
    from napari_dvc_correct.tiled.points import correlate_points_tiled

    params = CorrelationParams(subvolume=args.subvolume, step=args.step, search_radius=8)
    rng = np.random.default_rng(0)
    low, high = params.half + 4, args.size - params.half - 5
    points = rng.uniform(low, high, (args.points, 3))
    folder = Path(tempfile.mkdtemp(prefix="bench_tiled_points_"))
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; {args.size}³ uint16")
    try:
        warm_up()
        paths = write_pair(folder, args.size, "tiff")
        reference, deformed = open_volume(paths[0]), open_volume(paths[1])
        with PeakMemory() as memory:
            started = time.perf_counter()
            tiled = correlate_points_tiled(
                reference, deformed, points, params, max_memory=args.max_memory
            )
            seconds = time.perf_counter() - started
        info = tiled.metadata["tiled"]
        timings = tiled.metadata["timings"]
        print(f"guide field {timings['guide_s']:.1f} s, points {timings['points_s']:.1f} s")
        print(
            f"{info['groups']} groups of up to {info['group_voxels']}³ voxels, largest region "
            f"{info['largest_region_voxels']:,} voxels, estimated peak "
            f"{info['estimated_peak_bytes'] / 2**30:.2f} GiB (limit {args.max_memory})"
        )
        _row("tiled", tiled, seconds, memory.peak, memory.base, args.size)
        if args.compare:
            with PeakMemory() as memory:
                started = time.perf_counter()
                g, f = np.asarray(reference), np.asarray(deformed)
                whole = correlate_points(g, f, points, params)
                seconds = time.perf_counter() - started
                del g, f
            _row("in memory", whole, seconds, memory.peak, memory.base, args.size)
            good = whole.valid & tiled.valid
            print(
                f"tiled against in memory: same status {np.mean(whole.status == tiled.status):.4f}, "
                f"largest difference {np.max(np.abs(whole.u[good] - tiled.u[good])):.2e} voxel"
            )
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
