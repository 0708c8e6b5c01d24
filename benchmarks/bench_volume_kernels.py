"""The whole-volume kernels every DVC run and correction pass starts with, on a ``--size``³ volume.

* ``prefilter``: the cubic B-spline coefficients (``engine.correlation.interpolation.prefilter``), against
  ``scipy.ndimage.spline_filter(..., output=float32)`` (what the engine used before, one thread);
* ``gradient``: ``∇G`` of the interpolant at every voxel (``icgn_reference.gradient_volume``);
* ``second-order set-up``: IC-GN of second order from a zero guess on a clean shifted pair, so
  the stage is the per-POI set-up (gather, ``H`` from the 35 quartic moments, Cholesky) plus the
  sampling passes; reported as voxel-iterations per second.

Each figure is the best of ``--repeat`` calls after one warm-up call (numba's cache warm), for
each thread count of ``--threads``; the largest difference to scipy's coefficients is printed.

    python benchmarks/bench_volume_kernels.py [--size 256] [--threads 1 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import time

import numba

numba.config.THREADING_LAYER = "threadsafe"

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from napari_dvc_correct.engine import synthetic  # noqa: E402
from napari_dvc_correct.engine.correlation.icgn_reference import gradient_volume  # noqa: E402
from napari_dvc_correct.engine.correlation.interpolation import prefilter  # noqa: E402
from napari_dvc_correct.engine.correlation.params import CorrelationParams  # noqa: E402
from napari_dvc_correct.engine.correlation.pyramid import PyramidLevel  # noqa: E402


def _best(function, repeat: int) -> float:
    function()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def _second_order_rate(size: int, repeat: int) -> tuple[float, float]:
    """Voxel-iterations/s of second-order IC-GN (subvolume 15) from a zero guess; mean iterations."""
    reference = synthetic.textured_volume((size,) * 3, 2.0, seed=1)
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.3, -0.2, 0.4)))
    params = CorrelationParams(subvolume=15, step=8, order=2)
    level = PyramidLevel.build(1, reference, deformed, None, params.half, params.min_texture)
    axis = np.arange(params.half + 2, size - params.half - 2, params.step)
    centers = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    centers = np.ascontiguousarray(centers, np.int64)
    iterations = []

    def run():
        warps = np.zeros((len(centers), 30))
        iterations[:] = [level.match(centers, warps, 2, params)[2].mean()]

    seconds = _best(run, repeat)
    return len(centers) * iterations[0] * params.subvolume**3 / seconds, iterations[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    volume = synthetic.textured_volume((args.size,) * 3, 2.0, seed=0).astype(np.float32)
    expected = ndimage.spline_filter(volume, order=3, mode="mirror", output=np.float32)
    difference = float(np.abs(prefilter(volume) - expected).max() / np.abs(expected).max())
    scipy_s = _best(
        lambda: ndimage.spline_filter(volume, order=3, mode="mirror", output=np.float32),
        args.repeat,
    )
    voxels = volume.size
    print(f"{args.size}³: scipy spline_filter {scipy_s:.3f} s ({voxels / scipy_s / 1e6:.1f} "
          f"Mvoxel/s); largest relative difference of ours {difference:.2g}")  # fmt: skip
    rows = []
    coefficients = prefilter(volume)
    for threads in args.threads:
        numba.set_num_threads(threads)
        prefilter_s = _best(lambda: prefilter(volume), args.repeat)
        gradient_s = _best(lambda: gradient_volume(coefficients), args.repeat)
        rate, iterations = _second_order_rate(min(args.size, 96), args.repeat)
        rows.append(
            {"threads": threads, "prefilter_s": prefilter_s, "gradient_s": gradient_s,
             "second_order_voxel_iterations_per_s": rate, "iterations": iterations}
        )  # fmt: skip
        print(
            f"threads {threads}: prefilter {prefilter_s:.3f} s ({voxels / prefilter_s / 1e6:.0f} "
            f"Mvoxel/s), gradient {gradient_s:.3f} s ({voxels / gradient_s / 1e6:.0f} Mvoxel/s), "
            f"second-order IC-GN {rate:.3g} voxel-iterations/s ({iterations:.2f} iterations)"
        )
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"size": args.size, "scipy_s": scipy_s, "rows": rows}, handle, indent=2)


if __name__ == "__main__":
    main()
