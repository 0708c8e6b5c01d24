"""The whole pipeline out of core on a large uint16 pair on disk (issue 13).

Makes the pair of :mod:`bench_tiled` (a seamless speckle pattern and its image under a known smooth
field, uint16 TIFF stacks written slab by slab), then runs the command line as a user would, each
step a new process whose peak resident memory (``ru_maxrss``) is reported:

1. ``correlate --tiled --self-correct --max-memory 1.8GB`` on the whole pair;
2. ``evaluate --tiled`` of the corrected field (reference-frame residual, volumes written);
3. on a centred crop (``--crop``, default 256³) of both volumes: the same tiled command, and the
   in-memory ``correlate --self-correct``; the largest difference of the two corrected fields over
   the nodes both call good (the claim: within 1e-3 voxel).

It prints a table and writes the figures as JSON (``--out``). Run::

    python benchmarks/bench_tiled_pipeline.py                 # 512³, about 15 min on 2 cores
    python benchmarks/bench_tiled_pipeline.py --size 192 --crop 128   # a quick try
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_tiled import displacement, write_pair

#: Runs one CLI command in this interpreter and prints its own peak RSS (bytes) last on stderr.
_RUNNER = (
    "import resource, sys\n"
    "from napari_dvc_correct.cli import main\n"
    "try:\n"
    "    code = main(sys.argv[1:])\n"
    "finally:\n"
    "    print('PEAK_RSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,"
    " file=sys.stderr)\n"
    "sys.exit(code)\n"
)


def run_cli(arguments: list[str]) -> dict:
    """One command in a new process: wall time, exit code and peak resident memory."""
    started = time.perf_counter()
    completed = subprocess.run(
        [sys.executable, "-c", _RUNNER, *arguments], capture_output=True, text=True
    )
    seconds = time.perf_counter() - started
    peak = [line for line in completed.stderr.splitlines() if line.startswith("PEAK_RSS")]
    if completed.returncode != 0:
        raise RuntimeError(f"{arguments[0]} failed ({completed.returncode}):\n{completed.stderr}")
    return {
        "seconds": round(seconds, 1),
        "peak_rss_bytes": int(peak[-1].split()[1]) if peak else None,
        "load_average": round(os.getloadavg()[0], 2),
        "stderr_tail": completed.stderr.strip().splitlines()[-3:],
    }


def crop_pair(paths, folder: Path, size: int, crop: int) -> tuple[Path, Path, int]:
    """Centred ``crop``³ copies of both volumes as TIFF; returns their paths and the offset."""
    import tifffile

    start = (size - crop) // 2
    out = []
    for path in paths:
        volume = tifffile.memmap(path, mode="r")
        target = folder / f"crop_{Path(path).name}"
        tifffile.imwrite(target, np.ascontiguousarray(volume[(slice(start, start + crop),) * 3]))
        out.append(target)
        del volume
    return out[0], out[1], start


def field_summary(path: Path, size: int, offset: int = 0) -> dict:
    from napari_dvc_correct.engine.fields.field import GOOD_STATUSES
    from napari_dvc_correct.io.npz import load_field

    field = load_field(path)
    good = np.isin(field.status, list(GOOD_STATUSES))
    truth = displacement(field.points + offset, size).reshape(field.u.shape)
    error = np.linalg.norm((field.u - truth)[good], axis=1)
    passes = field.metadata.get("correction", {}).get("passes_applied")
    return {
        "points": int(field.n_points),
        "good_fraction": round(float(good.mean()), 4),
        "rmse_voxels": float(f"{np.sqrt(np.mean(error**2)):.3g}"),
        "passes_applied": passes,
    }


def max_difference(first: Path, second: Path) -> dict:
    from napari_dvc_correct.engine.fields.field import GOOD_STATUSES
    from napari_dvc_correct.io.npz import load_field

    a, b = load_field(first), load_field(second)
    both = np.isin(a.status, list(GOOD_STATUSES)) & np.isin(b.status, list(GOOD_STATUSES))
    difference = np.linalg.norm(a.u - b.u, axis=-1)[both]
    return {
        "nodes_compared": int(both.sum()),
        "status_differences": int(np.count_nonzero(a.status != b.status)),
        "max_difference_voxels": float(f"{difference.max():.3g}"),
        "mean_difference_voxels": float(f"{difference.mean():.3g}"),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=512, help="volume edge (voxels)")
    parser.add_argument("--crop", type=int, default=256, help="edge of the in-memory comparison")
    parser.add_argument("--subvolume", type=int, default=31)
    parser.add_argument("--step", type=int, default=16)
    parser.add_argument("--search", type=int, default=8, help="search radius (voxels)")
    parser.add_argument("--max-memory", default="1.8GB", help="limit of the tiled runs")
    parser.add_argument("--max-passes", type=int, default=2)
    parser.add_argument("--dir", help="where to write the volumes (default: a temporary folder)")
    parser.add_argument("--reuse", action="store_true", help="use the volumes already in --dir")
    parser.add_argument("--out", help="write the figures to this JSON file")
    args = parser.parse_args(argv)

    folder = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    folder.mkdir(parents=True, exist_ok=True)
    dvc = [
        "--subvolume", str(args.subvolume), "--step", str(args.step), "--search", str(args.search),
        "--max-passes", str(args.max_passes), "--quiet",
    ]  # fmt: skip
    tiled = ["--tiled", "--max-memory", args.max_memory, "--temp-dir", str(folder / "temp")]
    report = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "python": sys.version.split()[0],
        "size": args.size,
        "crop": args.crop,
        "max_memory": args.max_memory,
    }
    try:
        existing = folder / "reference.tif", folder / "deformed.tif"
        started = time.perf_counter()
        if args.reuse and all(p.exists() for p in existing):
            paths = existing
        else:
            paths = write_pair(folder, args.size, "tiff")
        report["write_seconds"] = round(time.perf_counter() - started, 1)
        ref, dfm = (str(p) for p in paths)
        whole = folder / "corrected.npz"
        step = run_cli(["correlate", ref, dfm, "--out", str(whole), "--self-correct", *dvc, *tiled])
        step.update(field_summary(whole, args.size))
        report["correlate_tiled_self_correct"] = step
        print("correlate --tiled --self-correct:", json.dumps(step), flush=True)
        evaluation = run_cli(
            ["evaluate", ref, dfm, "--field", str(whole), "--out-dir", str(folder / "report"),
             "--quiet", "--tiled", "--max-memory", args.max_memory]
        )  # fmt: skip
        report["evaluate_tiled"] = evaluation
        print("evaluate --tiled:", json.dumps(evaluation), flush=True)

        crop_ref, crop_dfm, offset = crop_pair(paths, folder, args.size, args.crop)
        crop_tiled, crop_memory = folder / "crop_tiled.npz", folder / "crop_memory.npz"
        pair = [str(crop_ref), str(crop_dfm)]
        report["crop_tiled"] = run_cli(
            ["correlate", *pair, "--out", str(crop_tiled), "--self-correct", *dvc, *tiled]
        )
        report["crop_in_memory"] = run_cli(
            ["correlate", *pair, "--out", str(crop_memory), "--self-correct", *dvc]
        )
        report["crop_tiled"].update(field_summary(crop_tiled, args.size, offset))
        report["crop_in_memory"].update(field_summary(crop_memory, args.size, offset))
        report["crop_tiled_vs_in_memory"] = max_difference(crop_tiled, crop_memory)
        print("crop, tiled vs in memory:", json.dumps(report["crop_tiled_vs_in_memory"]))
    finally:
        if not args.dir:
            shutil.rmtree(folder, ignore_errors=True)
    gib = 2.0**30
    for name in ("correlate_tiled_self_correct", "evaluate_tiled", "crop_tiled", "crop_in_memory"):
        step = report[name]
        print(f"{name:30s} {step['seconds']:8.1f} s  peak {step['peak_rss_bytes'] / gib:.2f} GiB")
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
