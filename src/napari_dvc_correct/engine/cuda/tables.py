"""Host-side index tables that let one GPU kernel build the IC-GN reference terms of either order.

The reference-side sums of IC-GN for a subvolume are (``J = ∇G · ∂W/∂p``, ``J[(k, j)] = g_k b_j``
with ``g_k`` the gradient component along axis ``k`` and ``b_j`` the shape-function monomials):

- ``A[k, j] = Σ g_k b_j``                 (``Σ J``),
- ``B[k, j] = Σ g_k (g − ḡ) b_j``         (``Σ J (g − ḡ)``),
- ``S[kl, q] = Σ g_k g_l m_q``           (Hessian: ``H[(k, j), (l, i)] = S[kl, q(j·i)]``),
- ``Σ (g − ḡ)²``,

where ``m_q`` are the monomials of degree ≤ 2·order of the local coordinates ``(ξz, ξy, ξx)``
(10 for the affine shape function, 35 for the quadratic one). Counting products this way needs
60 / 210 Hessian sums instead of 78 / 465 entries.

The kernel visits the subvolume column by column (fixed ``ξy, ξx``, all ``ξz``). Along a column it
accumulates, for each *factor* (``g_k``, ``g_k (g − ḡ)``, ``g_k g_l``, ``(g − ḡ)²``), only the
moments ``Σ factor · ξz^a``; at the end of the column each wanted sum receives
``moment[a] · ξy^b · ξx^c``. Per voxel that is (factors × powers of ξz) multiply-adds, whatever the
number of sums. The sums are split into *passes* of at most :data:`MAX_TERMS` (one block reduction
each) with at most :data:`N_SLOTS` factors.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

#: Factors: 0-2 g_k, 3-5 g_k·dg, 6-11 g_k·g_l for the pairs below, 12 dg² (dg = g − ḡ).
PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
N_FACTORS = 13
N_SLOTS = 4
MAX_TERMS = 35


def monomial_exponents(max_degree: int) -> np.ndarray:
    """Exponents ``(a, b, c)`` of ``ξz^a ξy^b ξx^c`` up to ``max_degree``, shape (n, 3).

    The first 10 follow :mod:`napari_dvc_correct.engine.correlation.icgn`:
    ``1, z, y, x, zz, yy, xx, zy, yx, zx``; higher degrees follow in a fixed order.
    """
    first = [
        (0, 0, 0),
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
        (2, 0, 0),
        (0, 2, 0),
        (0, 0, 2),
        (1, 1, 0),
        (0, 1, 1),
        (1, 0, 1),
    ]
    exps = [e for e in first if sum(e) <= max_degree]
    for degree in range(3, max_degree + 1):
        for a in range(degree, -1, -1):
            for b in range(degree - a, -1, -1):
                exps.append((a, b, degree - a - b))
    return np.array(exps, dtype=np.int64)


@dataclass(frozen=True)
class ReferenceTables:
    """Index tables for one shape-function order (see the module docstring).

    Attributes
    ----------
    nb : int
        Monomials of the shape function (4 or 10); ``3 * nb`` parameters.
    n_powers : int
        Powers of ξz tracked per factor along a column (``2 * order + 1``).
    pass_slots : ndarray (n_passes, N_SLOTS) int64
        Factor of each slot of a pass (-1 = unused).
    pass_base, pass_count : ndarray (n_passes,) int64
        Where a pass's sums start in the sums vector, and how many it has.
    dist : ndarray (n_passes, N_SLOTS, n_powers, max_terms, 3) int64
        For (pass, slot, power a): rows ``(b, c, local index)``: the sum at ``local index`` gets
        ``moment[slot, a] · ξy^b · ξx^c`` at the end of each column.
    dist_n : ndarray (n_passes, N_SLOTS, n_powers) int64
        Rows used in ``dist``.
    hess_map : ndarray (3nb, 3nb) int64
        Index of ``H[r, c]`` in the sums vector.
    jsum_map, jgsum_map : ndarray (3nb,) int64
        Index of ``Σ J[r]`` and ``Σ J[r] (g − ḡ)``.
    ssg_index : int
        Index of ``Σ (g − ḡ)²``.
    n_sums : int
        Length of the sums vector.
    """

    nb: int
    n_powers: int
    pass_slots: np.ndarray
    pass_base: np.ndarray
    pass_count: np.ndarray
    dist: np.ndarray
    dist_n: np.ndarray
    hess_map: np.ndarray
    jsum_map: np.ndarray
    jgsum_map: np.ndarray
    ssg_index: int
    n_sums: int

    @property
    def n_passes(self) -> int:
        return len(self.pass_base)


@functools.cache
def reference_tables(nb: int) -> ReferenceTables:
    """Tables for the affine (``nb = 4``) or quadratic (``nb = 10``) shape function."""
    if nb not in (4, 10):
        raise ValueError(f"nb must be 4 or 10, got {nb}")
    order = 1 if nb == 4 else 2
    exps = monomial_exponents(2 * order)
    n_q = len(exps)
    index_of = {tuple(e): q for q, e in enumerate(exps)}
    n_powers = 2 * order + 1

    # passes: list of (slots, terms) with terms (slot, monomial q)
    passes = [
        ([0, 1, 2], [(k, j) for k in range(3) for j in range(nb)]),
        ([3, 4, 5, 12], [(k, j) for k in range(3) for j in range(nb)] + [(3, 0)]),
    ]
    pairs_per_pass = max(1, MAX_TERMS // n_q)
    for start in range(0, len(PAIRS), pairs_per_pass):
        chosen = list(range(start, min(start + pairs_per_pass, len(PAIRS))))
        passes.append(
            ([6 + p for p in chosen], [(s, q) for s in range(len(chosen)) for q in range(n_q)])
        )

    n_passes = len(passes)
    pass_slots = -np.ones((n_passes, 4), np.int64)
    pass_base = np.zeros(n_passes, np.int64)
    pass_count = np.zeros(n_passes, np.int64)
    dist = np.zeros((n_passes, 4, n_powers, MAX_TERMS, 3), np.int64)
    dist_n = np.zeros((n_passes, 4, n_powers), np.int64)
    base = 0
    for p, (slots, terms) in enumerate(passes):
        assert len(slots) <= 4 and len(terms) <= MAX_TERMS
        pass_slots[p, : len(slots)] = slots
        pass_base[p] = base
        pass_count[p] = len(terms)
        for local, (slot, q) in enumerate(terms):
            a, b, c = exps[q]
            row = dist_n[p, slot, a]
            dist[p, slot, a, row] = (b, c, local)
            dist_n[p, slot, a] += 1
        base += len(terms)
    n_sums = base

    a_base, b_base = pass_base[0], pass_base[1]
    jsum_map = np.array([a_base + k * nb + j for k in range(3) for j in range(nb)], np.int64)
    jgsum_map = np.array([b_base + k * nb + j for k in range(3) for j in range(nb)], np.int64)
    ssg_index = int(b_base + 3 * nb)

    pair_location = {}
    for p, (slots, _) in enumerate(passes[2:], start=2):
        for s, factor in enumerate(slots):
            pair_location[PAIRS[factor - 6]] = (p, s)
    n_par = 3 * nb
    hess_map = np.zeros((n_par, n_par), np.int64)
    for r in range(n_par):
        k, j = divmod(r, nb)
        for c in range(n_par):
            l, i = divmod(c, nb)
            p, s = pair_location[(min(k, l), max(k, l))]
            q = index_of[tuple(exps[j] + exps[i])]
            hess_map[r, c] = pass_base[p] + s * n_q + q
    return ReferenceTables(
        nb=nb,
        n_powers=n_powers,
        pass_slots=pass_slots,
        pass_base=pass_base,
        pass_count=pass_count,
        dist=dist,
        dist_n=dist_n,
        hess_map=hess_map,
        jsum_map=jsum_map,
        jgsum_map=jgsum_map,
        ssg_index=ssg_index,
        n_sums=n_sums,
    )


def reference_sums_numpy(g, grad, xi, tables: ReferenceTables) -> np.ndarray:
    """The sums vector computed directly with numpy (float64), for tests of the tables.

    Parameters
    ----------
    g : ndarray (n,)
        Reference gray values of the subvolume voxels (minus nothing: centred here).
    grad : ndarray (n, 3)
        Gradient ``(d/dz, d/dy, d/dx)`` at those voxels.
    xi : ndarray (n, 3)
        Local coordinates ``(ξz, ξy, ξx)``.
    """
    g = np.asarray(g, np.float64)
    dg = g - g.mean()
    grad = np.asarray(grad, np.float64)
    factors = np.empty((N_FACTORS, len(g)))
    factors[0:3] = grad.T
    factors[3:6] = grad.T * dg
    for p, (k, l) in enumerate(PAIRS):
        factors[6 + p] = grad[:, k] * grad[:, l]
    factors[12] = dg * dg
    out = np.zeros(tables.n_sums)
    xi = np.asarray(xi, np.float64)
    for p in range(tables.n_passes):
        for s in range(N_SLOTS):
            factor = tables.pass_slots[p, s]
            if factor < 0:
                continue
            for a in range(tables.n_powers):
                for row in range(tables.dist_n[p, s, a]):
                    b, c, local = tables.dist[p, s, a, row]
                    out[tables.pass_base[p] + local] += np.sum(
                        factors[factor] * xi[:, 0] ** a * xi[:, 1] ** b * xi[:, 2] ** c
                    )
    return out
