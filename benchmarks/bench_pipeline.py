"""The whole command line on 100³ pairs, plain and self-corrected, with the time of every stage.

Three pairs like the issue's table (subvolume 21, step 8, first order; the deformed scans are made
with a 5th-order spline, not our cubic B-spline):

* ``translation``: a weak-contrast two-phase volume shifted by (2.3, -1.6, 3.7) voxels;
* ``shear band``: a textured volume with an inclined shear band (slip 5, width 8) and a shift;
* ``noisy band``: the shear band on a weak-contrast two-phase volume with 6 % noise on both scans
  (σ = 6 % of the clean reference's p1–p99 range).

Each case runs ``napari-dvc-correct correlate`` and ``correlate --self-correct`` as a user would
(a new process: start-up, reading the volumes, writing the field), three times each with the numba
cache warm after the first; the best warm time is reported with the engine's own stage timings
(from the field file) and the RMSE against the truth.

    python benchmarks/bench_pipeline.py [--size 100] [--repeat 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import GOOD_STATUSES
from napari_dvc_correct.io.npz import load_field


def _deform_order5(pattern: np.ndarray, displacement, margin: int) -> np.ndarray:
    """``F(X + u(X)) = G(X)`` by inverting ``u`` and sampling with a 5th-order spline (scipy)."""
    grids = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in pattern.shape], indexing="ij")
    targets = np.stack([g.reshape(-1) for g in grids], axis=1)
    shifted = lambda points: displacement(np.asarray(points) - margin)  # noqa: E731
    source = targets.copy()
    for _ in range(30):  # fixed point X = x - u(X)
        source = targets - shifted(source)
    values = ndimage.map_coordinates(pattern, source.T, order=5, mode="mirror")
    return values.reshape(pattern.shape).astype(np.float32)


def make_case(name: str, size: int, seed: int = 0):
    shape = (size,) * 3
    margin = 12
    big = tuple(n + 2 * margin for n in shape)
    center = tuple(n / 2 for n in shape)
    if name == "translation":
        truth = synthetic.translation((2.3, -1.6, 3.7))
        pattern = synthetic.two_phase_volume(big, phase_grays=(100.0, 112.0), seed=seed)
        noise = 0.0
    elif name == "shear band":
        truth = synthetic.shear_band(center, width=8.0, slip=5.0, shift=(1.5, -2.0, 2.5))
        pattern = synthetic.textured_volume(big, 2.0, seed=seed)
        noise = 0.0
    elif name == "noisy band":
        truth = synthetic.shear_band(center, width=8.0, slip=5.0, shift=(1.5, -2.0, 2.5))
        pattern = synthetic.two_phase_volume(big, phase_grays=(100.0, 112.0), seed=seed)
        noise = 0.06
    else:
        raise ValueError(name)
    crop = tuple(slice(margin, margin + n) for n in shape)
    reference = np.ascontiguousarray(pattern[crop], np.float32)
    deformed = np.ascontiguousarray(_deform_order5(pattern, truth, margin)[crop])
    if noise:
        low, high = np.percentile(reference, [1, 99])
        sigma = noise * float(high - low)
        reference = synthetic.add_noise(reference, sigma, seed=seed + 1)
        deformed = synthetic.add_noise(deformed, sigma, seed=seed + 2)
    return reference, deformed, truth


def _rmse(field_path: Path, truth) -> tuple[float, float]:
    field = load_field(field_path)
    expected = synthetic.sample_displacement(truth, field.points.reshape(*field.shape, 3))
    error = np.linalg.norm(field.u - expected, axis=-1)
    good = np.isin(field.status, [int(s) for s in GOOD_STATUSES]) & np.isfinite(error)
    filled = np.isfinite(error)
    return float(np.sqrt(np.mean(error[filled] ** 2))), float(good.mean())


def run_case(name: str, size: int, repeat: int) -> dict:
    reference, deformed, truth = make_case(name, size)
    result = {"case": name, "size": size}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        np.save(folder / "ref.npy", reference)
        np.save(folder / "def.npy", deformed)
        for label, extra in (("plain", []), ("self-corrected", ["--self-correct"])):
            out = folder / f"{label}.npz"
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
                *extra,
                "--out",
                str(out),
            ]
            times = []
            for _ in range(repeat):
                start = time.perf_counter()
                done = subprocess.run(command, capture_output=True, text=True)
                times.append(time.perf_counter() - start)
                if done.returncode:
                    raise RuntimeError(f"{name} {label}: {done.stderr.strip()}")
            field = load_field(out)
            rmse, good = _rmse(out, truth)
            timings = field.metadata.get("timings", {})
            correction = field.metadata.get("correction", {})
            result[label] = {
                "first_s": times[0],
                "warm_s": min(times[1:]) if len(times) > 1 else times[0],
                "rmse_voxel": rmse,
                "good_fraction": good,
                "engine_stages_s": {k: v for k, v in timings.items() if k.endswith("_s")},
                "correction_s": correction.get("seconds"),
                "passes": correction.get("passes_applied"),
                "correction_stages_s": correction.get("stages", {}),
                "stop_reason": correction.get("stop_reason"),
                "matched_per_pass": [
                    p.get("matched_nodes") for p in field.metadata.get("correction_passes", [])[1:]
                ],
            }
    result["correction_cost"] = result["self-corrected"]["warm_s"] / result["plain"]["warm_s"]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cases", nargs="*", default=["translation", "shear band", "noisy band"])
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    results = []
    for name in args.cases:
        row = run_case(name, args.size, args.repeat)
        results.append(row)
        plain, corrected = row["plain"], row["self-corrected"]
        print(
            f"{name:12s} plain {plain['warm_s']:6.2f} s (first {plain['first_s']:.1f}) "
            f"RMSE {plain['rmse_voxel']:.3f} | self-corrected {corrected['warm_s']:6.2f} s "
            f"RMSE {corrected['rmse_voxel']:.3f} passes {corrected['passes']} | "
            f"cost x{row['correction_cost']:.2f}",
            flush=True,
        )
        print(f"    plain stages: {plain['engine_stages_s']}", flush=True)
        stages = {k: round(v, 2) for k, v in corrected["correction_stages_s"].items()}
        print(f"    correction {corrected['correction_s']:.2f} s: {stages}", flush=True)
        print(
            f"    matched per pass {corrected['matched_per_pass']}; stop: "
            f"{corrected['stop_reason']}",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
