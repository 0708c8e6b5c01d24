"""A regularised estimate where a field's neighbourhood holds only matching noise.

A node's match carries the noise of one subvolume; its neighbours measure the same smooth
field with partly independent voxels. Where a node's neighbourhood (:data:`NEIGHBOURHOOD_NODES`)
is consistent with one affine field plus that noise, the generalised-least-squares fit of the
affine field over the neighbourhood estimates the node's displacement with less variance than
its own match. Here, per node and per component:

* the noise of node ``j`` has the standard deviation its match recorded (``uncertainty``), and
  two nodes' noises are correlated by the overlap of their subvolumes, the product over the axes
  of the shared length over the geometric mean of the two edges (``1 - |Δ| / S`` for equal
  edges ``S``): a match's noise is a linear functional of the images' noise over its subvolume
  (:func:`overlap_correlation`);
* the affine field ``u(x) = a + B (x - x_i)`` is fitted by GLS; ``a`` is the estimate at the
  node, its variance ``[(Xᵀ C⁻¹ X)⁻¹]₀₀``;
* the fit is used only where a χ² test says the neighbourhood is that field plus that noise
  (the whole neighbourhood's ``Σ rᵀ C⁻¹ r`` over the three components, and the node's own
  standardised residual, both under the :data:`CHI2_LEVEL` quantile), where every node of the
  neighbourhood is a good measurement (a flagged, refilled, masked or discontinuous node, or one
  without an uncertainty, stops it), and where the fit's variance is at most
  :data:`MAX_VARIANCE_RATIO` of the node's own.

A band, a crack or a fault bends the neighbourhood's values by more than the noise and fails the
test; so does a band's tail where the field bends by a fraction of the noise over the
neighbourhood. See ``docs/method.md`` ("A regularised estimate where the data say noise").
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance, Status
from .pass_method import node_bend

#: Half-width (nodes) of the neighbourhood of the fit: the node and its 26 neighbours.
NEIGHBOURHOOD_NODES = 1

#: Upper-tail probability of the χ² tests: a neighbourhood whose values spread more than pure
#: noise does with this probability is not fitted (a pure-noise neighbourhood fails it as often).
CHI2_LEVEL = 0.05

#: The fit replaces a node's value only where its variance is at most this fraction of the
#: node's own (summed over the components): a smaller gain is not worth a change of model.
MAX_VARIANCE_RATIO = 0.7

#: Nodes whose status says the field is not smooth there (a flagged value, a discontinuity) or
#: that it was not measured by choice: no neighbourhood holding one is fitted.
BLOCKING_STATUSES = (Status.OUTLIER_REPLACED, Status.DISCONTINUITY, Status.MASKED)

#: The matches' noise correlation is the subvolumes' overlap fraction to this power (measured on
#: heavy-noise translations, docs/method.md: the errors of neighbouring nodes correlate less
#: than their subvolumes overlap).
CORRELATION_POWER = 2.0

#: Fewest nodes of a neighbourhood (the grid's edges truncate it): 2 x 2 x 2 pins an affine field
#: with 4 degrees of freedom per component left for the test.
MIN_NODES = 8


@dataclass(frozen=True)
class NoiseFit:
    """What :func:`fit_noise_regions` did, per node (arrays of the grid's shape).

    Attributes
    ----------
    field : DisplacementField
        The field with the fitted nodes' values and uncertainties replaced.
    fitted : ndarray of bool
        Nodes whose value is now the fit's.
    eligible : ndarray of bool
        Nodes whose whole neighbourhood is good measurements (the test was made).
    chi2 : ndarray
        The neighbourhood's χ² over its degrees of freedom (NaN where not eligible).
    variance_ratio : ndarray
        The fit's variance over the node's own (NaN where not eligible).
    curvature : ndarray
        The χ² the quadratic terms explain over its degrees of freedom (NaN where not eligible).
    """

    field: DisplacementField
    fitted: np.ndarray
    eligible: np.ndarray
    chi2: np.ndarray
    variance_ratio: np.ndarray
    curvature: np.ndarray
    #: Why no node was tested at all ("" where the tests ran).
    reason: str = ""

    def summary(self) -> dict:
        """JSON-ready counts and the fitted nodes (flat C-order indices of the grid)."""
        fitted = self.fitted.reshape(-1)
        ratio = self.variance_ratio[self.fitted]
        return {
            "neighbourhood_nodes": 2 * NEIGHBOURHOOD_NODES + 1,
            "chi2_level": CHI2_LEVEL,
            "max_variance_ratio": MAX_VARIANCE_RATIO,
            "eligible_nodes": int(self.eligible.sum()),
            "fitted_nodes": int(fitted.sum()),
            "median_variance_ratio": float(np.median(ratio)) if ratio.size else None,
            "fitted": [int(i) for i in np.flatnonzero(fitted)],
            "not_run": self.reason,
        }


def overlap_correlation(offsets: np.ndarray, edge_a: np.ndarray, edge_b: np.ndarray) -> np.ndarray:
    """Correlation of two matches' noises from the overlap of their cubic subvolumes.

    Parameters
    ----------
    offsets : ndarray, shape (..., 3)
        Centre of one subvolume minus the other's (voxels, (z, y, x)).
    edge_a, edge_b : ndarray, broadcastable to ``offsets.shape[:-1]``
        Edges of the two subvolumes (voxels).

    Returns
    -------
    ndarray, shape ``offsets.shape[:-1]``
        ``Π_axes max(0, L) / sqrt(S_a S_b)`` with ``L`` the length the two boxes share along the
        axis: ``1 - |Δ| / S`` for equal edges, 1 at zero offset, 0 without overlap.
    """
    offsets = np.abs(np.asarray(offsets, np.float64))
    a = np.asarray(edge_a, np.float64)[..., None]
    b = np.asarray(edge_b, np.float64)[..., None]
    # box a on [-a/2, a/2], box b on [d - b/2, d + b/2] along each axis
    shared = np.minimum(0.5 * a, offsets + 0.5 * b) - np.maximum(-0.5 * a, offsets - 0.5 * b)
    shared = np.clip(shared, 0.0, None)
    return np.prod(shared / np.sqrt(a * b), axis=-1)


def _neighbourhood_offsets() -> np.ndarray:
    r = NEIGHBOURHOOD_NODES
    return np.array(list(itertools.product(range(-r, r + 1), repeat=3)), np.int64)


def regularise(
    field: DisplacementField,
    subvolume: int,
    pass_subvolume: int,
    usable=None,
    filled: DisplacementField | None = None,
) -> NoiseFit:
    """:func:`fit_noise_regions` on a corrected field: a ``CORRECTED`` node's value was measured
    by a correcting match of edge ``pass_subvolume``, the others by the first run's
    ``subvolume``; no node is fitted where the field bends across the first run's subvolume by
    more than the node's uncertainty anywhere in its neighbourhood (:func:`.pass_method.node_bend`,
    the test of :func:`.acceptance.noise_only_corrections`), measured on ``filled`` (the same
    field with its masked or failed nodes filled in: the bend needs every node; default
    ``field``). A field without uncertainties is returned unchanged, with the reason."""
    if field.uncertainty is None:  # a field from elsewhere: nothing says what its noise is
        nothing = np.zeros(field.shape, bool)
        nan = np.full(field.shape, np.nan)
        reason = "the field carries no match uncertainty"
        return NoiseFit(field.copy(), nothing, nothing.copy(), nan, nan.copy(), nan.copy(), reason)
    edges = np.where(field.provenance == Provenance.CORRECTED, pass_subvolume, subvolume)
    bend = node_bend(field if filled is None else filled, int(subvolume) // 2)
    return fit_noise_regions(field, edges, usable, bend=bend)


def fit_noise_regions(
    field: DisplacementField,
    subvolume,
    usable: np.ndarray | None = None,
    *,
    bend: np.ndarray | None = None,
) -> NoiseFit:
    """Replace each node's value by the GLS affine fit over its neighbourhood where the data
    say the neighbourhood holds only noise (see the module).

    Parameters
    ----------
    field : DisplacementField
        The field to regularise; must carry ``uncertainty`` (per component, voxels).
    subvolume : int or ndarray of int, the grid's shape
        Edge (voxels) of the subvolume that measured each node's current value.
    usable : ndarray of bool, the grid's shape, optional
        Nodes that may enter a fit at all (besides a good status, a measured or corrected
        provenance and a finite value and uncertainty); the others refuse every neighbourhood
        they are in. Default: all.
    bend : ndarray, the grid's shape, optional
        The field's bend across a subvolume at each node (voxels, :func:`.pass_method.node_bend`):
        a node is fitted only where the largest bend within two neighbourhood half-widths stays
        under its own uncertainty (norm), so that no curvature below the χ² tests' power is
        averaged away. NaN: any bend (not fitted).

    Returns
    -------
    NoiseFit
        The regularised field and what was done per node. Fitted nodes keep their status and
        provenance; their ``uncertainty`` becomes the fit's standard deviation.
    """
    if field.uncertainty is None:
        raise ValueError(
            "the regularised estimate needs each node's match uncertainty: this field has none "
            "(a field from another program or an older file); correlate it again with this one"
        )
    shape = field.shape
    edges = np.broadcast_to(np.asarray(subvolume, np.float64), shape)
    if not np.all(np.isfinite(edges) & (edges > 0)):
        raise ValueError("subvolume edges must be finite and > 0")
    u = np.asarray(field.u, np.float64)
    sigma = np.asarray(field.uncertainty, np.float64)
    # a node that says the field is not smooth there, or that the user did not ask for, refuses
    # every neighbourhood it is in; a match that merely failed or is doubtful is left out
    blocking = np.isin(field.status, [int(s) for s in BLOCKING_STATUSES])
    blocking |= field.provenance == Provenance.MASKED
    if usable is not None:
        blocking |= ~np.asarray(usable, bool).reshape(shape)
    good = np.isin(field.status, [int(s) for s in GOOD_STATUSES]) & ~blocking
    good &= np.isin(field.provenance, [int(Provenance.MEASURED), int(Provenance.CORRECTED)])
    good &= np.all(np.isfinite(u), axis=-1) & np.all(np.isfinite(sigma) & (sigma > 0), axis=-1)

    offsets = _neighbourhood_offsets()  # (k, 3) node offsets
    k = len(offsets)
    r = NEIGHBOURHOOD_NODES
    centres = good.copy()
    if bend is not None:
        bend = np.asarray(bend, np.float64).reshape(shape)
        bent = ndimage.maximum_filter(
            np.where(np.isfinite(bend), bend, np.inf), 4 * NEIGHBOURHOOD_NODES + 1, mode="nearest"
        )  # over the neighbourhood of every node of the neighbourhood
        centres &= ~(bent > np.linalg.norm(np.nan_to_num(sigma), axis=-1))
    index = np.argwhere(centres)  # candidate centres
    neighbour = index[:, None, :] + offsets[None, :, :]  # (n, k, 3)
    inside = np.all((neighbour >= 0) & (neighbour < np.asarray(shape)), axis=-1)
    clipped = np.clip(neighbour, 0, np.asarray(shape) - 1)
    at = tuple(clipped[..., a] for a in range(3))
    present = inside & good[at]
    # no blocking node in the neighbourhood, and enough good ones
    whole = ~np.any(inside & blocking[at], axis=1) & (present.sum(axis=1) >= MIN_NODES)
    for a in range(3):  # the affine field's gradient needs two positions along every axis
        along = offsets[None, :, a]
        span = np.max(np.where(present, along, -r), axis=1) - np.min(
            np.where(present, along, r), axis=1
        )
        whole &= span >= 1
    index, neighbour, present = index[whole], neighbour[whole], present[whole]
    at = tuple(np.clip(neighbour, 0, np.asarray(shape) - 1)[..., a] for a in range(3))
    n = len(index)

    fitted_u = u.copy()
    fitted_sigma = sigma.copy()
    chi2_map = np.full(shape, np.nan)
    ratio_map = np.full(shape, np.nan)
    fitted = np.zeros(shape, bool)
    eligible = np.zeros(shape, bool)
    if n == 0:
        return NoiseFit(field.copy(), fitted, eligible, chi2_map, ratio_map, chi2_map.copy())
    eligible[tuple(index.T)] = True

    step = np.asarray(field.step, np.float64)
    positions = offsets * step  # (k, 3) voxels
    edge = edges[at]  # (n, k)
    correlation = (
        overlap_correlation(
            positions[None, :, None, :] - positions[None, None, :, :],
            edge[:, :, None],
            edge[:, None, :],
        )
        ** CORRELATION_POWER
    )  # (n, k, k)
    scaled = positions / np.max(step * r)
    pairs = [(a, b) for a in range(3) for b in range(a, 3)]
    quadratic = np.stack([scaled[:, a] * scaled[:, b] for a, b in pairs], axis=1)
    design = np.concatenate([np.ones((k, 1)), scaled, quadratic], axis=1)  # (k, 10)
    design = np.where(present[..., None], design[None], 0.0)  # absent nodes carry no weight
    eye = np.eye(k)[None]
    values = np.where(present[..., None], u[at], 0.0)  # (n, k, 3)
    sig = np.where(present[..., None], sigma[at], 1.0)

    chi2 = np.zeros(n)
    curvature = np.zeros(n)
    own_chi2 = np.zeros(n)
    estimate = np.zeros((n, 3))
    variance = np.zeros((n, 3))
    centre = k // 2
    for c in range(3):
        s = sig[..., c]
        cov = correlation * s[:, :, None] * s[:, None, :]
        cov = np.where(present[:, :, None] & present[:, None, :], cov, 0.0)
        cov = cov + np.where(present, 0.0, 1.0)[:, :, None] * eye
        whitened = np.linalg.solve(cov, np.concatenate([design, values[..., c, None]], axis=2))
        inv_x, inv_u = whitened[..., :4], whitened[..., -1]  # C⁻¹ X (affine), C⁻¹ u
        normal = np.einsum("nka,nkb->nab", design[..., :4], inv_x)
        normal_inv = np.linalg.inv(normal)
        beta = np.einsum("nab,nkb,nk->na", normal_inv, inv_x, values[..., c])
        residual = values[..., c] - np.einsum("nka,na->nk", design[..., :4], beta)
        affine_chi2 = np.einsum(
            "nk,nk->n", residual, np.linalg.solve(cov, residual[..., None])[..., 0]
        )
        chi2 += affine_chi2
        # the quadratic terms' share of it: a curvature the omnibus test is too weak to see
        curved = quadratic_chi2(design, whitened[..., :-1], values[..., c], inv_u)
        curvature += affine_chi2 - curved
        estimate[:, c] = beta[:, 0]
        variance[:, c] = normal_inv[:, 0, 0]
        # the node's own residual: GLS residuals are uncorrelated with the fit, so
        # var(u_i - a) = σ_i² - var(a)
        own_variance = np.maximum(
            s[:, centre] ** 2 - normal_inv[:, 0, 0], 1e-12 * s[:, centre] ** 2
        )
        own_chi2 += residual[:, centre] ** 2 / own_variance
    dof = 3 * (present.sum(axis=1) - 4)
    from scipy import stats  # here: scipy.stats takes 0.3 s to import (every correction's start-up)

    passes = chi2 <= stats.chi2.ppf(1.0 - CHI2_LEVEL, dof)
    passes &= own_chi2 <= stats.chi2.ppf(1.0 - CHI2_LEVEL, 3)
    passes &= curvature <= stats.chi2.ppf(1.0 - CHI2_LEVEL, 3 * len(pairs))
    own = sigma[tuple(index.T)]
    ratio = variance.sum(axis=1) / np.sum(own**2, axis=1)
    take = passes & (ratio <= MAX_VARIANCE_RATIO)

    where = tuple(index.T)
    chi2_map[where] = chi2 / np.maximum(dof, 1)
    ratio_map[where] = ratio
    curvature_map = np.full(shape, np.nan)
    curvature_map[where] = curvature / (3 * len(pairs))
    chosen = tuple(index[take].T)
    fitted[chosen] = True
    fitted_u[chosen] = estimate[take]
    fitted_sigma[chosen] = np.sqrt(variance[take])
    result = field.copy()
    result.u = fitted_u
    result.uncertainty = fitted_sigma
    return NoiseFit(result, fitted, eligible, chi2_map, ratio_map, curvature_map)


def quadratic_chi2(design, inv_design, values, inv_values) -> np.ndarray:
    """``min (u - X β)ᵀ C⁻¹ (u - X β)`` over the full (quadratic) design, per neighbourhood,
    from ``C⁻¹ X`` and ``C⁻¹ u``. Where the neighbourhood cannot pin the quadratic terms (a
    truncated one) it equals the affine χ² (no curvature is tested there beyond it)."""
    normal = np.einsum("nka,nkb->nab", design, inv_design)
    rhs = np.einsum("nka,nk->na", inv_design, values)  # Xᵀ C⁻¹ u
    beta = np.einsum("nab,nb->na", np.linalg.pinv(normal, hermitian=True), rhs)
    fitted = np.einsum("nka,na->nk", design, beta)
    return np.einsum("nk,nk->n", values, inv_values) - np.einsum("nk,nk->n", fitted, inv_values)
