"""Per-POI uncertainty of a match from the images alone: the sandwich estimate.

After IC-GN has converged, one more pass over each subvolume gives the gray variance of the
reference subvolume and the standard deviation of the three translations, in voxels, from the
sensitivity of the match to the imaging noise (see :func:`subvolume_statistics`; its per-voxel
sums are in :mod:`.uncertainty_sums`). The noise stage needs only the variance and the gradient
power, from plain sums (:func:`subvolume_moments`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from .icgn_reference import gradient_source, reference_terms, translation_h_inverse
from .shape_function import cholesky_solve_setup, inverse_rows
from .uncertainty_sums import affine_sensitivity_sums, quadratic_sensitivity_sums, sensitivity_sums


@njit(parallel=True, **KERNEL_OPTIONS)
def subvolume_moments(reference, gradient, mask, use_mask, centers, half, nb, variance, power):
    """Gray variance and gradient power of each POI's reference subvolume, from plain sums.

    The noise stage's part of :func:`subvolume_statistics` (the same numbers, without ``H``):
    ``variance = Σ(g − ḡ)² / n`` and ``power = Σ |∇G|² / n`` over the ``n`` unmasked voxels,
    summed in float64 from the float32 volumes as there.

    Parameters
    ----------
    reference, gradient, mask, use_mask, centers, half, nb
        As in :func:`subvolume_statistics` (``nb`` only sets the ``3·nb + 3`` voxels needed).
    variance : ndarray (N,) float64, out
        Gray variance (gray levels²); NaN where fewer than ``3·nb + 3`` voxels are usable.
    power : ndarray (N,) float64, out
        Mean of ``|∇G|²`` (gray²/voxel²); NaN where the variance is.
    """
    m_par = 3 * nb
    for n in prange(centers.shape[0]):
        cz = centers[n, 0]
        cy = centers[n, 1]
        cx = centers[n, 2]
        source, oz, oy, ox = gradient_source(gradient, cz, cy, cx, half)
        count = 0
        sum_g = 0.0
        sum_power = 0.0
        for z in range(cz - half, cz + half + 1):
            for y in range(cy - half, cy + half + 1):
                for x in range(cx - half, cx + half + 1):
                    if use_mask and not mask[z, y, x]:
                        continue
                    sum_g += np.float64(reference[z, y, x])
                    for k in range(3):
                        gk = np.float64(source[k, z - oz, y - oy, x - ox])
                        sum_power += gk * gk
                    count += 1
        variance[n] = np.nan
        power[n] = np.nan
        if count < m_par + 3:
            continue
        mean_g = sum_g / count
        ss_g = 0.0
        for z in range(cz - half, cz + half + 1):
            for y in range(cy - half, cy + half + 1):
                for x in range(cx - half, cx + half + 1):
                    if use_mask and not mask[z, y, x]:
                        continue
                    d = np.float64(reference[z, y, x]) - mean_g
                    ss_g += d * d
        delta_g = np.sqrt(ss_g)  # as reference_terms: Σ(g − ḡ)² through its square root
        variance[n] = delta_g * delta_g / count
        power[n] = sum_power / count


@njit(**KERNEL_OPTIONS)
def perpendicular_hessian(low, sum_j, sum_jg, count, ss_g, m_par):
    """``H⊥ = H − ΣJ ΣJᵀ/n − ΣJg ΣJgᵀ/Σ(g − ḡ)²`` from the Cholesky factor ``low`` of ``H``
    (:func:`.icgn_reference.reference_terms`); see :func:`subvolume_statistics`."""
    h_perp = np.empty((m_par, m_par))
    for r in range(m_par):
        for c in range(r + 1):
            v = 0.0
            for k in range(c + 1):
                v += low[r, k] * low[c, k]
            v -= sum_j[r] * sum_j[c] / count + sum_jg[r] * sum_jg[c] / ss_g
            h_perp[r, c] = v
            h_perp[c, r] = v
    return h_perp


@njit(**KERNEL_OPTIONS)
def residual_variance(ss_g, zncc, count, m_par):
    """``σ_r² = 2 Σ(g − ḡ)² (1 − ZNCC) / (n − 3·nb − 2)``, per voxel (gray levels²)."""
    return 2.0 * ss_g * max(1.0 - zncc, 0.0) / max(count - m_par - 2, 1)


@njit(**KERNEL_OPTIONS)
def plain_sigma(h_perp, residual, m_par, nb, out):
    """``out[k] = sqrt(σ_r² (H⊥⁻¹)_kk)`` for the three translations (``inf`` where ``H⊥`` is
    singular): the estimate where the reference's noise adds little to ``H``."""
    ok_perp, low_perp = cholesky_solve_setup(h_perp, m_par)
    h_inv = np.empty(3)
    if ok_perp:
        translation_h_inverse(low_perp, m_par, nb, h_inv)
    for k in range(3):
        out[k] = np.sqrt(residual * h_inv[k]) if ok_perp else np.inf


