"""Tiled correlation of a pair of large uint16 volumes stored on disk (issue 6).

The benchmark makes its own pair, chunk by chunk, never holding a full volume in memory:

- ``G`` tiles a periodic speckle pattern (a 128³ block of Gaussian-filtered noise, wrapped);
- ``F(x) = G(X)`` with ``x = X + u(X)`` for a known smooth field ``u`` (a rigid shift, a small
  strain and two sine waves, up to about 3.5 voxels), by fixed-point inversion and cubic-spline
  sampling of the periodic pattern, slab by slab;
- both are quantised to uint16 and written as uncompressed TIFF stacks (memory-mapped on reading)
  or Zarr arrays (``--format zarr``).

Then it correlates them with :func:`napari_dvc_correct.tiled.correlate_tiled`:

1. on dask's local threaded scheduler under ``--max-memory`` (default 1.8 GB), sampling this
   process's resident memory every 5 ms (the claim: peak under 2 GB for 512³);
2. on a ``dask.distributed.LocalCluster`` of 1 and 2 worker processes (one thread each), for the
   throughput (POIs/s and voxel-iterations/s) and the scaling; workers report their own peak
   memory.

It prints a table and writes the figures as JSON (``--out``). Run::

    python benchmarks/bench_tiled.py                  # 512³, several minutes on 2 cores
    python benchmarks/bench_tiled.py --size 192       # a quick try
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_correlate import PeakMemory  # samples the resident memory every 5 ms

TILE = 128


def max_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


# --- the pair ----------------------------------------------------------------------------------
def periodic_pattern(seed: int = 0, feature: float = 1.6) -> np.ndarray:
    """A 128³ speckle pattern that tiles space seamlessly (values in [0, 1])."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((TILE, TILE, TILE))
    pattern = ndimage.gaussian_filter(noise, feature, mode="wrap")
    low, high = np.percentile(pattern, [0.5, 99.5])
    return np.clip((pattern - low) / (high - low), 0.0, 1.0)


def displacement(points: np.ndarray, size: int) -> np.ndarray:
    """The known field ``u(X)`` (voxels) at points (N, 3) ``(z, y, x)``."""
    z, y, x = points[:, 0], points[:, 1], points[:, 2]
    center = size / 2.0
    return np.stack(
        [
            1.3 + 0.8 * np.sin(2 * np.pi * x / 256.0),
            -2.1 + 0.004 * (z - center),
            0.7 + 0.5 * np.cos(2 * np.pi * y / 200.0) - 0.003 * (x - center),
        ],
        axis=1,
    )


def _quantise(values: np.ndarray) -> np.ndarray:
    return np.round(5000.0 + 50000.0 * values).astype(np.uint16)


def write_pair(folder: Path, size: int, fmt: str, slab: int = 8) -> tuple[Path, Path]:
    """Write ``G`` and ``F`` (uint16, ``size``³) slab by slab; return their paths."""
    from scipy import ndimage

    pattern = periodic_pattern()
    coefficients = ndimage.spline_filter(pattern, order=3, mode="grid-wrap")
    shape = (size, size, size)
    suffix = ".zarr" if fmt == "zarr" else ".tif"
    paths = folder / f"reference{suffix}", folder / f"deformed{suffix}"
    if fmt == "zarr":
        import zarr

        outputs = [
            zarr.create_array(str(p), shape=shape, chunks=(64, 64, 64), dtype=np.uint16)
            for p in paths
        ]
    else:
        import tifffile

        outputs = [tifffile.memmap(p, shape=shape, dtype=np.uint16) for p in paths]
    reps = -(-size // TILE)
    yy, xx = np.meshgrid(
        np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64), indexing="ij"
    )
    for z0 in range(0, size, slab):
        z1 = min(size, z0 + slab)
        planes = np.arange(z0, z1) % TILE
        block = np.tile(pattern[planes], (1, reps, reps))[:, :size, :size]
        outputs[0][z0:z1] = _quantise(block)
        # deformed: F(x) = G(X) with X = x - u(X), by fixed-point iteration
        targets = np.stack(
            [
                np.repeat(np.arange(z0, z1, dtype=np.float64), size * size),
                np.tile(yy.reshape(-1), z1 - z0),
                np.tile(xx.reshape(-1), z1 - z0),
            ],
            axis=1,
        )
        source = targets - displacement(targets, size)
        for _ in range(8):
            source = targets - displacement(source, size)
        values = ndimage.map_coordinates(
            coefficients, (source % TILE).T, order=3, mode="grid-wrap", prefilter=False
        )
        outputs[1][z0:z1] = _quantise(np.clip(values, 0.0, 1.0).reshape(z1 - z0, size, size))
    for output in outputs:
        if hasattr(output, "flush"):
            output.flush()
    del outputs
    return paths


