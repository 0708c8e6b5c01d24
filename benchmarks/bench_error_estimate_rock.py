"""The error estimate on the real rock pair of ../shared/data/real-rock (issue 26; no truth).

Correlates each crop (subvolume 21, step 10, first order), cleans the field and evaluates it:
the estimate should be high along the crack of ``rock_lower.npz`` and low in ``rock_upper.npz``.
Prints the pair's gray-level map, r0, p, the estimate's median / 95th percentile / share above
0.5 voxel, and (lower crop) the estimate near the crack (nodes the correlation could not match
or flagged as discontinuous, and their neighbours) against the rest.

    python benchmarks/bench_error_estimate_rock.py [../shared/data/real-rock] [--apply-correlation]

The pair's measured noise correlation is printed; ``--apply-correlation`` lets the estimate use it
(``noise_correlation.NOISE_CORRELATION_APPLIED``, off by default).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from napari_dvc_correct.engine.correction.cleaning import clean
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.evaluation.results import measured_mask


def main(folder: Path) -> None:
    for name in ("rock_upper", "rock_lower"):
        data = np.load(folder / f"{name}.npz")
        reference = data["reference"].astype(np.float32)
        deformed = data["deformed"].astype(np.float32)
        started = time.perf_counter()
        field = correlate(reference, deformed, CorrelationParams(subvolume=21, step=10))
        cleaned = clean(field, fill_masked=True)
        result = evaluate_fields(reference, deformed, {name: cleaned}, keep_volumes=False)
        item = result[name]
        error = item.error
        print(
            f"{name}: {time.perf_counter() - started:.0f} s; {result.gray_levels.describe()}; "
            f"r0 {result.pair.background.mean:.3f}; mean residual {item.mean_residual:.3f}; "
            f"p {item.accuracy:.4f}; measured {item.measured_nodes}/{cleaned.n_points}; "
            f"estimate median {error['median']:.3f}, 95 % {error['p95']:.3f}, "
            f"likely > 0.5: {100 * error['likely_bad']:.1f} %, "
            f"resolution median {error['resolution']:.3f}"
        )
        correlation = getattr(result.pair, "noise_correlation", None)
        if correlation is not None:
            lags = "; ".join(
                f"{axis} {np.round(correlation.along(a), 3).tolist()}"
                for a, axis in enumerate("zyx")
            )
            factors = {k: round(v, 2) for k, v in correlation.factors.items()}
            print(f"  noise correlation at lags 1-3: {lags}; window factors {factors}")
        # the crack: nodes the DVC could not match, and their neighbours
        unmatched = ~measured_mask(field)
        near = ndimage.binary_dilation(unmatched) & ~unmatched
        far = ~ndimage.binary_dilation(unmatched, iterations=2)
        e = item.error_estimate
        for label, nodes in (("unmatched", unmatched), ("next to them", near), ("far", far)):
            values = e[nodes & np.isfinite(e)]
            if values.size:
                print(
                    f"  {label}: {values.size} nodes, median {np.median(values):.3f}, "
                    f"share > 0.5 {100 * np.mean(values > 0.5):.1f} % ({np.sum(values > 0.5)} nodes)"
                )
        z = np.argmax(np.nansum(e > 0.5, axis=(1, 2)))
        rows = np.where(np.isfinite(e[z]), np.minimum(e[z], 9.9), np.nan)
        print(f"  estimate at node plane z={z} (voxels, capped at 9.9):")
        for row in rows:
            print("   " + " ".join(f"{v:4.1f}" for v in row))


if __name__ == "__main__":
    here = Path(__file__).resolve().parents[1]
    if "--apply-correlation" in sys.argv:  # the pair's measured noise correlation in the estimate
        from napari_dvc_correct.engine.evaluation import noise_correlation

        noise_correlation.NOISE_CORRELATION_APPLIED = True
        sys.argv.remove("--apply-correlation")
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else here.parent / "shared/data/real-rock")
