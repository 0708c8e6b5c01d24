"""Subvolume matching by the inverse-compositional Gauss–Newton (IC-GN) algorithm.

For a POI at reference position ``c`` and local coordinates ``ξ`` in the subvolume ``[-M, M]³``,
the shape function maps ``ξ`` to the deformed position ``c + W(ξ; p)`` with

``W_k(ξ; p) = ξ_k + Σ_j p[k, j] · b_j(ξ)``,

where ``b(ξ)`` are monomials of the local coordinates: ``(1, ξz, ξy, ξx)`` for the first-order
(affine, 12 parameters) shape function and additionally ``(ξz², ξy², ξx², ξzξy, ξyξx, ξzξx)`` for the
second-order one (30 parameters). So ``p[k, 0]`` is the displacement ``u_k`` at the POI and
``p[k, 1 + l] = ∂u_k/∂X_l``.

The criterion is ZNSSD (reported as ZNCC = 1 − ZNSSD/2). IC-GN precomputes the reference-side
steepest-descent images ``J = ∇G · ∂W/∂p`` and the Hessian ``H = Σ JᵀJ`` once per POI; each
iteration samples the deformed volume at the current warp (tricubic B-spline), solves
``H Δp = -Σ Jᵀ [(G − Ḡ) − (ΔG/ΔF)(F − F̄)]`` and updates ``W(p) ← W(p) ∘ W(Δp)⁻¹``. Warps are
composed and inverted in the matrix representation that maps the monomial vector ``b(ξ)`` to
``b(W(ξ))`` (exact for the affine warp, truncated at degree 2 for the quadratic one).

Iterations stop when the incremental warp moves every subvolume corner by less than the tolerance.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from ..fields.field import Status
from .icgn_pass import sample_pass as _sample_pass
from .icgn_reference import gradient_source, reference_terms, translation_h_inverse
from .icgn_uncertainty import match_sigma, sandwich_sigma
from .shape_function import (
    PRODUCT_TABLE,
    QUAD_AXES,
    cholesky_solve,
    compose_inverse,
    monomials,
    parameters_from_matrix,
    warp_matrix,
)

_CONVERGED = int(Status.CONVERGED)
_DIVERGED = int(Status.DIVERGED)
_LOW_TEXTURE = int(Status.LOW_TEXTURE)
_MASKED = int(Status.MASKED)
_MAX_ITERATIONS = int(Status.MAX_ITERATIONS)
_OUT_OF_BOUNDS = int(Status.OUT_OF_BOUNDS)
_SINGULAR = int(Status.SINGULAR)


#: The noise stop applies to matches whose ZNCC is below this (residual variance above 0.1 % of
#: the subvolume's): noise-free scans converge to ``tolerance`` as before.
NOISE_STOP_MAX_ZNCC = 0.999


@njit(inline="always", **KERNEL_OPTIONS)
def update_motion(dp, nb, half, corner):
    """The largest displacement (voxels) the update ``dp`` gives a corner of the subvolume of
    half size ``half``: IC-GN's convergence measure. ``corner`` is scratch of ``nb`` values."""
    largest = 0.0
    for sz in (-half, half):
        for sy in (-half, half):
            for sx in (-half, half):
                monomials(float(sz), float(sy), float(sx), nb, corner)
                norm2 = 0.0
                for k in range(3):
                    moved = 0.0
                    for j in range(nb):
                        moved += dp[k * nb + j] * corner[j]
                    norm2 += moved * moved
                largest = max(largest, norm2)
    return np.sqrt(largest)


@njit(inline="always", **KERNEL_OPTIONS)
def diverged(p, m_par, nb, start, max_update):
    """True where a parameter of ``p`` is not finite or its translation moved more than
    ``max_update`` voxels from ``start`` along an axis."""
    finite = True
    for r in range(m_par):
        if not np.isfinite(p[r]):
            finite = False
    moved_far = False
    for k in range(3):
        if abs(p[k * nb] - start[k]) > max_update:
            moved_far = True
    return not finite or moved_far