# --- the runs ----------------------------------------------------------------------------------
def _summary(field, seconds, size, params, peak=None):
    from napari_dvc_correct.engine.fields.field import Status

    good = field.status == Status.CONVERGED
    truth = displacement(field.points, size).reshape(field.u.shape)
    error = np.linalg.norm((field.u - truth)[good], axis=1)
    timings = field.metadata["timings"]
    voxel_iterations = int(field.iterations[good].sum()) * params.subvolume**3
    return {
        "seconds": round(seconds, 2),
        "batches_seconds": round(timings["batches_s"], 2),
        "whole_volume_pass_seconds": round(timings["whole_volume_s"], 2),
        "points": int(field.n_points),
        "converged_fraction": round(float(good.mean()), 4),
        "points_per_s": round(field.n_points / timings["batches_s"], 1),
        "voxel_iterations_per_s": float(f"{voxel_iterations / timings['batches_s']:.3g}"),
        "mean_iterations": round(float(field.iterations[good].mean()), 2),
        "rmse_voxels": float(f"{np.sqrt(np.mean(error**2)):.3g}"),
        "p95_error_voxels": float(f"{np.percentile(error, 95):.3g}"),
        "margin_overhead": round(timings["margin_overhead"], 3),
        "batches": field.metadata["tiled"]["batches"],
        "batch_shape": field.metadata["tiled"]["batch_shape"],
        "estimated_peak_bytes": field.metadata["tiled"]["estimated_peak_bytes"],
        "peak_rss_bytes": peak,
        # other processes compete for the cores on a shared machine: 1-minute load average
        "load_average": round(os.getloadavg()[0], 2),
    }


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _add_cpu(result, cpu_seconds):
    """CPU time used, per POI and per wall second (how many cores the run actually got)."""
    result["cpu_seconds"] = round(cpu_seconds, 1)
    result["cpu_ms_per_point"] = round(1000 * cpu_seconds / result["points"], 2)
    result["cores_used"] = round(cpu_seconds / result["seconds"], 2)
    return result


def run_local(paths, size, params, max_memory, workers, margin):
    from napari_dvc_correct.tiled import correlate_tiled

    with PeakMemory() as memory:
        started = time.perf_counter()
        cpu = _cpu_seconds()
        field = correlate_tiled(
            *paths, params, max_memory=max_memory, workers=workers, margin=margin
        )
        seconds = time.perf_counter() - started
        cpu = _cpu_seconds() - cpu
    return _add_cpu(_summary(field, seconds, size, params, memory.peak), cpu)


def _worker_usage():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_maxrss * 1024, usage.ru_utime + usage.ru_stime


