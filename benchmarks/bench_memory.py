"""Peak memory of an in-memory ``correlate`` of a uint16 pair (issue 30: 384³ under 1.5 GB).

A ``--size``³ uint16 pair (smoothed random texture, the deformed scan shifted by whole voxels
and re-noised) is held by the caller, as a user's arrays are; ``correlate_iter`` then runs with
a thread sampling the process's resident memory (``/proc/self/statm``) every 2 ms. Printed: the
peak RSS of the process, the peak above the RSS before the call, the pair's own size, and the
largest RSS seen in each stage (the stage a ``Progress`` record last named). ``--self-correct``
then self-corrects the field in memory (``correct_iter``), sampled the same way (its stages are
printed with a ``correct:`` prefix, and its peak apart). ``--band`` shears the deformed scan
by a band (slip 6 voxels over a half-width of 8, read by linear interpolation) so that the
correction runs its passes; ``--case upper`` / ``lower`` takes a real 200³ crop and its specimen
mask instead (``bench_plain_cpu.load_case``; 8-bit scans).

    python benchmarks/bench_memory.py [--size 384] [--subvolume 21] [--step 24] [--self-correct]
        [--band | --case upper]
"""

from __future__ import annotations

import argparse
import os
import resource
import threading
import time

import numpy as np
from scipy import ndimage

PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_bytes() -> int:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * PAGE


class Sampler(threading.Thread):
    def __init__(self):
        super().__init__(daemon=True)
        self.stage = "start"
        self.peaks = {}
        self.running = True

    def run(self):
        while self.running:
            value = rss_bytes()
            self.peaks[self.stage] = max(self.peaks.get(self.stage, 0), value)
            time.sleep(0.002)


def pair(size: int, band: bool = False):
    rng = np.random.default_rng(3)
    texture = ndimage.uniform_filter(rng.random((size + 8,) * 3, np.float32), 3)
    texture -= texture.min()
    texture *= 40000.0 / texture.max()
    reference = (texture[4:-4, 4:-4, 4:-4] + 5000).astype(np.uint16)
    deformed = sheared(texture) if band else texture[3:-5, 6:-2, 2:-6]
    deformed = deformed + 5000 + rng.normal(0, 300, (size,) * 3)
    return reference, np.clip(deformed, 0, 65535).astype(np.uint16)


def sheared(texture: np.ndarray) -> np.ndarray:
    """The texture's inner ``size``³ (its 4-voxel margin off) read at ``x - u(x)``, ``u`` a
    shear band through the centre plus the whole-voxel shift of the plain pair, slab by slab
    (linear interpolation: a benchmark's deformation, not a test's)."""
    from napari_dvc_correct.engine.synthetic import shear_band

    size = texture.shape[0] - 8
    u = shear_band((size / 2.0,) * 3, width=8.0, slip=6.0, shift=(1.0, -2.0, 2.0))
    out = np.empty((size,) * 3, np.float32)
    ys, xs = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    for z in range(size):
        points = np.stack([np.full(ys.size, z), ys.ravel(), xs.ravel()], axis=1).astype(float)
        source = points - u(points) + 4.0
        out[z] = ndimage.map_coordinates(texture, source.T, order=1).reshape(size, size)
    return out


def case_pair(name: str):
    """``(reference, deformed, mask)`` of a real crop (``bench_plain_cpu.load_case``)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_plain_cpu import load_case

    data = load_case(name)
    if data is None:
        raise SystemExit(f"{name}: ../shared/data/real-rock is absent")
    return data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--subvolume", type=int, default=21)
    parser.add_argument("--step", type=int, default=24)
    parser.add_argument("--self-correct", action="store_true")
    parser.add_argument("--band", action="store_true")
    parser.add_argument("--case", choices=("upper", "lower"))
    args = parser.parse_args()
    from napari_dvc_correct.engine.correlation.correlate import correlate_iter
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    mask = None
    if args.case:
        reference, deformed, mask = case_pair(args.case)
        args.size = reference.shape[0]
    else:
        reference, deformed = pair(args.size, args.band)
    sampler = Sampler()
    base = rss_bytes()
    # the pair's creation (float64 noise) may have set the process's high-water mark already:
    # ru_maxrss counts only if the call raised it
    maxrss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    sampler.start()
    started, cpu = time.perf_counter(), time.process_time()
    params = CorrelationParams(args.subvolume, args.step)
    run = correlate_iter(reference, deformed, params, mask=mask)
    try:
        while True:
            sampler.stage = next(run).stage
    except StopIteration as stop:
        field = stop.value
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    sampler.running = False
    sampler.join()
    gib = 2**30
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    peak = max(max(sampler.peaks.values()), maxrss if maxrss > maxrss_before else 0)
    print(f"{args.case or 'synthetic'} {args.size}³ {reference.dtype} pair "
          f"({2 * reference.nbytes / gib:.2f} GiB), subvolume "
          f"{args.subvolume}, step {args.step}: {field.n_points} nodes, wall {wall:.1f} s, "
          f"cpu {cpu:.1f} s, load {os.getloadavg()[0]:.1f}")  # fmt: skip
    print(
        f"peak RSS {peak / gib:.2f} GiB during the call, {(peak - base) / gib:.2f} GiB above the "
        f"RSS before the call ({base / gib:.2f} GiB: interpreter, libraries, the pair); the "
        f"process's high-water mark before the call (making the pair) {maxrss_before / gib:.2f} GiB"
    )
    for stage, value in sampler.peaks.items():
        print(f"  {stage}: {value / gib:.2f} GiB")
    statuses = dict(zip(*np.unique(field.status, return_counts=True)))
    print("statuses", {int(k): int(v) for k, v in statuses.items()})
    if args.self_correct:
        _self_correct(reference, deformed, field, base, mask)


def _self_correct(reference, deformed, field, base, mask=None) -> None:
    from napari_dvc_correct.engine.correction.self_correction import correct_iter

    sampler = Sampler()
    sampler.stage = "correct: start"
    sampler.start()
    started, cpu = time.perf_counter(), time.process_time()
    run = correct_iter(reference, deformed, field, mask=mask)
    try:
        while True:
            sampler.stage = f"correct: {next(run).stage}"
    except StopIteration as stop:
        corrected = stop.value
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    sampler.running = False
    sampler.join()
    gib = 2**30
    peak = max(sampler.peaks.values())
    passes = len(corrected.metadata.get("correction_passes", [])) - 1  # the first is the input's
    print(f"self-correction: wall {wall:.1f} s, cpu {cpu:.1f} s, correcting passes {passes}, peak RSS "
          f"{peak / gib:.2f} GiB, {(peak - base) / gib:.2f} GiB above the RSS before the plain "
          f"call, load {os.getloadavg()[0]:.1f}")  # fmt: skip
    for stage, value in sampler.peaks.items():
        print(f"  {stage}: {value / gib:.2f} GiB")


if __name__ == "__main__":
    main()