@njit(**KERNEL_OPTIONS)
def _noise_converged(dp, nb, h_inv, delta_g, zncc, count, previous, noise_fraction):
    """Noise stop: True when the remaining translation error is below ``noise_fraction`` of its noise.

    With noise on the reference, ``H = Σ J_GᵀJ_G`` holds the gradient of that noise, which the
    deformed scan does not share, so IC-GN steps are too short and converge linearly: each step is
    ``ρ`` times the last and ``ρ / (1 − ρ)`` times the step is still to go. With
    ``d = max_k |Δu_k| / σ_k`` (``σ_k² = σ_r² (H⁻¹)_kk``, the residual variance per voxel
    ``σ_r² = 2 Σ(g − ḡ)² (1 − ZNCC) / (n − 3·nb − 2)``) and the true noise uncertainty about
    ``σ_k / (1 − ρ)``, the remaining error is below ``noise_fraction`` of it when ``d · ρ`` is:
    the rule is ``d < 1`` and ``d · min(ρ, 1) < noise_fraction``, ``ρ = d / d_previous``.
    The rule applies only where ``ZNCC < NOISE_STOP_MAX_ZNCC``: on noise-free scans the usual
    tolerance decides, exactly as without it.

    Returns ``(stop, d)``.
    """
    if not (zncc < NOISE_STOP_MAX_ZNCC):
        return False, np.inf
    m_par = 3 * nb
    residual = 2.0 * delta_g * delta_g * max(1.0 - zncc, 0.0) / max(count - m_par - 2, 1)
    d = 0.0
    for k in range(3):
        scale = np.sqrt(residual * h_inv[k])
        if not (scale > 0.0):
            return False, np.inf
        d = max(d, abs(dp[k * nb]) / scale)
    if d < 1.0 and np.isfinite(previous):
        rho = min(d / previous, 1.0) if previous > 0.0 else 0.0
        if d * rho < noise_fraction:
            return True, d
    return False, d


#: A match whose incremental warp has not become :data:`STALL_FACTOR` times shorter than its
#: shortest so far in this many iterations with steps above its noise level cannot converge (it
#: oscillates, wanders or grows): it stops as ``DIVERGED`` instead of running to
#: ``max_iterations``. Steady convergence at a step ratio below
#: ``STALL_FACTOR ** (1 / STALL_ITERATIONS)`` (0.987) never stalls; steps below the noise level
#: (``d < 1`` in :func:`_noise_converged`) are left to the noise stop.
STALL_ITERATIONS = 8
STALL_FACTOR = 0.9


