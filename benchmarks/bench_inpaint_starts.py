"""Would a warm start shorten the correction's inpainting? Conjugate-gradient iterations of every
inpainting solve of one self-correction, from each starting point (issue 30).

Runs the plain field and its correction on the cases of :mod:`bench_plain_cpu` (``upper`` /
``lower``: the real crops with the specimen mask, where the masked nodes make the solves large
enough for conjugate gradients; the synthetic cases fill fewer than
:data:`~napari_dvc_correct.engine.correction.cleaning.DIRECT_SOLVE_LIMIT` nodes and solve
directly), records every call of :func:`~napari_dvc_correct.engine.correction.cleaning.inpaint`,
and solves each call's system again with the same stopping rule (``‖r‖ < 10⁻¹⁰ ‖b‖``) from:
the nearest known value (what :func:`inpaint` does), zero, and the previous call's solution at
the nodes both calls fill (the warm start). Prints the sparse products of each and the largest
difference of each solution from a direct (``splu``) solve.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_inpaint_starts.py upper lower
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import linalg as sparse_linalg

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_plain_cpu import load_case  # noqa: E402

from napari_dvc_correct.engine.correction import cleaning  # noqa: E402

RTOL, MAX_ITERATIONS = 1e-10, 2000  # as inpaint's


class _Counting:
    """A sparse matrix that counts its products (``jacobi_cg`` needs ``@`` and ``diagonal``)."""

    def __init__(self, matrix):
        self.matrix, self.products, self.shape = matrix, 0, matrix.shape

    def diagonal(self):
        return self.matrix.diagonal()

    def __matmul__(self, other):
        self.products += 1
        return self.matrix @ other


def _system(values, known, step):
    """``inpaint``'s normal equations, right-hand side, nearest-value start and unknown nodes."""
    values = np.asarray(values, dtype=np.float64)
    values = values[..., None] if values.ndim == 3 else values
    known = known & np.all(np.isfinite(values), axis=-1)
    unknown = ~known
    matrix, rhs = cleaning._thin_plate_system(values, unknown, step)
    normal = (matrix.T @ matrix).tocsc()
    ridge = 1e-11 * float(normal.diagonal().max())
    normal = normal + ridge * sparse.identity(normal.shape[0], format="csc")
    normal_rhs = matrix.T @ rhs + ridge * values[known].mean(axis=0)
    _, nearest = ndimage.distance_transform_edt(unknown, return_indices=True)
    return normal, normal_rhs, values[tuple(nearest)][unknown], unknown


def _solve(normal, rhs, start):
    counting = _Counting(normal)
    return cleaning.jacobi_cg(counting, rhs, start, RTOL, MAX_ITERATIONS), counting.products


def main() -> None:
    from napari_dvc_correct.engine.correction.self_correction import correct
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="+")
    args = parser.parse_args()
    params = CorrelationParams(subvolume=21, step=8)
    original = cleaning.inpaint
    calls = []

    def recording(values, known, step=(1.0, 1.0, 1.0), **kwargs):
        calls.append((np.array(values), np.array(known), step))
        return original(values, known, step, **kwargs)

    for name in args.cases:
        data = load_case(name)
        if data is None:
            print(f"{name}: data absent, skipped")
            continue
        reference, deformed, mask = data
        plain = correlate(reference, deformed, params, mask=mask)
        calls.clear()
        cleaning.inpaint = recording
        try:
            correct(reference, deformed, plain, params, mask=mask)
        finally:
            cleaning.inpaint = original
        print(f"{name}: {len(calls)} inpainting calls")
        previous = None
        for number, (values, known, step) in enumerate(calls):
            normal, rhs, nearest, unknown = _system(values, known, step)
            if unknown.sum() <= cleaning.DIRECT_SOLVE_LIMIT:
                print(f"  call {number}: {unknown.sum()} nodes to fill, direct solve")
                previous = None
                continue
            exact = sparse_linalg.splu(normal).solve(np.ascontiguousarray(rhs))
            rows = []
            starts = [("nearest", nearest), ("zero", np.zeros_like(nearest))]
            if previous is not None and previous[1].shape[1] == rhs.shape[1]:
                warm = np.zeros(unknown.shape + (rhs.shape[1],))
                warm[previous[0]] = previous[1]
                starts.append(("previous solution", warm[unknown]))
            for label, start in starts:
                solution, products = _solve(normal, rhs, start)
                rows.append(f"{label} {products} ({np.abs(solution - exact).max():.1e})")
                if label == "nearest":
                    previous = (unknown, solution)
            print(
                f"  call {number}: {unknown.sum()} nodes to fill, {rhs.shape[1]} columns, "
                f"‖b‖ {np.linalg.norm(rhs):.2e}; products (largest difference from splu): "
                + "; ".join(rows)
            )


if __name__ == "__main__":
    main()
