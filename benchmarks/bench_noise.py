"""Noisy weak-texture CT (issue 10, measurement side): flags, noise stop and uncertainty.

A CT-like concrete pair (:func:`engine.synthetic.noisy_ct_pair`: faint aggregates 5 % brighter
than the matrix, a dark background outside a cylinder, noise of ``--noise`` × the p1–p99 range on
both scans) under a broad shear band with compression, correlated with subvolume 21, step 8.
Prints the noise estimate, the ZNCC thresholds, status counts, IC-GN iterations and time, the
RMSE of the good nodes and how the predicted uncertainty compares with the actual errors.

Runs against whatever ``napari_dvc_correct`` is importable, so the same script measures another
branch (``PYTHONPATH=/path/to/other/src python benchmarks/bench_noise.py``). Timings on a shared
machine are noisy: compare A/B runs made one after the other.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time
from pathlib import Path

import numpy as np

from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import GOOD_STATUSES


def _synthetic():
    """This checkout's ``engine/synthetic.py`` (numpy + scipy only), whatever package runs."""
    path = Path(__file__).parents[1] / "src" / "napari_dvc_correct" / "engine" / "synthetic.py"
    spec = importlib.util.spec_from_file_location("bench_synthetic", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    synthetic = _synthetic()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=80)
    parser.add_argument("--noise", type=float, default=0.06)
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--noise-tolerance", type=float, default=None)
    args = parser.parse_args()
    shape = (args.size,) * 3
    center = np.array(shape) / 2.0
    truth = synthetic.shear_band(
        center, width=8.0, slip=3.0, background_strain=0.01, shift=(0.4, -0.7, 1.2)
    )
    reference, deformed, sigma = synthetic.noisy_ct_pair(shape, truth, args.noise, args.seed)
    options = {} if args.noise_tolerance is None else {"noise_tolerance": args.noise_tolerance}
    params = CorrelationParams(subvolume=21, step=8, **options)
    correlate(reference[:40, :40, :40], deformed[:40, :40, :40], params)  # compile / cache
    start = time.perf_counter()
    field = correlate(reference, deformed, params)
    total = time.perf_counter() - start
    expected = synthetic.sample_displacement(truth, field.points).reshape(*field.shape, 3)
    good = np.isin(field.status, [int(s) for s in GOOD_STATUSES])
    error = field.u - expected
    rmse = float(np.sqrt(np.mean(np.sum(error[good] ** 2, axis=-1))))
    report = {
        "noise_sigma_added": sigma,
        "pois": field.n_points,
        "status": field.status_counts(),
        "mean_zncc": float(np.nanmean(field.zncc)),
        "mean_iterations_good": float(field.iterations[good].mean()),
        "icgn_s": round(field.metadata["timings"]["icgn_s"], 2),
        "total_s": round(total, 2),
        "rmse_good": round(rmse, 4),
    }
    if "noise" in field.metadata:
        report["noise"] = field.metadata["noise"]
    if getattr(field, "uncertainty", None) is not None:
        predicted = field.uncertainty[good]
        report["predicted_sigma_rms"] = np.sqrt(np.nanmean(predicted**2, axis=0)).round(4).tolist()
        report["error_std"] = error[good].std(axis=0).round(4).tolist()
        ratio = np.abs(error[good]) / predicted
        report["fraction_within_2_sigma"] = round(float(np.mean(ratio < 2.0)), 3)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