@njit(**KERNEL_OPTIONS)
def match_one(
    reference,
    gradient,
    coef_deformed,
    mask,
    use_mask,
    cz,
    cy,
    cx,
    half,
    nb,
    p,
    max_iterations,
    tolerance,
    min_std,
    min_mask_fraction,
    max_update,
    product_table,
    quad_axes,
    noise_fraction=0.0,
    sigma_out=None,
    noise_power=0.0,
):
    """Match one subvolume by IC-GN; ``p`` (3·nb) is the initial guess in and the result out.

    Returns ``(zncc, status, iterations)``. Kernels assume valid input: the reference subvolume
    lies inside the reference volume. ``noise_fraction`` > 0 adds the noise stop of
    :func:`_noise_converged`. ``sigma_out`` (4,) float64, optional: for a match that ends
    ``CONVERGED`` or ``MAX_ITERATIONS`` on every voxel of its subvolume, ``sigma_out[:3]`` gets
    the noise-free-``H`` uncertainty :func:`.icgn_uncertainty.subvolume_statistics` would
    compute at this match (from the reference terms held here) and ``sigma_out[3]`` 1; else
    ``sigma_out[3]`` stays 0. Where the subvolume's gradient power (``Σ|∇G|²/n``, from ``H``)
    is below ``noise_power`` (gray²/voxel²; 0: nowhere), the POI is expected to be noisy and
    ``sigma_out[:3]`` gets instead what that kernel computes with the sensitivity pass
    (:func:`.icgn_uncertainty.sandwich_sigma` at the final ``p``), and ``sigma_out[3]`` 2.
    """
    m_par = 3 * nb
    edge = 2 * half + 1
    n_total = edge * edge * edge
    # the subvolume in float32, as G and ∇G are stored (exact; every sum is float64): half the
    # memory traffic of float64 copies in each sampling pass
    g = np.empty(n_total, np.float32)
    grad = np.empty((n_total, 3), np.float32)
    xi = np.empty((n_total, 3), np.float32)
    source, oz, oy, ox = gradient_source(gradient, cz, cy, cx, half)
    count = 0
    for dz in range(-half, half + 1):
        z = cz + dz
        for dy in range(-half, half + 1):
            y = cy + dy
            for dx in range(-half, half + 1):
                x = cx + dx
                if use_mask and not mask[z, y, x]:
                    continue
                g[count] = reference[z, y, x]
                grad[count, 0] = source[0, z - oz, y - oy, x - ox]
                grad[count, 1] = source[1, z - oz, y - oy, x - ox]
                grad[count, 2] = source[2, z - oz, y - oy, x - ox]
                xi[count, 0] = dz
                xi[count, 1] = dy
                xi[count, 2] = dx
                count += 1
    if count < min_mask_fraction * n_total or count < m_par + 1:
        return np.nan, _MASKED, 0

    mean_g, delta_g, ok, low, sum_j, sum_jg = reference_terms(g, grad, xi, count, nb)
    if delta_g <= min_std * np.sqrt(count) or delta_g == 0.0:
        return np.nan, _LOW_TEXTURE, 0
    if not ok:
        return np.nan, _SINGULAR, 0

    start = np.empty(3)
    for k in range(3):
        start[k] = p[k * nb]
    h_inv = np.empty(3)
    translation_h_inverse(low, m_par, nb, h_inv)
    previous = np.inf
    shortest = np.inf
    since_shortest = 0
    sum_jf = np.empty(m_par)
    rhs = np.empty(m_par)
    dp = np.empty(m_par)
    corner = np.empty(10)
    zncc = np.nan
    outside = np.zeros(count, np.bool_)
    whole = True  # every voxel of the subvolume still in the sums
    for iteration in range(1, max_iterations + 1):
        sum_f, sum_ff, sum_gf, n_outside = _sample_pass(
            coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, p, nb, outside, sum_jf
        )
        if n_outside > 0:
            # Part of the deformed subvolume left the volume: drop those voxels, rebuild the
            # reference-side terms on the rest and iterate again from the same warp.
            whole = False
            kept = 0
            for i in range(count):
                if not outside[i]:
                    g[kept] = g[i]
                    grad[kept, 0] = grad[i, 0]
                    grad[kept, 1] = grad[i, 1]
                    grad[kept, 2] = grad[i, 2]
                    xi[kept, 0] = xi[i, 0]
                    xi[kept, 1] = xi[i, 1]
                    xi[kept, 2] = xi[i, 2]
                    kept += 1
                outside[i] = False
            count = kept
            if count < min_mask_fraction * n_total or count < m_par + 1:
                return zncc, _OUT_OF_BOUNDS, iteration
            mean_g, delta_g, ok, low, sum_j, sum_jg = reference_terms(g, grad, xi, count, nb)
            if not ok or delta_g == 0.0:
                return zncc, _OUT_OF_BOUNDS, iteration
            translation_h_inverse(low, m_par, nb, h_inv)
            previous = np.inf
            continue
        mean_f = sum_f / count
        ss_f = sum_ff - count * mean_f * mean_f
        if not (ss_f > 0.0):
            return np.nan, _DIVERGED, iteration
        delta_f = np.sqrt(ss_f)
        zncc = sum_gf / (delta_g * delta_f)
        ratio = delta_g / delta_f
        for r in range(m_par):
            rhs[r] = -(sum_jg[r] - ratio * (sum_jf[r] - mean_f * sum_j[r]))
        cholesky_solve(low, rhs, m_par, dp)

        # W(p) <- W(p) o W(dp)^-1
        m_current = warp_matrix(p, nb, product_table, quad_axes)
        m_update = warp_matrix(dp, nb, product_table, quad_axes)
        m_new = compose_inverse(m_current, m_update, nb)
        parameters_from_matrix(m_new, nb, p)

        if diverged(p, m_par, nb, start, max_update):
            return zncc, _DIVERGED, iteration
        motion = update_motion(dp, nb, half, corner)
        if motion < tolerance:
            if sigma_out is not None:
                _sigma_into(
                    sigma_out, whole, low, sum_j, sum_jg, delta_g, count, nb, zncc, ok,
                    noise_power, coef_deformed, g, grad, xi, mean_g, cz, cy, cx, p,
                )  # fmt: skip
            return zncc, _CONVERGED, iteration
        if noise_fraction > 0.0:
            stop, previous = _noise_converged(
                dp, nb, h_inv, delta_g, zncc, count, previous, noise_fraction
            )
            if stop:
                if sigma_out is not None:
                    _sigma_into(
                        sigma_out, whole, low, sum_j, sum_jg, delta_g, count, nb, zncc, ok,
                        noise_power, coef_deformed, g, grad, xi, mean_g, cz, cy, cx, p,
                    )  # fmt: skip
                return zncc, _CONVERGED, iteration
        if motion < STALL_FACTOR * shortest:
            shortest = motion
            since_shortest = 0
        elif not (previous < 1.0):  # above the noise level (below it the noise stop decides)
            since_shortest += 1
            if since_shortest >= STALL_ITERATIONS:
                return zncc, _DIVERGED, iteration
    if sigma_out is not None:
        _sigma_into(
            sigma_out, whole, low, sum_j, sum_jg, delta_g, count, nb, zncc, ok,
            noise_power, coef_deformed, g, grad, xi, mean_g, cz, cy, cx, p,
        )  # fmt: skip
    return zncc, _MAX_ITERATIONS, max_iterations


