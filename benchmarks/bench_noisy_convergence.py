"""IC-GN convergence on very noisy CT-like pairs (issue 13): POIs at the limit, iterations, RMSE.

A CT-like concrete pair (:func:`engine.synthetic.noisy_ct_pair`, the deformed scan made with a
5th-order spline, noise of ``--noise`` × the p1–p99 range on both scans) under a broad shear band
with background strain (``--case band``, as ``bench_noise.py``) or an affine field (``--case
affine``, where only the noise makes errors), correlated with subvolume 21, step 8, once per
``--noise-tolerance``. Prints, per run: POIs at ``max_iterations``, mean iterations, statuses,
IC-GN time, and the RMSE against the imposed field over the good POIs and over every POI with a
value (LOW_ZNCC POIs keep theirs).

Runs against whatever ``napari_dvc_correct`` is importable, so the same script measures another
branch (``PYTHONPATH=/path/to/other/src python benchmarks/bench_noisy_convergence.py``).

    python benchmarks/bench_noisy_convergence.py [--size 100] [--case band] [--noise 0.12]
        [--noise-tolerance 0.1 0.5]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import GOOD_STATUSES


def make_case(case: str, size: int, noise: float, seed: int = 4):
    """Reference, deformed and the imposed field ``u(points)`` of one case."""
    center = np.array((size / 2.0,) * 3)
    if case == "band":
        truth = synthetic.shear_band(
            center, width=8.0, slip=3.0, background_strain=0.01, shift=(0.4, -0.7, 1.2)
        )
    elif case == "affine":
        truth = synthetic.affine(np.diag([0.01, -0.005, 0.008]), center, shift=(0.37, -0.61, 1.23))
    else:
        raise ValueError(case)
    reference, deformed, _ = synthetic.noisy_ct_pair((size,) * 3, truth, noise, seed)
    return reference, deformed, truth


def run(reference, deformed, truth, noise_tolerance: float, max_iterations: int) -> dict:
    params = CorrelationParams(
        subvolume=21, step=8, noise_tolerance=noise_tolerance, max_iterations=max_iterations
    )
    field = correlate(reference, deformed, params)
    expected = synthetic.sample_displacement(truth, field.points.reshape(*field.shape, 3))
    error = np.linalg.norm(field.u - expected, axis=-1)
    good = np.isin(field.status, [int(s) for s in GOOD_STATUSES]) & np.isfinite(error)
    return {
        "noise_tolerance": noise_tolerance,
        "pois": int(field.status.size),
        "at_limit": int(np.sum(field.iterations >= max_iterations)),
        "mean_iterations": round(float(field.iterations[field.iterations > 0].mean()), 2),
        "status": field.status_counts(),
        "icgn_s": round(field.metadata["timings"]["icgn_s"], 2),
        "rmse_good": round(float(np.sqrt(np.mean(error[good] ** 2))), 4),
        "rmse_all": round(float(np.sqrt(np.nanmean(error**2))), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--case", choices=("band", "affine"), default="band")
    parser.add_argument("--noise", type=float, default=0.12)
    parser.add_argument("--noise-tolerance", type=float, nargs="+", default=[0.1])
    parser.add_argument("--max-iterations", type=int, default=50)
    args = parser.parse_args()
    reference, deformed, truth = make_case(args.case, args.size, args.noise)
    correlate(reference[:40, :40, :40], deformed[:40, :40, :40], CorrelationParams(21, 8))
    for tolerance in args.noise_tolerance:
        report = run(reference, deformed, truth, tolerance, args.max_iterations)
        print(json.dumps({"case": args.case, "size": args.size, "noise": args.noise, **report}))


if __name__ == "__main__":
    main()