def run_cluster(paths, size, params, n_workers, batch_shape, margin):
    import distributed

    from napari_dvc_correct.tiled import correlate_tiled

    with (
        distributed.LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            memory_limit="3GiB",
            silence_logs=40,
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        client.run(
            lambda: __import__("napari_dvc_correct.engine.correlation.correlate")
        )  # warm imports
        before = client.run(_worker_usage)
        started = time.perf_counter()
        field = correlate_tiled(
            *paths,
            params,
            scheduler=client,
            batch_shape=batch_shape,
            threads_per_task=1,
            margin=margin,
        )
        seconds = time.perf_counter() - started
        after = client.run(_worker_usage)
    result = _summary(field, seconds, size, params)
    result["worker_peak_rss_bytes"] = max(peak for peak, _ in after.values())
    result["workers"] = n_workers
    cpu = sum(after[w][1] - before[w][1] for w in after)
    return _add_cpu(result, cpu)


def warm_up():
    """Compile (or load from numba's cache) every kernel before timing."""
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    volume = synthetic.textured_volume((40, 40, 40), 2.0, seed=1)
    moved = synthetic.deform_volume(volume, synthetic.translation((0.5, 0.2, -0.3)))
    correlate(volume, moved, CorrelationParams(subvolume=15, step=10))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=512, help="volume edge (voxels)")
    parser.add_argument("--subvolume", type=int, default=31)
    parser.add_argument("--step", type=int, default=16)
    parser.add_argument("--search", type=int, default=8, help="search radius (voxels)")
    parser.add_argument("--format", choices=("tiff", "zarr"), default="tiff")
    parser.add_argument("--max-memory", default="1.8GB", help="limit of the local run")
    parser.add_argument("--local-workers", type=int, default=2)
    parser.add_argument("--margin", type=int, default=0, help="POI layers around each batch")
    parser.add_argument("--cluster", default="1,2", help="worker counts of the cluster runs")
    parser.add_argument("--dir", help="where to write the volumes (default: a temporary folder)")
    parser.add_argument("--keep", action="store_true", help="keep the volumes")
    parser.add_argument(
        "--reuse", action="store_true", help="use the volumes already in --dir (same size)"
    )
    parser.add_argument("--out", help="write the figures to this JSON file")
    args = parser.parse_args(argv)

    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    params = CorrelationParams(subvolume=args.subvolume, step=args.step, search_radius=args.search)
    folder = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="bench_tiled_"))
    folder.mkdir(parents=True, exist_ok=True)
    report = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "python": sys.version.split()[0],
        "size": args.size,
        "format": args.format,
        "params": params.to_dict(),
    }
    try:
        warm_up()
        started = time.perf_counter()
        suffix = ".zarr" if args.format == "zarr" else ".tif"
        existing = folder / f"reference{suffix}", folder / f"deformed{suffix}"
        if args.reuse and all(p.exists() for p in existing):
            paths = existing
        else:
            paths = write_pair(folder, args.size, args.format)
        report["write_seconds"] = round(time.perf_counter() - started, 1)
        report["max_rss_after_writing_bytes"] = max_rss_bytes()
        print(f"volumes written in {report['write_seconds']} s: {paths[0]}, {paths[1]}", flush=True)
        local = run_local(
            paths, args.size, params, args.max_memory, args.local_workers, args.margin
        )
        local["max_memory"] = args.max_memory
        local["workers"] = args.local_workers
        report["local"] = local
        print("local threads:", json.dumps(local), flush=True)
        report["cluster"] = []
        for n in [int(v) for v in args.cluster.split(",") if v.strip()]:
            batch = tuple(local["batch_shape"])
            result = run_cluster(paths, args.size, params, n, batch, args.margin)
            report["cluster"].append(result)
            print(f"cluster, {n} worker(s):", json.dumps(result), flush=True)
        report["max_rss_bytes"] = max_rss_bytes()
    finally:
        if not args.keep and not args.dir:
            shutil.rmtree(folder, ignore_errors=True)
    gib = 2.0**30
    print(
        f"\npeak memory of the local run: {local['peak_rss_bytes'] / gib:.2f} GiB "
        f"(estimate {local['estimated_peak_bytes'] / gib:.2f} GiB, limit {args.max_memory})"
    )
    base = None
    for result in report["cluster"]:
        rate = result["points_per_s"]
        base = base or rate
        print(
            f"{result['workers']} worker(s): {rate:.1f} POIs/s, "
            f"{result['voxel_iterations_per_s']:.3g} voxel-iterations/s, "
            f"speed-up {rate / base:.2f}, worker peak {result['worker_peak_rss_bytes'] / gib:.2f} GiB, "
            f"{result['cpu_ms_per_point']} CPU-ms per POI, {result['cores_used']} cores used"
        )
    if args.out:
        from napari_dvc_correct.io.atomic import atomic_path

        with atomic_path(args.out) as temp:
            temp.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
