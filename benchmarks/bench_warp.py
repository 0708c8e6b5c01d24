"""Speed and accuracy of the forward warp (issue 13: "a correction at most 2x a plain run").

The forward warp ``G'(X + u(X)) = G(X)`` inverts the field at every loaded voxel. Two ways, A/B
in the same process on the same volume and field:

* ``exact``: Newton at every voxel (``warp_forward_block(..., accuracy=None)``, i.e.
  ``FieldSpline.invert`` warm-started from the x neighbour);
* ``lattice``: Newton on a coarse lattice, interpolation checked cell by cell, Newton where the
  check fails (``FieldSpline.invert_lattice``, the default).

Workload: a 256³ textured float32 volume, a POI grid of subvolume 21 and step 8, two fields: a
smooth large displacement (translation, 3° rotation, 2 % waves) and a narrow shear band (width 8
voxels = the node step, slip 4 voxels: 25 % peak shear). Prints Mvoxel/s of the whole warp and of
its two stages (inversion, sampling ``G``) at 1 and 2 numba threads, wall and CPU time (the
machine is shared: CPU time of one thread is the cleaner figure), the lattice inverse's max and
mean error against the exact one, and the share of voxels solved by Newton.

Run: ``python benchmarks/bench_warp.py [--size 256] [--threads 1 2]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np


def make_case(size: int, kind: str):
    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.field import DisplacementField, grid_for_volume
    from napari_dvc_correct.engine.field_spline import FieldSpline

    centre = np.full(3, size / 2.0)
    if kind == "smooth":
        rotation = synthetic.rotation_z(3.0, centre, (4.0, -6.0, 7.5))

        def function(points):
            waves = (
                0.02
                * size
                / (2 * np.pi)
                * np.sin(np.asarray(points)[..., [2, 0, 1]] * 2 * np.pi / size)
            )
            return rotation(points) + waves

    else:
        function = synthetic.shear_band(centre, width=8.0, slip=4.0, shift=(1.5, -2.0, 2.5))
    origin, step, shape = grid_for_volume((size,) * 3, 21, 8)
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(function, field.points.reshape(*shape, 3))
    return FieldSpline.from_field(field)


def timed(function):
    wall, cpu = time.perf_counter(), time.process_time()
    result = function()
    return result, time.perf_counter() - wall, time.process_time() - cpu


def run(coefficients, spline, accuracy):
    """Warp slab by slab; returns the source positions and the stage times."""
    from napari_dvc_correct.engine import warp
    from napari_dvc_correct.engine.interpolation import sample

    shape = coefficients.shape
    positions = np.empty((int(np.prod(shape)), 3))
    fallback = 0
    times = np.zeros(4)  # inversion wall, cpu; sampling wall, cpu
    done = 0
    for _, box in warp.slab_boxes(shape):
        if accuracy is None:
            (source, _), wall, cpu = timed(lambda box=box: spline.invert(warp.box_lattice(box)))
        else:
            inverse, wall, cpu = timed(
                lambda box=box: spline.invert_lattice(box, accuracy=accuracy)
            )
            source = inverse.positions
            fallback += int(inverse.exact.sum())
        times[:2] += wall, cpu
        _, wall, cpu = timed(lambda source=source: sample(coefficients, source, cval=np.nan))
        times[2:] += wall, cpu
        positions[done : done + len(source)] = source
        done += len(source)
    return positions, times, fallback / len(positions)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()

    import numba

    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.interpolation import prefilter
    from napari_dvc_correct.engine.warp import INVERSE_ACCURACY

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"numba {numba.__version__}, load average {os.getloadavg()[0]:.2f} at start"
    )
    size = args.size
    coefficients = prefilter(synthetic.textured_volume((size,) * 3, 2.0, seed=0))
    voxels = size**3
    for kind in ("smooth", "band"):
        spline = make_case(size, kind)
        small = prefilter(np.zeros((8, 8, 8), np.float32))
        run(small, spline, None)  # compile or load every kernel
        run(small, spline, INVERSE_ACCURACY)
        for threads in args.threads:
            numba.set_num_threads(threads)
            exact, exact_times, _ = run(coefficients, spline, None)
            fast, fast_times, fallback = run(coefficients, spline, INVERSE_ACCURACY)
            error = np.abs(fast - exact).max(axis=1)
            print(f"{kind} field, {size}^3, threads={threads}, load {os.getloadavg()[0]:.2f}:")
            for name, t in (("exact  ", exact_times), ("lattice", fast_times)):
                whole_wall, whole_cpu = t[0] + t[2], t[1] + t[3]
                print(
                    f"  {name} warp {voxels / whole_wall / 1e6:6.2f} Mvox/s wall, "
                    f"{voxels / whole_cpu / 1e6:6.2f} per CPU-s | inversion "
                    f"{voxels / t[0] / 1e6:6.2f} wall, {voxels / t[1] / 1e6:6.2f} CPU | "
                    f"sampling {voxels / t[2] / 1e6:6.2f} wall, {voxels / t[3] / 1e6:6.2f} CPU"
                )
            print(
                f"  lattice vs exact: inverse error max {error.max():.2e} mean {error.mean():.2e} "
                f"voxel, Newton at {100 * fallback:.1f} % of voxels, "
                f"speed-up {(exact_times[0] + exact_times[2]) / (fast_times[0] + fast_times[2]):.1f}x "
                f"(inversion {exact_times[0] / fast_times[0]:.1f}x)"
            )


if __name__ == "__main__":
    main()
