"""Measurements behind docs/method.md: the self-correction's variants, scan series, warp speed.

Case A: the shear band of ``tests/engine/test_correction.py`` (64³ two-phase noisy pair, band
width 8, slip 10, rigid shift (8, -6, 12): equivalent strain about 0.36 at the band, displacements
up to 17 voxels; subvolume 25, step 5). The uncorrected field, the first-order floor (best affine
fit of the true field over each subvolume) and the four variants frame × update, each with up to
3 passes. Errors in voxels against the true field at every node; the mean gray residual in gray
levels (reference mode, hull, measured the same way for every field).

Case B: a scan series of three states (the band's slip and shift grow with the state), total vs
incremental, with and without the correction of the merged totals; RMSE of ``U_0→2``.

Case C: speed and memory of densify / pull-back / forward warp on a 256³ volume.

Run: ``python benchmarks/bench_correction.py [--cases abc] [--size 256]``.
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc

import numpy as np

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction.cleaning import clean
from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.interpolation import prefilter
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation import residual
from napari_dvc_correct.engine.fields import field_spline, warp
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.series.strategies import series

SIZE = 64
PARAMS = CorrelationParams(subvolume=25, step=5)


def band(slip=10.0, shift=(8.0, -6.0, 12.0)):
    return synthetic.shear_band((SIZE / 2,) * 3, width=8.0, slip=slip, shift=shift)


def errors(field: DisplacementField, truth) -> np.ndarray:
    return np.linalg.norm(field.displacement - truth(field.points), axis=1)


def floor_errors(field: DisplacementField, truth, half: int) -> np.ndarray:
    offsets = np.stack(
        np.meshgrid(*[np.arange(-half, half + 1.0)] * 3, indexing="ij"), axis=-1
    ).reshape(-1, 3)
    row = np.linalg.pinv(np.column_stack([np.ones(len(offsets)), offsets]))[0]
    return np.array(
        [np.linalg.norm(row @ truth(p + offsets) - truth(p[None])[0]) for p in field.points]
    )


def line(name, err, residual, extra=""):
    ok = np.isfinite(err)
    rmse = np.sqrt(np.mean(err[ok] ** 2))
    print(
        f"| {name:<28} | {rmse:6.3f} | {np.mean(err[ok] > 1.0):6.3f} | {err[ok].max():5.2f} | "
        f"{residual:7.3f} | {extra}"
    )


def case_a():
    truth = band()
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.two_phase_volume(s, seed=4), (SIZE,) * 3, truth, margin=24
    )
    reference = synthetic.add_noise(reference, 6.0, seed=1)
    deformed = synthetic.add_noise(deformed, 6.0, seed=2)
    started = time.perf_counter()
    measured = correlate(reference, deformed, PARAMS)
    dvc_seconds = time.perf_counter() - started
    print(f"\nCase A: grid {measured.shape}, DVC {dvc_seconds:.1f} s")
    print("| field | RMSE | >1 vox | max | residual | passes, time |")
    floor = floor_errors(measured, truth, PARAMS.half)
    print(f"| first-order floor            | {np.sqrt(np.mean(floor**2)):6.3f} | "
          f"{np.mean(floor > 1):6.3f} | {floor.max():5.2f} |")  # fmt: skip
    cleaned = clean(measured)
    line(
        "uncorrected",
        errors(measured, truth),
        residual.mean_gray_residual(reference, deformed, cleaned),
    )
    for frame in ("loaded", "reference"):
        for update in ("exact", "sum"):
            started = time.perf_counter()
            corrected = correct(reference, deformed, measured, frame=frame, update=update)
            seconds = time.perf_counter() - started
            passes = corrected.metadata["correction_passes"]
            trail = " -> ".join(
                f"{p['mean_gray_residual']:.2f}{'' if p['accepted'] else ' (rejected)'}"
                for p in passes
            )
            line(
                f"{frame} / {update}",
                errors(corrected, truth),
                residual.mean_gray_residual(reference, deformed, corrected),
                f"{corrected.metadata['correction']['passes_applied']} applied, {seconds:.0f} s; "
                f"own residual {trail}",
            )


def case_b():
    states = [
        band(0.0, (0.0, 0.0, 0.0)),
        band(5.0, (4.0, -3.0, 6.0)),
        band(10.0, (8.0, -6.0, 12.0)),
    ]
    margin = 24
    big = synthetic.two_phase_volume(tuple(n + 2 * margin for n in (SIZE,) * 3), seed=4)
    crop = tuple(slice(margin, margin + SIZE) for _ in range(3))
    volumes = [synthetic.add_noise(big[crop], 6.0, seed=10)]
    for k in (1, 2):
        moved = synthetic.deform_volume(big, lambda p, t=states[k]: t(np.asarray(p) - margin))
        volumes.append(synthetic.add_noise(moved[crop], 6.0, seed=10 + k))
    print("\nCase B: three states, RMSE of U_0->2 (voxels), mean gray residual of V0/V2")
    for strategy in ("total", "incremental"):
        for corrected in (False, True):
            started = time.perf_counter()
            result = series(volumes, PARAMS, strategy=strategy, correct_total=corrected)
            seconds = time.perf_counter() - started
            total = result.totals[-1]
            err = errors(total, states[2])
            ok = np.isfinite(err)
            print(
                f"| {strategy:<11} | corrected={corrected!s:<5} | RMSE {np.sqrt(np.mean(err[ok] ** 2)):.3f} "
                f"| >1 vox {np.mean(err[ok] > 1):.3f} | residual "
                f"{total.metadata['series']['mean_gray_residual']:.3f} | {seconds:.0f} s |"
            )


def case_c(size=256):
    truth = band()
    origin, step = (12.0, 12.0, 12.0), (8.0, 8.0, 8.0)
    shape = tuple(int((size - 25) // 8 + 1) for _ in range(3))
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(truth, field.points.reshape(*shape, 3))
    volume = synthetic.textured_volume((size,) * 3, 2.0, seed=1)
    coefficients = prefilter(volume)
    print(f"\nCase C: {size}^3 volume, {os.cpu_count()} CPU(s), field grid {shape}")
    print("(volume coefficients prefiltered beforehand; peaks include the float32 output volume)")
    dense_bytes = 3 * size**3 * 8

    def slabs():
        for _ in field_spline.iter_dense(field, volume.shape):
            pass

    for name, run in (
        ("densify, slab by slab", slabs),
        ("pull_back", lambda: warp.pull_back(volume, field, coefficients=coefficients)),
        ("warp_forward", lambda: warp.warp_forward(volume, field, coefficients=coefficients)),
        (
            "mean_gray_residual",
            lambda: residual.mean_gray_residual(
                volume, volume, field, deformed_coefficients=coefficients
            ),
        ),
        (
            "mean_gray_residual loaded",
            lambda: residual.mean_gray_residual(
                volume, volume, field, "loaded", reference_coefficients=coefficients
            ),
        ),
    ):
        run()  # compile
        started = time.perf_counter()
        run()
        seconds = time.perf_counter() - started
        # memory in a second run: tracemalloc also traces numba's allocations, which slows
        # the kernels down, so it must not run while timing
        tracemalloc.start()
        run()
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(
            f"| {name:<26} | {seconds:6.2f} s | {size**3 / seconds / 1e6:6.1f} Mvoxel/s | "
            f"peak {peak / 2**20:7.1f} MiB (a dense float64 field: {dense_bytes / 2**20:.0f} MiB) |"
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="abc", help="which cases to run (default abc)")
    parser.add_argument("--size", type=int, default=256, help="volume edge for case C")
    args = parser.parse_args()
    if "a" in args.cases:
        case_a()
    if "b" in args.cases:
        case_b()
    if "c" in args.cases:
        case_c(args.size)


if __name__ == "__main__":
    main()
