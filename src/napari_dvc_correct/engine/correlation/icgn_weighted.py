"""IC-GN on weighted subvolumes: each voxel of a subvolume counts with a weight ``w(ξ) ≥ 0``.

A Gaussian window (:func:`.params.gaussian_window`) keeps more of the noise averaging of a box
than a smaller box while it follows a field that bends inside it with less bias: the weighted
least-squares fit of a shape function reads the field through an equivalent kernel whose far
voxels count little (Gaussian-weighted ZNSSD; Yuan, Pan et al. 2014 for 2-D DIC). Everything of :mod:`.icgn` is
weighted:

* means and norms: ``ḡ = Σ w g / W``, ``Δg² = Σ w (g − ḡ)²`` (``W = Σ w``), the same for ``f``;
  ``ZNCC = Σ w (g − ḡ)(f − f̄) / (Δg Δf)``;
* the Hessian ``H₁ = Σ w JᵀJ`` and the steepest-descent sums ``Σ w J``, ``Σ w J (g − ḡ)``,
  ``Σ w J f``; the step solves ``H₁⊥ Δp = −Σ w Jᵀ [(g − ḡ) − (Δg/Δf)(f − f̄)]`` with
  ``H₁⊥ = Σ w J⊥ J⊥ᵀ`` (:func:`_projected_hessian`: ``J`` less its weighted mean and its part
  along ``g − ḡ``), the Gauss-Newton Hessian of the zero-mean, normalised residual.
  :func:`.icgn.match_one` steps with ``H₁`` itself, which costs little on a uniform box (the
  mean gradient of many voxels is small) but under a narrow window made the second-order match
  walk at a rate of ~0.6 per iteration (7.4 iterations on the 100³ shear band's first
  correcting pass; 4.2 with the mean removed, 3.1 with ``H₁⊥``). The step's Hessian changes
  only the path: the solution (the right-hand side at zero) is the same.

With every weight 1 these are the sums of :func:`.icgn.match_one` and the same solution (to
rounding when both are converged tightly; the stop rules may end the two walks a stop's
tolerance apart; the unweighted kernels stay as they are, this module is used only where a
window is asked for).
``H₁`` comes from one moment pass (:func:`.icgn_weighted_moments.weighted_reference_moments`)
that also gives what the uncertainty reads with the weights squared (``H₂ = Σ w² JᵀJ`` and the
like); the deformed side reuses IC-GN's sampling and sums with ``w ∇G`` and ``w (g − ḡ)``.

The uncertainty is the weighted sandwich (:mod:`.icgn_weighted_uncertainty`). Units: voxels,
gray levels; axis order (z, y, x).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from ..fields.field import Status
from .icgn import STALL_FACTOR, STALL_ITERATIONS, _noise_converged, diverged, update_motion
from .icgn_pass import _affine_samples, _affine_sums, _quadratic_samples, _quadratic_sums
from .icgn_reference import gradient_source, translation_h_inverse
from .icgn_weighted_moments import weighted_reference_moments
from .icgn_weighted_uncertainty import weighted_sigma, weighted_sigma_at
from .params import gaussian_window  # noqa: F401  (the weights of CorrelationParams.window)
from .shape_function import (
    cholesky_solve,
    cholesky_solve_setup,
    compose_inverse,
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


def check_weights(weights, half: int) -> np.ndarray:
    """Validate subvolume weights; return them as a C-ordered float64 ``(edge³,)`` array.

    Raises
    ------
    ValueError
        Weights of another shape than ``(2·half + 1,)*3``, not finite, negative, or all zero.
    """
    edge = 2 * int(half) + 1
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (edge, edge, edge):
        raise ValueError(
            f"subvolume weights must have the subvolume's shape {(edge,) * 3}, got {weights.shape}"
        )
    if not np.all(np.isfinite(weights)):
        raise ValueError("subvolume weights must be finite (no NaN or infinity)")
    if np.any(weights < 0):
        raise ValueError("subvolume weights must be >= 0 (a negative weight has no meaning)")
    if not np.any(weights > 0):
        raise ValueError("subvolume weights are all zero: no voxel would count")
    return np.ascontiguousarray(weights.reshape(-1))


@njit(**KERNEL_OPTIONS)
def _projected_hessian(h1, sum_j, sum_jg, total, ss_g, m):
    """``H₁⊥ = H₁ − (Σ w J)(Σ w J)ᵀ / W − (Σ w J (g − ḡ))(Σ w J (g − ḡ))ᵀ / Δg²``
    ``= Σ w J⊥ J⊥ᵀ``: the Gauss-Newton Hessian of the weighted ZNSSD, whose Jacobian ``J⊥`` is
    ``J`` less its weighted mean and its part along ``g − ḡ`` (the gray offset and scale that
    ZNSSD ignores; the same ``H₁⊥`` as the uncertainty's, :mod:`.icgn_weighted_uncertainty`)."""
    out = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            out[a, b] = h1[a, b] - sum_j[a] * sum_j[b] / total - sum_jg[a] * sum_jg[b] / ss_g
    return out


@njit(**KERNEL_OPTIONS)
def weighted_terms(g, grad, xi, w, count, nb):
    """Weighted reference terms: ``(ḡ, Δg, ok, low, Σ w J, Σ w J (g − ḡ), W, second)`` with
    ``low`` the Cholesky factor of the step's Hessian :func:`_projected_hessian` (``ok`` False
    where it is not positive definite) and ``second`` what the uncertainty reads, from the same pass
    (:func:`.icgn_weighted_moments.weighted_reference_moments`): ``(H₁, H₂, Σ w² J,
    Σ w² J (g − ḡ), W₂, Σ w² (g − ḡ), Σ w² (g − ḡ)², Σ w |∇G|² / W)``."""
    (mean_g, ss_g, total, total2, w2d, w2dd, power, h1, h2, sum_j, sum_jg, s2j,
     s2jd) = weighted_reference_moments(g, grad, xi, w, count, nb)  # fmt: skip
    hessian = _projected_hessian(h1, sum_j, sum_jg, total, ss_g, 3 * nb)
    ok, low = cholesky_solve_setup(hessian, 3 * nb)
    second = (h1, h2, s2j, s2jd, total2, w2d, w2dd, power)
    return mean_g, np.sqrt(ss_g), ok, low, sum_j, sum_jg, total, second


@njit(**KERNEL_OPTIONS)
def _gather(reference, gradient, mask, use_mask, weights, cz, cy, cx, half, g, grad, xi, w):
    """Copy the subvolume's voxels of non-zero weight (inside the mask) into the buffers; returns
    ``(count, kept weight, whole weight)``."""
    source, oz, oy, ox = gradient_source(gradient, cz, cy, cx, half)
    count = 0
    kept = 0.0
    whole = 0.0
    n = 0
    for dz in range(-half, half + 1):
        for dy in range(-half, half + 1):
            for dx in range(-half, half + 1):
                weight = weights[n]
                n += 1
                whole += weight
                if weight == 0.0:
                    continue
                z = cz + dz
                y = cy + dy
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
                w[count] = weight
                kept += weight
                count += 1
    return count, kept, whole


@njit(**KERNEL_OPTIONS)
def _scaled_inputs(g, grad, w, count, mean_g, gw, gradw):
    """``w (g − ḡ)`` and ``w ∇G``: IC-GN's unweighted per-iteration sums of these are the
    weighted sums ``Σ w (g − ḡ) f`` and ``Σ w J f``."""
    for i in range(count):
        gw[i] = w[i] * (g[i] - mean_g)
        for k in range(3):
            gradw[i, k] = w[i] * np.float64(grad[i, k])


@njit(**KERNEL_OPTIONS)
def _noise_scale(low, m_par, nb, total, total2, h_inv):
    """The noise stop's inputs for weights: ``diag(H₁⁻¹)`` times ``W₂/W``, the effective voxel
    count ``W²/W₂`` (``W₂ = Σ w²``) and the factor ``√(W/W₂)`` on ``Δg``, so that
    :func:`.icgn._noise_converged` reads the weighted residual variance and about the weighted
    translation noise (``H₂ ≈ (W₂/W) H₁``; a stopping rule only, the uncertainty is the
    sandwich). All 1 and ``n`` for unit weights."""
    translation_h_inverse(low, m_par, nb, h_inv)
    factor = total2 / total
    for k in range(3):
        h_inv[k] *= factor
    return total * total / total2, np.sqrt(total / total2)


@njit(**KERNEL_OPTIONS)
def match_one_weighted(
    reference, gradient, coef_deformed, mask, use_mask, weights, cz, cy, cx, half, nb, p,
    max_iterations, tolerance, min_std, min_mask_fraction, max_update, product_table, quad_axes,
    noise_fraction, sigma_out, noise_power,
):  # fmt: skip
    """:func:`.icgn.match_one` on a weighted subvolume (``weights`` (edge³,) float64, ≥ 0, in
    (z, y, x) order; :func:`check_weights`).

    Returns ``(zncc, status, iterations)``; ``p`` (3·nb) is the guess in and the result out.
    ``min_mask_fraction`` is read on the weight inside the mask; ``min_std`` on the weighted gray
    standard deviation. ``sigma_out`` (4,): for a match that ends ``CONVERGED`` or
    ``MAX_ITERATIONS`` on its whole subvolume, the weighted sandwich uncertainty
    (:func:`.icgn_weighted_uncertainty.weighted_sigma`) in ``[:3]`` and 1 in ``[3]`` (2 where
    the subvolume's weighted gradient power is below ``noise_power``: measured with the
    sensitivity pass); else ``[3]`` stays 0.
    """
    m_par = 3 * nb
    edge = 2 * half + 1
    n_total = edge * edge * edge
    g = np.empty(n_total, np.float32)
    grad = np.empty((n_total, 3), np.float32)
    xi = np.empty((n_total, 3), np.float32)
    w = np.empty(n_total)
    count, kept, whole_weight = _gather(
        reference, gradient, mask, use_mask, weights, cz, cy, cx, half, g, grad, xi, w
    )
    if kept < min_mask_fraction * whole_weight or count < m_par + 1:
        return np.nan, _MASKED, 0
    mean_g, delta_g, ok, low, sum_j, sum_jg, total, second = weighted_terms(
        g, grad, xi, w, count, nb
    )
    if delta_g <= min_std * np.sqrt(total) or delta_g == 0.0:
        return np.nan, _LOW_TEXTURE, 0
    if not ok:
        return np.nan, _SINGULAR, 0
    gw = np.empty(count)
    gradw = np.empty((count, 3))
    _scaled_inputs(g, grad, w, count, mean_g, gw, gradw)
    start = np.empty(3)
    for k in range(3):
        start[k] = p[k * nb]
    h_inv = np.empty(3)
    n_eff, norm_scale = _noise_scale(low, m_par, nb, total, second[4], h_inv)
    previous = np.inf
    shortest = np.inf
    since_shortest = 0
    sum_jf = np.empty(m_par)
    rhs = np.empty(m_par)
    dp = np.empty(m_par)
    corner = np.empty(10)
    values = np.empty(count, np.float32)
    zncc = np.nan
    outside = np.zeros(count, np.bool_)
    whole = True
    for iteration in range(1, max_iterations + 1):
        if nb == 4:
            n_outside = _affine_samples(coef_deformed, xi, count, cz, cy, cx, p, outside, values)
        else:
            n_outside = _quadratic_samples(coef_deformed, xi, count, cz, cy, cx, p, outside, values)
        if n_outside > 0:
            whole = False
            kept_n = 0
            for i in range(count):
                if not outside[i]:
                    g[kept_n] = g[i]
                    grad[kept_n] = grad[i]
                    xi[kept_n] = xi[i]
                    w[kept_n] = w[i]
                    kept_n += 1
                outside[i] = False
            count = kept_n
            kept_weight = 0.0
            for i in range(count):
                kept_weight += w[i]
            if kept_weight < min_mask_fraction * whole_weight or count < m_par + 1:
                return zncc, _OUT_OF_BOUNDS, iteration
            mean_g, delta_g, ok, low, sum_j, sum_jg, total, second = weighted_terms(
                g, grad, xi, w, count, nb
            )
            if not ok or delta_g == 0.0:
                return zncc, _OUT_OF_BOUNDS, iteration
            _scaled_inputs(g, grad, w, count, mean_g, gw, gradw)
            n_eff, norm_scale = _noise_scale(low, m_par, nb, total, second[4], h_inv)
            previous = np.inf
            continue
        if nb == 4:
            _affine_sums(values, gw, gradw, xi, count, 0.0, sum_jf)
        else:
            _quadratic_sums(values, gw, gradw, xi, count, 0.0, sum_jf)
        sum_f = 0.0
        sum_ff = 0.0
        sum_gf = 0.0
        for i in range(count):
            f = np.float64(values[i])
            sum_f += w[i] * f
            sum_ff += w[i] * f * f
            sum_gf += gw[i] * f
        mean_f = sum_f / total
        ss_f = sum_ff - total * mean_f * mean_f
        if not (ss_f > 0.0):
            return np.nan, _DIVERGED, iteration
        delta_f = np.sqrt(ss_f)
        zncc = sum_gf / (delta_g * delta_f)
        ratio = delta_g / delta_f
        for r in range(m_par):
            rhs[r] = -(sum_jg[r] - ratio * (sum_jf[r] - mean_f * sum_j[r]))
        cholesky_solve(low, rhs, m_par, dp)
        m_current = warp_matrix(p, nb, product_table, quad_axes)
        m_update = warp_matrix(dp, nb, product_table, quad_axes)
        parameters_from_matrix(compose_inverse(m_current, m_update, nb), nb, p)
        if diverged(p, m_par, nb, start, max_update):
            return zncc, _DIVERGED, iteration
        motion = update_motion(dp, nb, half, corner)
        stop = motion < tolerance
        if not stop and noise_fraction > 0.0:
            stop, previous = _noise_converged(
                dp, nb, h_inv, delta_g * norm_scale, zncc, n_eff, previous, noise_fraction
            )
        if stop:
            if sigma_out is not None and whole:
                weighted_sigma(
                    coef_deformed, g, grad, xi, w, count, nb, mean_g, delta_g, second, sum_j,
                    sum_jg, total, zncc, p, cz, cy, cx, noise_power, sigma_out,
                )  # fmt: skip
            return zncc, _CONVERGED, iteration
        if motion < STALL_FACTOR * shortest:
            shortest = motion
            since_shortest = 0
        elif not (previous < 1.0):
            since_shortest += 1
            if since_shortest >= STALL_ITERATIONS:
                return zncc, _DIVERGED, iteration
    if sigma_out is not None and whole:
        weighted_sigma(
            coef_deformed, g, grad, xi, w, count, nb, mean_g, delta_g, second, sum_j, sum_jg,
            total, zncc, p, cz, cy, cx, noise_power, sigma_out,
        )  # fmt: skip
    return zncc, _MAX_ITERATIONS, max_iterations


@njit(parallel=True, **KERNEL_OPTIONS)
def match_many_weighted(inputs, weights, centers, params, zncc, status, iterations, sigma,
                        noise_power):  # fmt: skip
    """:func:`.icgn.match_many_sigma` on weighted subvolumes (``weights`` (edge³,) float64).

    ``inputs`` is :class:`.icgn.MatchInputs`; ``sigma`` (N, 4) float64 out as there (the
    weighted sandwich uncertainty, :func:`match_one_weighted`)."""
    for i in prange(centers.shape[0]):
        p = params[i].copy()
        out = np.zeros(4)
        value, code, its = match_one_weighted(
            inputs.reference, inputs.gradient, inputs.coef_deformed, inputs.mask, inputs.use_mask,
            weights, centers[i, 0], centers[i, 1], centers[i, 2], inputs.half, inputs.nb, p,
            inputs.max_iterations, inputs.tolerance, inputs.min_std, inputs.min_mask_fraction,
            inputs.max_update, inputs.product_table, inputs.quad_axes, inputs.noise_fraction, out,
            noise_power,
        )  # fmt: skip
        params[i, :] = p
        zncc[i] = value
        status[i] = code
        iterations[i] = its
        sigma[i, :] = out


@njit(parallel=True, **KERNEL_OPTIONS)
def weighted_statistics(
    reference, gradient, coef_deformed, mask, use_mask, weights, centers, half, nb, params, zncc,
    sensitivity, variance, gradient_power, sigma,
):  # fmt: skip
    """:func:`.icgn_uncertainty.subvolume_statistics` on weighted subvolumes (same arguments,
    and ``weights`` (edge³,) float64): the weighted gray variance ``Δg² / W``, the weighted
    gradient power ``Σ w |∇G|² / W`` and the weighted sandwich uncertainty
    (:func:`.icgn_weighted_uncertainty.weighted_sigma_at`)."""
    m_par = 3 * nb
    edge = 2 * half + 1
    n_total = edge * edge * edge
    for n in prange(centers.shape[0]):
        g = np.empty(n_total, np.float32)
        grad = np.empty((n_total, 3), np.float32)
        xi = np.empty((n_total, 3), np.float32)
        w = np.empty(n_total)
        cz, cy, cx = centers[n, 0], centers[n, 1], centers[n, 2]
        count, _, _ = _gather(
            reference, gradient, mask, use_mask, weights, cz, cy, cx, half, g, grad, xi, w
        )
        for k in range(3):
            sigma[n, k] = np.nan
        variance[n] = np.nan
        gradient_power[n] = np.nan
        if count < m_par + 3:
            continue
        mean_g, delta_g, ok, low, sum_j, sum_jg, total, second = weighted_terms(
            g, grad, xi, w, count, nb
        )
        variance[n] = delta_g * delta_g / total
        gradient_power[n] = second[7]
        if not ok or delta_g == 0.0 or not np.isfinite(zncc[n]):
            continue
        weighted_sigma_at(
            coef_deformed, g, grad, xi, w, count, nb, mean_g, delta_g, second, sum_j, sum_jg, total,
            zncc[n], params[n], cz, cy, cx, sensitivity[n], sigma[n],
        )  # fmt: skip


@njit(parallel=True, **KERNEL_OPTIONS)
def weighted_moments(reference, gradient, mask, use_mask, weights, centers, half, nb, variance,
                     power):  # fmt: skip
    """:func:`.icgn_uncertainty.subvolume_moments` on weighted subvolumes: ``Δg² / W`` and
    ``Σ w |∇G|² / W`` (NaN where fewer than ``3·nb + 3`` voxels count).

    Read from the volumes where they lie (the voxels of non-zero weight inside the mask, in
    :func:`_gather`'s order and with the same sums, so the same bits), without copying each
    subvolume first: the judge's moments of every node of a correcting pass."""
    m_par = 3 * nb
    for n in prange(centers.shape[0]):
        cz, cy, cx = centers[n, 0], centers[n, 1], centers[n, 2]
        source, oz, oy, ox = gradient_source(gradient, cz, cy, cx, half)
        count = 0
        total = 0.0
        mean_g = 0.0
        sum_power = 0.0
        i = 0
        for z in range(cz - half, cz + half + 1):
            for y in range(cy - half, cy + half + 1):
                for x in range(cx - half, cx + half + 1):
                    weight = weights[i]
                    i += 1
                    if weight == 0.0 or (use_mask and not mask[z, y, x]):
                        continue
                    total += weight  # float32 values as the gathered copies hold them
                    mean_g += weight * np.float32(reference[z, y, x])
                    for k in range(3):
                        gk = np.float64(np.float32(source[k, z - oz, y - oy, x - ox]))
                        sum_power += weight * gk**2
                    count += 1
        variance[n] = np.nan
        power[n] = np.nan
        if count < m_par + 3:
            continue
        mean_g /= total
        ss_g = 0.0
        i = 0
        for z in range(cz - half, cz + half + 1):
            for y in range(cy - half, cy + half + 1):
                for x in range(cx - half, cx + half + 1):
                    weight = weights[i]
                    i += 1
                    if weight == 0.0 or (use_mask and not mask[z, y, x]):
                        continue
                    ss_g += weight * (np.float32(reference[z, y, x]) - mean_g) ** 2
        variance[n] = ss_g / total
        power[n] = sum_power / total
