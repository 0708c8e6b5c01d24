"""Speed and accuracy of the forward warp (issue 13: "a correction at most 2x a plain run").

The forward warp ``G'(X + u(X)) = G(X)`` inverts the field at every loaded voxel. Two ways, A/B
in the same process on the same volume and field:

* ``exact``: Newton at every voxel (``warp_forward_block(..., accuracy=None)``, i.e.
  ``FieldSpline.invert`` warm-started from the x neighbour);
* ``lattice``: Newton on a coarse lattice, interpolation checked cell by cell, Newton where the
  check fails (``LatticeInverter.solve``, positions slab by slab, then sampled: what the tiled
  warps do with their lazy volumes);
* ``fused``: the same inverse with ``G`` sampled as the positions are made
  (``LatticeInverter.warp``, what ``warp_forward`` does in memory): no positions array.

Workload: a 256³ textured float32 volume, a POI grid of subvolume 21 and step 8, two fields: a
smooth large displacement (translation, 3° rotation, 2 % waves) and a narrow shear band (width 8
voxels = the node step, slip 4 voxels: 25 % peak shear). Prints Mvoxel/s of the whole warp and of
its two stages (inversion, sampling ``G``; for ``fused``: the coarse stage and the rest) at 1 and
2 numba threads, wall and CPU time (the
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
    from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
    from napari_dvc_correct.engine.fields.field_spline import FieldSpline

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
    """Warp slab by slab; returns the source positions, the stage times and the Newton share.

    ``accuracy=None``: Newton at every voxel. Otherwise one :class:`LatticeInverter` for the whole
    volume (its coarse stage is counted in the inversion), solved slab by slab, as
    ``warp.warp_forward`` does.
    """
    from napari_dvc_correct.engine.correlation.interpolation import sample
    from napari_dvc_correct.engine.fields import warp
    from napari_dvc_correct.engine.slabs import iter_slabs

    shape = coefficients.shape
    positions = np.empty((int(np.prod(shape)), 3))
    newton = 0
    times = np.zeros(4)  # inversion wall, cpu; sampling wall, cpu
    if accuracy is not None:
        from napari_dvc_correct.engine.fields.inverse_lattice import LatticeInverter

        box = tuple(slice(0, n) for n in shape)
        inverter, wall, cpu = timed(lambda: LatticeInverter(spline, box, accuracy=accuracy))
        times[:2] += wall, cpu
    done = 0
    for z in iter_slabs(shape, warp.DEFAULT_CHUNK_VOXELS):
        if accuracy is None:
            box = (z, slice(0, shape[1]), slice(0, shape[2]))
            (source, _), wall, cpu = timed(lambda box=box: spline.invert(warp.box_lattice(box)))
        else:
            inverse, wall, cpu = timed(lambda z=z: inverter.solve(z))
            source = inverse.positions
            newton += int(inverse.exact.sum())
        times[:2] += wall, cpu
        _, wall, cpu = timed(lambda source=source: sample(coefficients, source, cval=np.nan))
        times[2:] += wall, cpu
        positions[done : done + len(source)] = source
        done += len(source)
    return positions, times, newton / len(positions)


def run_fused(coefficients, spline, accuracy):
    """The fused warp: coarse stage (Newton at the nodes, checks), then fill and sampling."""
    from napari_dvc_correct.engine.fields.inverse_lattice import LatticeInverter

    box = tuple(slice(0, n) for n in coefficients.shape)
    inverter, wall, cpu = timed(lambda: LatticeInverter(spline, box, accuracy=accuracy))
    (values, _), fill_wall, fill_cpu = timed(lambda: inverter.warp(coefficients))
    return values, np.array([wall, cpu, fill_wall, fill_cpu])


def report(name, t, voxels, stages=("inversion", "sampling")):
    whole_wall, whole_cpu = t[0] + t[2], t[1] + t[3]
    print(
        f"  {name} warp {voxels / whole_wall / 1e6:6.2f} Mvox/s wall, "
        f"{voxels / whole_cpu / 1e6:6.2f} per CPU-s | {stages[0]} "
        f"{voxels / t[0] / 1e6:6.2f} wall, {voxels / t[1] / 1e6:6.2f} CPU | "
        f"{stages[1]} {voxels / t[2] / 1e6:6.2f} wall, {voxels / t[3] / 1e6:6.2f} CPU"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument(
        "--exact-only", action="store_true", help="per-voxel Newton only (runs on older versions)"
    )
    args = parser.parse_args()

    import numba

    from napari_dvc_correct.engine import synthetic
    from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
    from napari_dvc_correct.engine.fields.field_spline import inside_hull

    accuracy = None if args.exact_only else 1e-3  # warp.INVERSE_ACCURACY

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
        if accuracy is not None:
            run(small, spline, accuracy)
            run_fused(small, spline, accuracy)
        for threads in args.threads:
            numba.set_num_threads(threads)
            exact, exact_times, _ = run(coefficients, spline, None)
            print(f"{kind} field, {size}^3, threads={threads}, load {os.getloadavg()[0]:.2f}:")
            report("exact  ", exact_times, voxels)
            if accuracy is None:
                continue
            fast, fast_times, fallback = run(coefficients, spline, accuracy)
            report("lattice", fast_times, voxels)
            fused, fused_times = run_fused(coefficients, spline, accuracy)
            report("fused  ", fused_times, voxels, ("coarse stage", "fill + sampling"))
            two_pass = sample(coefficients, fast, cval=np.nan).reshape(fused.shape)
            same_nan = np.array_equal(np.isnan(fused), np.isnan(two_pass))
            print(
                f"  fused vs lattice + sample: max |difference| "
                f"{np.nanmax(np.abs(fused - two_pass)):.1e} gray levels, same NaNs: {same_nan}"
            )
            error = np.abs(fast - exact).max(axis=1)
            hull = inside_hull(spline, exact)
            print(
                f"  lattice vs exact: inverse error in the hull max {error[hull].max():.2e} "
                f"mean {error[hull].mean():.2e}, outside max {error[~hull].max():.2e} voxel "
                f"({100 * hull.mean():.0f} % in the hull), Newton at {100 * fallback:.1f} % of voxels, "
                f"speed-up {(exact_times[0] + exact_times[2]) / (fast_times[0] + fast_times[2]):.1f}x "
                f"(inversion {exact_times[0] / fast_times[0]:.1f}x)"
            )


if __name__ == "__main__":
    main()
