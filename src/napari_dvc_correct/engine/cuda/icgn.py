"""IC-GN on the GPU: the kernel, one thread block per POI, with the same algorithm and statuses
as :func:`napari_dvc_correct.engine.correlation.icgn.match_many`.

Mapping
-------
Block ``b`` matches POI ``b``. Its threads stride over the subvolume's *columns* ``(ξy, ξx)``
(consecutive threads take consecutive ``ξx``, so loads of G, ∇G and the taps of F coalesce) and walk
each column along ``ξz``. Per voxel a thread samples F at the warped position (64 float32 taps),
and accumulates the 3·nb + 3 sums of the iteration in float32 along the column, flushed into
float64 at the end of each column. A shared-memory tree reduction gives the block's sums; thread 0
then does the small serial work in float64: ZNCC, right-hand side, Cholesky solve (the factor stays
in shared memory for all iterations), warp composition ``W(p) ∘ W(Δp)⁻¹`` and the convergence test;
the other threads wait at a barrier.

The reference-side terms (ḡ, Σ(g − ḡ)², ΣJ, ΣJ(g − ḡ) and the Hessian) are built on the GPU too,
once per POI, by :mod:`.tables`' column-moment passes; ``G`` and ``∇G`` are read from the volumes at
every iteration rather than cached (4 coalesced loads per voxel against 64 for the taps).

Precision: taps, weights and per-column partial sums are float32; every block sum and all of thread
0's algebra is float64. Sums are taken around the float32 mean of the reference subvolume and
corrected exactly, so a large gray offset (16-bit CT) does not cancel digits.

POIs whose warped subvolume leaves the deformed volume are not handled here (the CPU drops the
voxels that left and rebuilds the reference terms, which needs per-voxel state): the kernel flags
them :data:`FALLBACK` and :func:`.launch.match_many_cuda` matches them again on the CPU, so results stay
identical to the CPU path. They are rare (subvolumes at the border moving outwards).

This module builds the kernel (:func:`build_kernel`). Its device helpers (reduction, Cholesky, warp
algebra) live in :mod:`.device_algebra`; the host side (uploads, launches in chunks, the CPU
fallback) in :mod:`.launch`.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import float32, float64, int32, int64, uint64

from ..correlation import icgn as cpu_icgn
from ..fields.field import Status
from ._numba_cuda import cuda, simulator_enabled
from .device_algebra import (
    REDUCE_CHUNK,
    block_reduce,
    cholesky,
    cholesky_solve,
    factor_value,
    finish,
    invert,
    monomials32,
    warp_matrix,
)
from .sampling import inside, interior, sample_interior, sample_mirrored, split_position
from .tables import MAX_TERMS, N_SLOTS, reference_tables

#: Status the kernel gives a POI the CPU must match instead (never returned to callers).
FALLBACK = -1

_CONVERGED = int(Status.CONVERGED)
_DIVERGED = int(Status.DIVERGED)
_LOW_TEXTURE = int(Status.LOW_TEXTURE)
_MASKED = int(Status.MASKED)
_MAX_ITERATIONS = int(Status.MAX_ITERATIONS)
_SINGULAR = int(Status.SINGULAR)

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)


@functools.cache
def build_kernel(nb: int, threads: int, max_registers: int | None = None):
    """The IC-GN kernel for ``nb`` monomials (4: first order, 10: second) and a block size.

    Sizes are closure constants so that numba sizes the local and shared arrays at compile time
    and unrolls the per-voxel loops (registers, not local memory, on a GPU). ``max_registers``
    caps the registers per thread (more blocks per SM, possibly spills); None lets the compiler
    choose (ptxas gives 223 registers for nb = 4 and 255 for nb = 10 on sm_90).
    """
    if threads < REDUCE_CHUNK or threads & (threads - 1):
        raise ValueError(f"threads per block must be a power of two >= 16, got {threads}")
    tables = reference_tables(nb)
    NB = nb
    NPAR = 3 * nb
    KIT = NPAR + 3  # Σ J(f − s) (3nb), Σ (f − s), Σ (f − s)², Σ (g − s)(f − s)
    KACC = max(KIT, MAX_TERMS)
    NPOW = tables.n_powers
    NMOM = N_SLOTS * NPOW
    NSUMS = tables.n_sums
    NPASS = tables.n_passes
    T = threads
    RED = REDUCE_CHUNK * threads
    NM = nb * nb
    NPAR2 = NPAR * NPAR
    NW = 2 * nb * nb
    MAXZ = cpu_icgn.NOISE_STOP_MAX_ZNCC
    STALL_FACTOR = cpu_icgn.STALL_FACTOR
    STALL_ITERATIONS = float64(cpu_icgn.STALL_ITERATIONS)
    options = {}
    if max_registers and not simulator_enabled():
        options["max_registers"] = int(max_registers)

    @cuda.jit(**options)
    def kernel(
        reference,
        gradient,
        coef,
        mask,
        use_mask,
        nz,
        ny,
        nx,
        centers,
        half,
        params,
        zncc,
        status,
        iterations,
        max_iterations,
        tolerance,
        min_std,
        min_mask_fraction,
        max_update,
        product_table,
        quad_axes,
        noise_fraction,
        pass_slots,
        pass_base,
        pass_count,
        dist,
        dist_n,
        hess_map,
        jsum_map,
        jgsum_map,
        ssg_index,
    ):
        poi = cuda.blockIdx.x
        t = cuda.threadIdx.x
        red = cuda.shared.array(RED, float64)
        rsum = cuda.shared.array(NSUMS, float64)
        isum = cuda.shared.array(KIT, float64)
        low = cuda.shared.array(NPAR2, float64)
        p_sh = cuda.shared.array(NPAR, float64)
        # count, Σg→ḡ, δg, zncc, start z/y/x, -, (H⁻¹) at z/y/x translations, last noise step,
        # shortest step, iterations since it
        scal = cuda.shared.array(14, float64)
        flag = cuda.shared.array(2, int32)  # finished, a warped voxel left the volume
        rhs = cuda.shared.array(NPAR, float64)
        dp = cuda.shared.array(NPAR, float64)
        ytmp = cuda.shared.array(NPAR, float64)
        m_cur = cuda.shared.array(NM, float64)
        m_upd = cuda.shared.array(NM, float64)
        m_inv = cuda.shared.array(NM, float64)
        work = cuda.shared.array(NW, float64)
        acc = cuda.local.array(KACC, float64)
        acc32 = cuda.local.array(KIT, float32)
        moments = cuda.local.array(NMOM, float32)
        fids = cuda.local.array(N_SLOTS, int64)
        pz = cuda.local.array(NPOW, float32)
        py = cuda.local.array(5, float64)
        px = cuda.local.array(5, float64)
        pf = cuda.local.array(NPAR, float32)
        b = cuda.local.array(NB, float32)

        sz = ny * nx
        nvox = nz * sz
        nvox2 = 2 * nvox
        cz = centers[poi, 0]
        cy = centers[poi, 1]
        cx = centers[poi, 2]
        edge = 2 * half + 1
        ncol = edge * edge
        n_total = edge * ncol

        if t == 0:
            flag[0] = 0
            flag[1] = 0
            for r in range(NPAR):
                p_sh[r] = params[poi, r]
            scal[4] = p_sh[0]
            scal[5] = p_sh[NB]
            scal[6] = p_sh[2 * NB]
        cuda.syncthreads()

        # 1. voxel count (mask) and mean of the reference subvolume
        acc[0] = 0.0
        acc[1] = 0.0
        for col in range(t, ncol, T):
            y = cy + col // edge - half
            x = cx + col % edge - half
            first = (cz - half) * sz + y * nx + x
            c32 = _ZERO
            s32 = _ZERO
            for k in range(edge):
                idx = uint64(first + k * sz)
                if use_mask and not mask[idx]:
                    continue
                c32 += _ONE
                s32 += reference[idx]
            acc[0] += c32
            acc[1] += s32
        block_reduce(acc, 2, red, scal, 0, t, T)
        if t == 0:
            count = scal[0]
            if count < min_mask_fraction * n_total or count < NPAR + 1:
                finish(
                    poi, _MASKED, math.nan, 0, p_sh, NPAR, params, zncc, status, iterations, flag
                )
            else:
                scal[1] = scal[1] / count
        cuda.syncthreads()
        if flag[0] != 0:
            return
        mean32 = float32(scal[1])

        # 2. reference-side sums, pass by pass (see tables.py)
        for ps in range(NPASS):
            for s in range(N_SLOTS):
                fids[s] = pass_slots[ps, s]
            for i in range(MAX_TERMS):
                acc[i] = 0.0
            for col in range(t, ncol, T):
                dyi = col // edge - half
                dxi = col % edge - half
                first = (cz - half) * sz + (cy + dyi) * nx + cx + dxi
                for i in range(NMOM):
                    moments[i] = _ZERO
                for dzi in range(-half, half + 1):
                    i0 = first + (dzi + half) * sz
                    if use_mask and not mask[uint64(i0)]:
                        continue
                    g0 = gradient[uint64(i0)]
                    g1 = gradient[uint64(i0 + nvox)]
                    g2 = gradient[uint64(i0 + nvox2)]
                    dg = reference[uint64(i0)] - mean32
                    zf = float32(dzi)
                    pz[0] = _ONE
                    for a in range(1, NPOW):
                        pz[a] = pz[a - 1] * zf
                    for s in range(N_SLOTS):
                        phi = factor_value(fids[s], g0, g1, g2, dg)
                        for a in range(NPOW):
                            moments[s * NPOW + a] += phi * pz[a]
                py[0] = 1.0
                px[0] = 1.0
                for a in range(1, 5):
                    py[a] = py[a - 1] * dyi
                    px[a] = px[a - 1] * dxi
                for s in range(N_SLOTS):
                    for a in range(NPOW):
                        mv = float64(moments[s * NPOW + a])
                        for row in range(dist_n[ps, s, a]):
                            acc[dist[ps, s, a, row, 2]] += (
                                mv * py[dist[ps, s, a, row, 0]] * px[dist[ps, s, a, row, 1]]
                            )
            block_reduce(acc, pass_count[ps], red, rsum, pass_base[ps], t, T)

        # 3. thread 0: texture test and Cholesky factor of the Hessian
        if t == 0:
            count = scal[0]
            shift = scal[1] - float64(mean32)  # sums were taken around mean32, not ḡ
            ss_g = rsum[ssg_index] - count * shift * shift
            delta_g = math.sqrt(max(ss_g, 0.0))
            scal[2] = delta_g
            if delta_g <= min_std * math.sqrt(count) or delta_g == 0.0:
                finish(
                    poi,
                    _LOW_TEXTURE,
                    math.nan,
                    0,
                    p_sh,
                    NPAR,
                    params,
                    zncc,
                    status,
                    iterations,
                    flag,
                )
            else:
                for r in range(NPAR):
                    for c in range(r + 1):
                        low[r * NPAR + c] = rsum[hess_map[r, c]]
                if not cholesky(low, NPAR):
                    finish(
                        poi,
                        _SINGULAR,
                        math.nan,
                        0,
                        p_sh,
                        NPAR,
                        params,
                        zncc,
                        status,
                        iterations,
                        flag,
                    )
                else:  # (H⁻¹)_kk at the translations, for the noise stop
                    for k in range(3):
                        for r in range(NPAR):
                            rhs[r] = 0.0
                        rhs[k * NB] = 1.0
                        cholesky_solve(low, rhs, NPAR, ytmp, dp)
                        scal[8 + k] = dp[k * NB]
            scal[3] = math.nan
            scal[11] = math.inf
            scal[12] = math.inf  # shortest step so far, and iterations since (icgn.STALL_*)
            scal[13] = 0.0
        cuda.syncthreads()
        if flag[0] != 0:
            return

        # 4. Gauss-Newton iterations
        for it in range(1, max_iterations + 1):
            # integer part of the translation goes to the base position, the rest stays float32
            rz = math.floor(p_sh[0] + 0.5)
            ry = math.floor(p_sh[NB] + 0.5)
            rx = math.floor(p_sh[2 * NB] + 0.5)
            bz = cz + int64(rz)
            by = cy + int64(ry)
            bx = cx + int64(rx)
            for r in range(NPAR):
                pf[r] = float32(p_sh[r])
            pf[0] = float32(p_sh[0] - rz)
            pf[NB] = float32(p_sh[NB] - ry)
            pf[2 * NB] = float32(p_sh[2 * NB] - rx)
            for i in range(KIT):
                acc[i] = 0.0
            for col in range(t, ncol, T):
                dyi = col // edge - half
                dxi = col % edge - half
                first = (cz - half) * sz + (cy + dyi) * nx + cx + dxi
                yf = float32(dyi)
                xf = float32(dxi)
                for i in range(KIT):
                    acc32[i] = _ZERO
                for dzi in range(-half, half + 1):
                    i0 = first + (dzi + half) * sz
                    if use_mask and not mask[uint64(i0)]:
                        continue
                    zf = float32(dzi)
                    monomials32(zf, yf, xf, NB, b)
                    wz = zf
                    wy = yf
                    wx = xf
                    for j in range(NB):
                        wz += pf[j] * b[j]
                        wy += pf[NB + j] * b[j]
                        wx += pf[2 * NB + j] * b[j]
                    iz, tz = split_position(bz, wz)
                    iy, ty = split_position(by, wy)
                    ix, tx = split_position(bx, wx)
                    if not (inside(iz, tz, nz) and inside(iy, ty, ny) and inside(ix, tx, nx)):
                        flag[1] = 1
                        continue
                    if interior(iz, nz) and interior(iy, ny) and interior(ix, nx):
                        f = sample_interior(coef, sz, nx, iz, iy, ix, tz, ty, tx)
                    else:
                        f = sample_mirrored(coef, nz, ny, nx, iz, iy, ix, tz, ty, tx)
                    fs = f - mean32
                    dg = reference[uint64(i0)] - mean32
                    gf0 = gradient[uint64(i0)] * fs
                    gf1 = gradient[uint64(i0 + nvox)] * fs
                    gf2 = gradient[uint64(i0 + nvox2)] * fs
                    for j in range(NB):
                        acc32[j] += gf0 * b[j]
                        acc32[NB + j] += gf1 * b[j]
                        acc32[2 * NB + j] += gf2 * b[j]
                    acc32[NPAR] += fs
                    acc32[NPAR + 1] += fs * fs
                    acc32[NPAR + 2] += dg * fs
                for i in range(KIT):
                    acc[i] += acc32[i]
            block_reduce(acc, KIT, red, isum, 0, t, T)

            if t == 0:
                if flag[1] != 0:
                    finish(
                        poi,
                        FALLBACK,
                        math.nan,
                        it,
                        p_sh,
                        NPAR,
                        params,
                        zncc,
                        status,
                        iterations,
                        flag,
                    )
                else:
                    count = scal[0]
                    delta_g = scal[2]
                    shift = scal[1] - float64(mean32)
                    s_f = isum[NPAR]
                    ss_f = isum[NPAR + 1] - s_f * s_f / count
                    if not (ss_f > 0.0):
                        finish(
                            poi,
                            _DIVERGED,
                            math.nan,
                            it,
                            p_sh,
                            NPAR,
                            params,
                            zncc,
                            status,
                            iterations,
                            flag,
                        )
                    else:
                        delta_f = math.sqrt(ss_f)
                        value = (isum[NPAR + 2] - shift * s_f) / (delta_g * delta_f)
                        scal[3] = value
                        ratio = delta_g / delta_f
                        mean_f_shift = s_f / count
                        for r in range(NPAR):
                            sum_j = rsum[jsum_map[r]]
                            sum_jg = rsum[jgsum_map[r]] - shift * sum_j
                            rhs[r] = -(sum_jg - ratio * (isum[r] - mean_f_shift * sum_j))
                        cholesky_solve(low, rhs, NPAR, ytmp, dp)
                        # W(p) <- W(p) o W(dp)^-1
                        warp_matrix(p_sh, NB, m_cur, product_table, quad_axes)
                        warp_matrix(dp, NB, m_upd, product_table, quad_axes)
                        invertible = invert(m_upd, NB, m_inv, work)
                        for i in range(NB):
                            for j in range(NB):
                                v = 0.0
                                for k in range(NB):
                                    v += m_cur[i * NB + k] * m_inv[k * NB + j]
                                work[i * NB + j] = v
                        for k in range(3):
                            for j in range(NB):
                                p_sh[k * NB + j] = work[(1 + k) * NB + j]
                            p_sh[k * NB + 1 + k] -= 1.0
                        largest = 0.0
                        for corner in range(8):
                            sz_ = float64(half if corner & 4 else -half)
                            sy_ = float64(half if corner & 2 else -half)
                            sx_ = float64(half if corner & 1 else -half)
                            norm2 = 0.0
                            for k in range(3):
                                moved = dp[k * NB] + dp[k * NB + 1] * sz_
                                moved += dp[k * NB + 2] * sy_ + dp[k * NB + 3] * sx_
                                if NB == 10:
                                    moved += dp[k * NB + 4] * sz_ * sz_ + dp[k * NB + 5] * sy_ * sy_
                                    moved += dp[k * NB + 6] * sx_ * sx_ + dp[k * NB + 7] * sz_ * sy_
                                    moved += dp[k * NB + 8] * sy_ * sx_ + dp[k * NB + 9] * sz_ * sx_
                                norm2 += moved * moved
                            largest = max(largest, norm2)
                        finite = invertible
                        for r in range(NPAR):
                            if math.isnan(p_sh[r]) or math.isinf(p_sh[r]):
                                finite = False
                        moved_far = False
                        for k in range(3):
                            if abs(p_sh[k * NB] - scal[4 + k]) > max_update:
                                moved_far = True
                        if not finite or moved_far:
                            finish(
                                poi,
                                _DIVERGED,
                                value,
                                it,
                                p_sh,
                                NPAR,
                                params,
                                zncc,
                                status,
                                iterations,
                                flag,
                            )
                        elif math.sqrt(largest) < tolerance:
                            finish(
                                poi,
                                _CONVERGED,
                                value,
                                it,
                                p_sh,
                                NPAR,
                                params,
                                zncc,
                                status,
                                iterations,
                                flag,
                            )
                        else:
                            stop = False
                            if noise_fraction > 0.0:  # as icgn._noise_converged
                                residual = 2.0 * delta_g * delta_g * max(1.0 - value, 0.0)
                                residual /= max(count - NPAR - 2, 1.0)
                                d = 0.0
                                scaled = value < MAXZ
                                for k in range(3):
                                    scale = math.sqrt(residual * scal[8 + k])
                                    if not (scale > 0.0):
                                        scaled = False
                                    else:
                                        d = max(d, abs(dp[k * NB]) / scale)
                                previous = scal[11]
                                scal[11] = d if scaled else math.inf
                                if scaled and d < 1.0 and not math.isinf(previous):
                                    rho = min(d / previous, 1.0) if previous > 0.0 else 0.0
                                    stop = d * rho < noise_fraction
                            motion = math.sqrt(largest)
                            if stop:
                                finish(
                                    poi,
                                    _CONVERGED,
                                    value,
                                    it,
                                    p_sh,
                                    NPAR,
                                    params,
                                    zncc,
                                    status,
                                    iterations,
                                    flag,
                                )
                            elif motion < STALL_FACTOR * scal[12]:  # as icgn.match_one
                                scal[12] = motion
                                scal[13] = 0.0
                            elif not (scal[11] < 1.0):
                                scal[13] += 1.0
                                if scal[13] >= STALL_ITERATIONS:
                                    finish(
                                        poi,
                                        _DIVERGED,
                                        value,
                                        it,
                                        p_sh,
                                        NPAR,
                                        params,
                                        zncc,
                                        status,
                                        iterations,
                                        flag,
                                    )
            cuda.syncthreads()
            if flag[0] != 0:
                return
        if t == 0:
            finish(
                poi,
                _MAX_ITERATIONS,
                scal[3],
                max_iterations,
                p_sh,
                NPAR,
                params,
                zncc,
                status,
                iterations,
                flag,
            )

    return kernel