@njit(**KERNEL_OPTIONS)
def _sigma_into(
    sigma_out, whole, low, sum_j, sum_jg, delta_g, count, nb, zncc, ok,
    noise_power, coef_deformed, g, grad, xi, mean_g, cz, cy, cx, p,
):  # fmt: skip
    if not whole:  # voxels were dropped: not the subvolume the statistics would gather
        return
    if noise_power > 0.0:
        power = 0.0  # Σ|∇G|² from H's translation diagonal, as the statistics kernel
        for k in range(3):
            for j in range(k * nb + 1):
                power += low[k * nb, j] * low[k * nb, j]
        if power / count < noise_power:
            for k in range(3):
                sigma_out[k] = np.nan
            if count >= 3 * nb + 3 and ok and delta_g != 0.0 and np.isfinite(zncc):
                sandwich_sigma(
                    coef_deformed, g, grad, xi, count, mean_g, delta_g, low, sum_j, sum_jg,
                    cz, cy, cx, p, nb, zncc, sigma_out[:3],
                )  # fmt: skip
            sigma_out[3] = 2.0
            return
    match_sigma(low, sum_j, sum_jg, delta_g, count, nb, zncc, ok, sigma_out[:3])
    sigma_out[3] = 1.0


class MatchInputs(NamedTuple):
    """Everything the IC-GN kernels need besides the POIs and their outputs.

    One bundle for :func:`match_many` and :func:`.cuda.match_many_cuda` (built by
    ``correlate.PyramidLevel.inputs``).

    Attributes
    ----------
    reference : ndarray (nz, ny, nx) float32
        Reference gray values G.
    gradient : ndarray (3, nz, ny, nx) float32
        Gradient of G's B-spline interpolant, ``(d/dz, d/dy, d/dx)``, gray levels per voxel; or
        (CPU kernels) G's B-spline coefficients (1, nz, ny, nx), from which each subvolume's
        gradient is computed (:func:`.icgn_reference.gradient_source`).
    coef_deformed : ndarray (nz, ny, nx) float32
        B-spline coefficients of F.
    mask : ndarray of bool (nz, ny, nx), or any bool array when ``use_mask`` is False
    use_mask : bool
    half : int
        Subvolume half size M (edge 2M + 1), voxels.
    nb : {4, 10}
        Monomials of the shape function (first / second order).
    max_iterations : int
    tolerance : float
        Convergence threshold (voxels) on the largest corner motion of the incremental warp.
    min_std : float
        Subvolumes whose gray standard deviation is at most this are ``LOW_TEXTURE``.
    min_mask_fraction : float
    max_update : float
        Largest translation change (voxels) from the guess before ``DIVERGED``.
    noise_fraction : float
        The noise stop (:func:`_noise_converged`); 0 turns it off.
    product_table, quad_axes : ndarray int64
        :data:`PRODUCT_TABLE`, :data:`QUAD_AXES`.
    """

    reference: np.ndarray
    gradient: np.ndarray
    coef_deformed: np.ndarray
    mask: np.ndarray
    use_mask: bool
    half: int
    nb: int
    max_iterations: int
    tolerance: float
    min_std: float
    min_mask_fraction: float
    max_update: float
    noise_fraction: float = 0.0
    product_table: np.ndarray = PRODUCT_TABLE
    quad_axes: np.ndarray = QUAD_AXES


