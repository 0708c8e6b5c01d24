"""Run the GPU kernels in numba's CUDA simulator on cases prepared by the tests.

Usage (the tests do this in a subprocess, so the simulator never leaks into other tests)::

    NUMBA_ENABLE_CUDASIM=1 python _simulate.py CASES.npz RESULTS.npz

``CASES.npz`` holds, per case ``c``: ``c/kind`` ("icgn" or "sample") and the arguments. The
results hold the outputs and, for IC-GN, the kernel's raw statuses before the CPU fallback.
"""

from __future__ import annotations

import os
import sys

import numpy as np


def main(cases_path: str, results_path: str) -> int:
    if os.environ.get("NUMBA_ENABLE_CUDASIM") != "1":
        raise SystemExit("set NUMBA_ENABLE_CUDASIM=1")
    from napari_dvc_correct.engine.backend import select_device
    from napari_dvc_correct.engine.correlation import icgn
    from napari_dvc_correct.engine.cuda import launch as gpu_launch
    from napari_dvc_correct.engine.cuda import match_many_cuda, sample_cuda, simulator_enabled

    launch = gpu_launch._launch

    assert simulator_enabled()
    data = dict(np.load(cases_path))
    names = sorted({key.split("/")[0] for key in data})
    out = {
        "device_cuda": np.array(select_device("cuda").kind),
        "device_cuda_description": np.array(select_device("cuda").description),
        "device_auto": np.array(select_device("auto").kind),
    }
    for name in names:
        case = {key.split("/", 1)[1]: value for key, value in data.items() if key.startswith(name)}
        if str(case["kind"]) == "sample":
            out[f"{name}/values"] = sample_cuda(case["coefficients"], case["points"])
            continue
        if str(case["kind"]) == "correlate":  # the whole pipeline with device="cuda"
            from napari_dvc_correct.engine.correlation.correlate import correlate
            from napari_dvc_correct.engine.correlation.params import CorrelationParams

            grid = (tuple(case["origin"]), tuple(case["step"]), tuple(case["grid_shape"]))
            params = CorrelationParams(
                subvolume=int(case["subvolume"]), search_radius=int(case["search_radius"])
            )
            field = correlate(case["reference"], case["deformed"], params, grid=grid, device="cuda")
            out[f"{name}/u"] = field.u
            out[f"{name}/status"] = field.status
            out[f"{name}/device"] = np.array(field.metadata["device"])
            continue
        n = len(case["centers"])
        inputs = icgn.MatchInputs(
            reference=case["reference"],
            gradient=case["gradient"],
            coef_deformed=case["coef_deformed"],
            mask=case["mask"],
            use_mask=bool(case["use_mask"]),
            half=int(case["half"]),
            nb=int(case["nb"]),
            max_iterations=int(case["max_iterations"]),
            tolerance=float(case["tolerance"]),
            min_std=float(case["min_std"]),
            min_mask_fraction=float(case["min_mask_fraction"]),
            max_update=float(case["max_update"]),
            noise_fraction=float(case["noise_fraction"]) if "noise_fraction" in case else 0.0,
        )
        recorded = {}

        def recording_launch(*arguments, recorded=recorded, **options):
            # keep the kernel's own statuses (before the CPU re-matches FALLBACK POIs)
            launch(*arguments, **options)
            recorded["status"] = arguments[4].copy()

        gpu_launch._launch = recording_launch
        params = case["params"].copy()
        zncc, status, iterations = np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64)
        match_many_cuda(
            inputs, case["centers"], params, zncc, status, iterations, threads_per_block=16
        )
        gpu_launch._launch = launch
        out[f"{name}/raw_status"] = recorded["status"]
        out[f"{name}/params"] = params
        out[f"{name}/zncc"] = zncc
        out[f"{name}/status"] = status
        out[f"{name}/iterations"] = iterations
    np.savez(results_path, **out)
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