@njit(**KERNEL_OPTIONS)
def match_sigma(low, sum_j, sum_jg, delta_g, count, nb, zncc, ok, out):
    """:func:`subvolume_statistics`' sigma of a POI not measured with the sensitivity pass,
    from the reference terms IC-GN already holds (the same ``g``, ``∇G`` and voxels): ``out``
    (3,) gets what that kernel would write, NaN where it writes NaN."""
    m_par = 3 * nb
    for k in range(3):
        out[k] = np.nan
    if count < m_par + 3 or not ok or delta_g == 0.0 or not np.isfinite(zncc):
        return
    ss_g = delta_g * delta_g
    h_perp = perpendicular_hessian(low, sum_j, sum_jg, count, ss_g, m_par)
    plain_sigma(h_perp, residual_variance(ss_g, zncc, count, m_par), m_par, nb, out)


@njit(parallel=True, **KERNEL_OPTIONS)
def subvolume_statistics(
    reference,
    gradient,
    coef_deformed,
    mask,
    use_mask,
    centers,
    half,
    nb,
    params,
    zncc,
    sensitivity,
    variance,
    gradient_power,
    sigma,
):
    """Gray variance of each POI's reference subvolume and the uncertainty of its translation.

    The match solves ``Φ(p) = Σ J_Gᵀ r(p) = 0`` with ``r = (g − ḡ) − (Δg/Δf)(f(W(ξ; p)) − f̄)``
    and ``J_G = ∇G · ∂W/∂p``. Noise moves the solution by ``δp = −A⁻¹ Φ`` with the sensitivity
    ``A = (Δg/Δf) Σ J_G⊥ᵀ (∇F(W) ⊗ b)``, so

    ``Cov p = A⁻¹ (Cov Φ) A⁻ᵀ``,   ``Cov Φ = σ_r² (H⊥ + sym A) / 2``,
    ``σ_r² = 2 Σ(g − ḡ)² (1 − ZNCC) / (n − 3·nb − 2)``.

    ``Cov Φ``: ``J_G`` holds the gradient of the reference's noise ``n_G`` and ``r`` holds
    ``n_G`` itself; their pairings at neighbouring voxels cancel ``σ_G²`` of the ``σ_r²`` that
    multiplies the noise part ``H − A`` of ``H``: ``Cov Φ = σ_r² H − σ_G² (H − A)``. With the
    same noise on both scans (``σ_G² = σ_r² / 2``) that is ``σ_r² (H + A) / 2``; with noise on
    the deformed scan only, ``A = H`` and it is ``σ_r² H``.

    ``⊥`` marks steepest-descent images made orthogonal to the gray offset and scale that ZNSSD
    ignores (``H⊥ = H − ΣJ ΣJᵀ/n − ΣJg ΣJgᵀ/Σ(g − ḡ)²``). ``A`` is taken with the gradient of
    the *deformed* volume at the warped voxels, whose noise is independent of the reference's: on
    noisy scans ``H = Σ J_GᵀJ_G`` is inflated by the gradient of the reference's noise while ``A``
    is not, and ``σ_r² H⁻¹`` alone would be several times too small (measured: 5× at 6 % noise).

    Where the reference's noise adds little to ``H`` (``sensitivity`` False), ``A = H⊥`` and the
    estimate is ``σ_r² (H⊥⁻¹)_kk``, without the pass over the deformed volume.

    Parameters
    ----------
    reference, gradient, coef_deformed, mask, use_mask, centers, half, nb
        As in :func:`match_many` (``centers`` (N, 3) int64, subvolumes inside the volume).
    params : ndarray (N, 3·nb) float64
        Final shape-function parameters of each POI.
    zncc : ndarray (N,) float64
        ZNCC of each POI's final match; NaN where none (then ``sigma`` is NaN).
    sensitivity : ndarray (N,) bool
        Where to measure ``A`` from the deformed volume (noisy scans).
    variance : ndarray (N,) float64, out
        Gray variance of the subvolume (masked voxels left out); NaN where fewer than
        ``3·nb + 3`` voxels are usable.
    gradient_power : ndarray (N,) float64, out
        Mean of ``|∇G|²`` over the subvolume (gray²/voxel²).
    sigma : ndarray (N, 3) float64, out
        Standard deviation of ``(uz, uy, ux)`` in voxels; ``inf`` where ``A`` is singular.
    """
    m_par = 3 * nb
    edge = 2 * half + 1
    n_total = edge * edge * edge
    nz, ny, nx = coef_deformed.shape
    for n in prange(centers.shape[0]):
        cz = centers[n, 0]
        cy = centers[n, 1]
        cx = centers[n, 2]
        g = np.empty(n_total, np.float32)  # exact copies, as in icgn.match_one
        grad = np.empty((n_total, 3), np.float32)
        xi = np.empty((n_total, 3), np.float32)
        source, oz, oy, ox = gradient_source(gradient, cz, cy, cx, half)
        count = 0
        for dz in range(-half, half + 1):
            for dy in range(-half, half + 1):
                for dx in range(-half, half + 1):
                    z = cz + dz
                    y = cy + dy
                    x = cx + dx
                    if use_mask and not mask[z, y, x]:
                        continue
                    g[count] = reference[z, y, x]
                    for k in range(3):
                        grad[count, k] = source[k, z - oz, y - oy, x - ox]
                    xi[count, 0] = dz
                    xi[count, 1] = dy
                    xi[count, 2] = dx
                    count += 1
        for k in range(3):
            sigma[n, k] = np.nan
        variance[n] = np.nan
        gradient_power[n] = np.nan
        if count < m_par + 3:
            continue
        mean_g, delta_g, ok, low, sum_j, sum_jg = reference_terms(g, grad, xi, count, nb)
        variance[n] = delta_g * delta_g / count
        power = 0.0
        for k in range(3):
            for j in range(k * nb + 1):
                power += low[k * nb, j] * low[k * nb, j]
        gradient_power[n] = power / count
        if not ok or delta_g == 0.0 or not np.isfinite(zncc[n]):
            continue
        if not sensitivity[n]:
            ss_g = delta_g * delta_g
            h_perp = perpendicular_hessian(low, sum_j, sum_jg, count, ss_g, m_par)
            plain_sigma(h_perp, residual_variance(ss_g, zncc[n], count, m_par), m_par, nb, sigma[n])
            continue
        sandwich_sigma(
            coef_deformed, g, grad, xi, count, mean_g, delta_g, low, sum_j, sum_jg, cz, cy, cx,
            params[n], nb, zncc[n], sigma[n],
        )  # fmt: skip