@njit(parallel=True, **KERNEL_OPTIONS)
def match_many(inputs, centers, params, zncc, status, iterations):
    """IC-GN for many POIs in parallel (:class:`MatchInputs`).

    ``centers`` (N, 3) int64 POI positions (each subvolume inside the volume); ``params``
    (N, 3·nb) holds guesses in, results out; ``zncc`` (N,) float64, ``status`` and
    ``iterations`` (N,) int64 are outputs.
    """
    for i in prange(centers.shape[0]):
        p = params[i].copy()
        value, code, its = match_one(
            inputs.reference,
            inputs.gradient,
            inputs.coef_deformed,
            inputs.mask,
            inputs.use_mask,
            centers[i, 0],
            centers[i, 1],
            centers[i, 2],
            inputs.half,
            inputs.nb,
            p,
            inputs.max_iterations,
            inputs.tolerance,
            inputs.min_std,
            inputs.min_mask_fraction,
            inputs.max_update,
            inputs.product_table,
            inputs.quad_axes,
            inputs.noise_fraction,
        )
        params[i, :] = p
        zncc[i] = value
        status[i] = code
        iterations[i] = its


@njit(parallel=True, **KERNEL_OPTIONS)
def match_many_sigma(inputs, centers, params, zncc, status, iterations, sigma, noise_power):
    """:func:`match_many` that also measures each good match's uncertainty from its own
    reference terms (``match_one``'s ``sigma_out``): ``sigma`` (N, 4) float64 out,
    ``sigma[:, :3]`` the uncertainty (voxels) as :func:`.icgn_uncertainty.subvolume_statistics`
    gives it, without the sensitivity pass where ``sigma[:, 3]`` is 1 and with it where 2 (the
    POIs whose gradient power is below ``noise_power``, gray²/voxel²; 0 for none)."""
    for i in prange(centers.shape[0]):
        p = params[i].copy()
        out = np.zeros(4)
        value, code, its = match_one(
            inputs.reference,
            inputs.gradient,
            inputs.coef_deformed,
            inputs.mask,
            inputs.use_mask,
            centers[i, 0],
            centers[i, 1],
            centers[i, 2],
            inputs.half,
            inputs.nb,
            p,
            inputs.max_iterations,
            inputs.tolerance,
            inputs.min_std,
            inputs.min_mask_fraction,
            inputs.max_update,
            inputs.product_table,
            inputs.quad_axes,
            inputs.noise_fraction,
            out,
            noise_power,
        )
        params[i, :] = p
        zncc[i] = value
        status[i] = code
        iterations[i] = its
        sigma[i, :] = out
