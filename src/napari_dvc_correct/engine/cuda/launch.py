"""Host side of the GPU IC-GN: :func:`match_many_cuda`, a drop-in for
:func:`napari_dvc_correct.engine.correlation.icgn.match_many`.

It uploads the volumes (kept on the GPU between calls, :mod:`.memory`) and the reference tables of
:mod:`.tables`, launches the kernel of :mod:`.icgn` in chunks of at most
:data:`MAX_POIS_PER_LAUNCH` POIs, and matches on the CPU the POIs the kernel flags
:data:`.icgn.FALLBACK` (warped subvolume leaving the volume) and, when the GPU fails (driver,
compiler, memory), all of them, with a warning.
"""

from __future__ import annotations

import functools
import warnings

import numpy as np

from ..correlation import icgn as cpu_icgn
from ._numba_cuda import cuda
from .icgn import FALLBACK, build_kernel
from .memory import default_threads, to_device_cached
from .tables import reference_tables

#: Largest number of POIs per kernel launch (keeps a launch well under a display watchdog).
MAX_POIS_PER_LAUNCH = 8192


@functools.cache
def _device_tables(nb: int):
    tables = reference_tables(nb)
    return (
        cuda.to_device(tables.pass_slots),
        cuda.to_device(tables.pass_base),
        cuda.to_device(tables.pass_count),
        cuda.to_device(tables.dist),
        cuda.to_device(tables.dist_n),
        cuda.to_device(tables.hess_map),
        cuda.to_device(tables.jsum_map),
        cuda.to_device(tables.jgsum_map),
        tables.ssg_index,
    )


def _gpu_errors() -> tuple[type[BaseException], ...]:
    """Exception types that mean "the GPU failed" (driver, compiler, memory), not a bug."""
    found = []
    for module_name, names in (
        ("numba.cuda.cudadrv.error", ("CudaSupportError", "CudaDriverError", "NvvmError")),
        ("numba.cuda.cudadrv.error", ("NvvmSupportError", "CudaRuntimeError", "NvrtcError")),
        ("numba.cuda.cudadrv.driver", ("CudaAPIError", "LinkerError")),
    ):
        try:
            module = __import__(module_name, fromlist=list(names))
        except ImportError:
            continue
        found += [getattr(module, n) for n in names if isinstance(getattr(module, n, None), type)]
    return tuple(found) or (RuntimeError,)


def match_many_cuda(
    inputs,
    centers,
    params,
    zncc,
    status,
    iterations,
    *,
    threads_per_block: int | None = None,
    max_registers: int | None = None,
    cpu_fallback: bool = True,
):
    """IC-GN for many POIs on the GPU; drop-in for :func:`..icgn.match_many` (same arguments).

    Parameters
    ----------
    inputs : icgn.MatchInputs
        The volumes and the matching settings, as for the CPU kernel.
    centers : ndarray (N, 3) int64
        POI positions ``(z, y, x)``; each subvolume ``center ± half`` lies inside the volume.
    params : ndarray (N, 3·nb) float64
        Initial guesses in, results out (modified in place), as in the CPU kernel.
    zncc, status, iterations : ndarray (N,)
        Outputs (float64, int64, int64), modified in place.
    threads_per_block : int, optional
        Power of two >= 16 (default 128 on a GPU, 32 in the simulator).
    max_registers : int, optional
        Register cap per thread for the kernel (a tuning knob; see ``benchmarks/bench_gpu.py``).
    cpu_fallback : bool
        When the GPU fails (driver, compiler, out of memory), warn and match on the CPU instead of
        raising. POIs whose warped subvolume leaves the volume are always matched on the CPU.

    The volumes stay on the GPU between calls while the same array objects are alive
    (:mod:`.memory`).
    """
    n = len(centers)
    if n == 0:
        return
    nb = inputs.nb
    if nb not in (4, 10):
        raise ValueError(f"nb must be 4 (first order) or 10 (second order), got {nb}")
    if params.shape != (n, 3 * nb):
        raise ValueError(f"params must have shape ({n}, {3 * nb}), got {params.shape}")
    guesses = params.copy()
    try:
        _launch(
            inputs,
            centers,
            params,
            zncc,
            status,
            iterations,
            threads_per_block=threads_per_block,
            max_registers=max_registers,
        )
    except _gpu_errors() as error:
        if not cpu_fallback:
            raise
        warnings.warn(
            f"the GPU failed ({type(error).__name__}: {error}); matching these {n} POIs on the "
            "CPU instead",
            RuntimeWarning,
            stacklevel=2,
        )
        params[:] = guesses
        cpu_icgn.match_many(inputs, centers, params, zncc, status, iterations)
        return
    redo = np.flatnonzero(status == FALLBACK)
    if redo.size:
        sub_params = np.ascontiguousarray(guesses[redo])
        sub_zncc = np.empty(redo.size)
        sub_status = np.empty(redo.size, np.int64)
        sub_its = np.empty(redo.size, np.int64)
        cpu_icgn.match_many(
            inputs, np.ascontiguousarray(centers[redo]), sub_params, sub_zncc, sub_status, sub_its
        )
        params[redo] = sub_params
        zncc[redo] = sub_zncc
        status[redo] = sub_status
        iterations[redo] = sub_its


def _launch(
    inputs,
    centers,
    params,
    zncc,
    status,
    iterations,
    *,
    threads_per_block=None,
    max_registers=None,
):
    (
        reference,
        gradient,
        coef_deformed,
        mask,
        use_mask,
        half,
        nb,
        max_iterations,
        tolerance,
        min_std,
        min_mask_fraction,
        max_update,
        noise_fraction,
        product_table,
        quad_axes,
    ) = inputs
    threads = int(threads_per_block or default_threads())
    kernel = build_kernel(int(nb), threads, max_registers)
    nz, ny, nx = reference.shape
    d_reference = to_device_cached(np.ascontiguousarray(reference, np.float32), flat=True)
    d_gradient = to_device_cached(np.ascontiguousarray(gradient, np.float32), flat=True)
    d_coef = to_device_cached(np.ascontiguousarray(coef_deformed, np.float32), flat=True)
    d_mask = to_device_cached(np.ascontiguousarray(mask, np.bool_), flat=True)
    d_product = to_device_cached(np.ascontiguousarray(product_table, np.int64))
    d_quad = to_device_cached(np.ascontiguousarray(quad_axes, np.int64))
    tables = _device_tables(int(nb))
    n = len(centers)
    for start in range(0, n, MAX_POIS_PER_LAUNCH):
        stop = min(start + MAX_POIS_PER_LAUNCH, n)
        d_centers = cuda.to_device(np.ascontiguousarray(centers[start:stop], np.int64))
        d_params = cuda.to_device(np.ascontiguousarray(params[start:stop], np.float64))
        d_zncc = cuda.device_array(stop - start, np.float64)
        d_status = cuda.device_array(stop - start, np.int64)
        d_its = cuda.device_array(stop - start, np.int64)
        kernel[stop - start, threads](
            d_reference,
            d_gradient,
            d_coef,
            d_mask,
            bool(use_mask),
            nz,
            ny,
            nx,
            d_centers,
            int(half),
            d_params,
            d_zncc,
            d_status,
            d_its,
            int(max_iterations),
            float(tolerance),
            float(min_std),
            float(min_mask_fraction),
            float(max_update),
            d_product,
            d_quad,
            float(noise_fraction),
            *tables,
        )
        params[start:stop] = d_params.copy_to_host()
        zncc[start:stop] = d_zncc.copy_to_host()
        status[start:stop] = d_status.copy_to_host()
        iterations[start:stop] = d_its.copy_to_host()