@njit(**KERNEL_OPTIONS)
def sandwich_sigma(
    coef_deformed, g, grad, xi, count, mean_g, delta_g, low, sum_j, sum_jg, cz, cy, cx, p, nb,
    zncc, out,
):  # fmt: skip
    """:func:`subvolume_statistics`' sigma of a noisy POI (the sensitivity ``A`` measured from
    the deformed volume at the warp ``p``), from the subvolume and reference terms already at
    hand (IC-GN's, or the statistics kernel's own): ``out`` (3,) gets the standard deviations,
    ``inf`` where ``A`` is singular; it is left as it is where that kernel writes NaN (fewer than
    ``3·nb + 3`` voxels of the warped subvolume inside ``F``, or no gray variance there). The
    caller has checked ``count ≥ 3·nb + 3``, ``H``'s factorisation, ``delta_g > 0`` and a finite
    ``zncc``."""
    m_par = 3 * nb
    ss_g = delta_g * delta_g
    h_perp = perpendicular_hessian(low, sum_j, sum_jg, count, ss_g, m_par)
    residual = residual_variance(ss_g, zncc, count, m_par)
    # A from the deformed volume's gradient at the warped voxels
    if nb == 4:
        cross, sum_jf, sum_jfg, used, sum_f, sum_ff = affine_sensitivity_sums(
            coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, p
        )
    elif nb == 10:
        cross, sum_jf, sum_jfg, used, sum_f, sum_ff = quadratic_sensitivity_sums(
            coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, p
        )
    else:
        cross, sum_jf, sum_jfg, used, sum_f, sum_ff = sensitivity_sums(
            coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, p, nb
        )
    if used < m_par + 3:
        return
    ss_f = sum_ff - sum_f * sum_f / used
    if not (ss_f > 0.0):
        return
    ratio = delta_g / np.sqrt(ss_f)
    for r in range(m_par):
        for c in range(m_par):
            cross[r, c] = ratio * (
                cross[r, c] - sum_j[r] * sum_jf[c] / count - sum_jg[r] * sum_jfg[c] / ss_g
            )
    inverse = inverse_rows(cross, np.array([0, nb, 2 * nb]), m_par)  # A⁻¹ at the translations
    # Cov Φ = σ_r² (H⊥ + sym A) / 2: see subvolume_statistics
    for r in range(m_par):
        for c in range(m_par):
            h_perp[r, c] = 0.5 * h_perp[r, c] + 0.25 * (cross[r, c] + cross[c, r])
    for k in range(3):
        quad = 0.0
        for r in range(m_par):
            t = 0.0
            for c in range(m_par):
                t += h_perp[r, c] * inverse[k, c]
            quad += inverse[k, r] * t
        value = np.sqrt(residual * max(quad, 0.0))
        out[k] = value if np.isfinite(value) else np.inf
