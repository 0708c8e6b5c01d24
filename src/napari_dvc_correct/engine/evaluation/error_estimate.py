"""An error estimate in voxels per node, from the gray residual and the image gradient.

The accuracy index of eq. 2 measures the gray mismatch in units of the phase contrast: any field
with errors under a voxel scores above 0.99, so it cannot tell a field that is 0.5 voxel off in
a band from a good one. This module turns the same gray-level-corrected residual into a
displacement error, node by node, over windows up to half-size :func:`error_region_half` around
the node (the sums are gathered block by block, :mod:`.accuracy_blocks`):

- **the error the residual resolves.** A field wrong by ``e`` at a voxel leaves the signed
  residual ``s = map(F)(X + u) - G(X) ≈ grad G · e + α G + β + n`` (``n`` the two scans' noise,
  variance ``2σ²``; ``α G + β`` what the gray-level map leaves of a gray change, or adds by its
  own error). One Gauss-Newton step of the matcher on the window, invariant to the local gray
  offset and gain as the ZNSSD criterion is, gives ``e`` back: with ``g = grad G`` and window
  covariances, ``Δu = H_t⁻¹ (cov(g, s) − a cov(G, s) / v)``, ``a = cov(g, G)``,
  ``v = var G − σ²``, ``H_t = cov(g, g) − a aᵀ / v − σ²/2 I`` (central differences of the noise
  add ``σ²/2`` per component, which would shrink ``Δu`` by the share of noise in the gradient).
  That step is taken with an **instrument**: the noise of ``G``'s gradient pairs with itself in
  ``cov(g, g)`` and makes the step noisy where the noise is a large share of the gradient
  (faint CT texture). The step uses ``w = (g + h)/2`` instead of ``g`` on the left of every
  covariance, ``h`` the gradient of ``G`` smoothed by a Gaussian of :data:`.error_moments.INSTRUMENT_SIGMA`
  voxel (:func:`.error_moments.smoothed_gradient`, the same texture with less noise):
  ``Δu = A⁻¹ (cov(w, s) − a_w (cov(G, s) + σ²) / v)``, ``A = cov(w, g) − a_w aᵀ / v − p σ² I``
  with ``a_w = cov(w, G)`` and ``p = (1/2 + c)/2`` the noise's pairing of ``w`` with ``g`` at a
  voxel (``c``: :func:`.error_moments.instrument_noise_pairing`; ``w`` and ``s`` do not pair: the derivative
  kernels are odd). Its noise has covariance ``C = 2σ²/n A⁻¹ W A⁻ᵀ``, ``W = cov(w, w) −
  a_w a_wᵀ / v``, over ``n`` voxels: ``√tr C`` is the node's **resolution** (errors below it
  do not show in the residual) and the resolved error is ``e_r = √max(|Δu|² − tr C, 0)``.
  (With ``w = g`` this is the plain step ``H_t⁻¹ (cov(g, s) − …)``, ``H_t = cov(g, g) − a aᵀ/v
  − σ²/2 I``; the instrument lowers the resolution by 10–17 % on CT texture at 3–5 % noise,
  ``docs/evaluation.md``.)
- **a residual the linear model does not explain.** Beyond the linear range (errors of a few
  voxels, a crack, the texture changed) the moved texture no longer matches the reference's
  (its contrast ``k = 1 + (cov(G, s) + σ²)/v`` against it falls below
  :data:`MATCHED_CONTRAST`) and ``Δu`` falls short. There, where the residual's excess variance
  ``V = var s − (k − 1)² v − 2σ²`` exceeds the part ``k² Δuᵀ H_t Δu`` that ``Δu`` explains by
  more than :data:`UNEXPLAINED_SIGMAS` of its noise (``2√2 σ²/√n``), the error that explains
  ``V`` with the error's direction random against the texture, ``√(3 V / tr H_t)``, is taken if
  larger.
- **the error at the node.** ``e = √(e_r² + max(|σ_u|, d)²)`` with ``|σ_u|`` the noise-based
  uncertainty of the match (``field.uncertainty``) where the field has it, and ``d`` the node's
  deviation from the leave-one-out quadratic fit of its neighbours
  (:func:`.node_roughness.node_roughness`): the window holds about a third of an error confined
  to one node, below its noise on faint texture, and the field's own shape shows it. Below the
  resolution the residual cannot rank the nodes; a match's error is then its noise error or its
  departure from its neighbourhood, the larger.
- **windows of several sizes** (:mod:`.error_scales`): ``e_r`` is read in the finest window
  (half-size 2 voxels up to :func:`error_region_half`) that resolves the node's error well, and
  ``d`` is bounded by what the windows' steps read along it (a true field that bends at the
  grid's scale is not an error).

``σ`` is the scans' noise, from the pair's ``r0`` (eq. 1: the residual's noise has variance
``π r0²/2``), half of it each scan's. The pairings above are white noise's; where the scans'
noise is correlated in space (measured on the pair's residual, :mod:`.noise_correlation`) they
follow its correlation, and the resolution's variance is multiplied by the window sums' factor
under it (:meth:`.noise_correlation.NoiseCorrelation.factor`). Where the window has no texture (``H_t`` near 0: air, a
flat region) the resolution is infinite. Measured against true errors in
``docs/evaluation.md`` (``benchmarks/bench_error_estimate.py``). Arrays are on the field's grid
``(nz, ny, nx)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import noise_correlation
from .error_moments import _PAIRS, ErrorMoments
from .error_scales import finest_resolved, node_error_bound
from .node_roughness import deviation_size, node_deviation
from .noise_correlation import NoiseCorrelation

#: Nodes whose error is likely above this many voxels are counted as likely bad
#: (:func:`probability_above`).
LIKELY_BAD = 0.5

#: A node is *likely* above :data:`LIKELY_BAD` where the probability is at least this, and
#: *possibly* above it where it is at least :data:`POSSIBLY` (the estimate plus one standard
#: deviation of its noise reaches the limit: a one-sided 84 % upper bound).
LIKELY = 0.5
POSSIBLY = 0.5 * math.erfc(1.0 / math.sqrt(2.0))  # 1 − Φ(1) = 0.1587

#: The texture's part of each gradient product is kept above this share of the measured one.
MIN_TEXTURE_SHARE = 0.05

#: The moved texture's contrast against the reference's is taken as at least this (below it the
#: two do not match: the residual's excess then speaks, not the step).
MIN_CONTRAST = 0.2

#: Below this contrast of the moved texture against the reference's, the two no longer match
#: (the error is beyond the linear range, or the texture changed): the residual's excess then
#: speaks. Above it, an excess the step leaves unexplained is the error varying inside the
#: window (a band's edge), which the step's mean already measures.
MATCHED_CONTRAST = 0.5

#: How many standard deviations of its noise the residual's unexplained excess variance must
#: reach before it counts as an error beyond the linear range.
UNEXPLAINED_SIGMAS = 4.0


def error_region_half(field) -> int:
    """Half-size of a node's window for the error estimate: one grid step (the largest), within
    the field's subvolume region (:func:`.local_accuracy.region_half`), at least 2 voxels.

    A window reaching the neighbouring nodes, not further: a wider one (the subvolume, 15
    voxels at step 5) spreads a band's error onto nodes two steps away and flags them; a
    narrower one is too noisy on faint texture (``benchmarks/bench_error_estimate.py``): finer
    windows are read only where they resolve (:mod:`.error_scales`)."""
    from .local_accuracy import region_half

    step = int(np.ceil(max(field.step)))
    return max(2, min(region_half(field), step))


def noise_sigma(background: float) -> float:
    """Standard deviation of one scan's noise from eq. 1's ``r0 = E|n_F - n_G| = 2σ/√π``."""
    return float(background) * np.sqrt(np.pi) / 2.0


@dataclass(frozen=True)
class ResidualError:
    """What the residual says of each node's error (voxels, the field's grid).

    Attributes
    ----------
    shift : ndarray, shape (nz, ny, nx, 3)
        ``Δu``, the Gauss-Newton step the window's residual asks for.
    resolved : ndarray, shape (nz, ny, nx)
        ``e_r``: ``|Δu|`` less its noise, or the error that explains an excess the linear model
        does not (see the module); NaN where the window has no defined residual, ``inf`` where it
        has an unexplained excess but no texture.
    resolution : ndarray, shape (nz, ny, nx)
        ``√tr C``: the noise of ``|Δu|``; errors below it do not show (``inf`` without texture).
    unexplained : ndarray of bool, shape (nz, ny, nx)
        Where the residual's excess is beyond what ``Δu`` explains (beyond the linear range).
    """

    shift: np.ndarray
    resolved: np.ndarray
    resolution: np.ndarray
    unexplained: np.ndarray


def residual_error(
    moments: ErrorMoments,
    background: float,
    own_share: float = 0.5,
    correlation: NoiseCorrelation | None = None,
) -> ResidualError:
    """The error each node's window residual resolves (see the module for the model).

    Parameters
    ----------
    moments : ErrorMoments
        Window means of the signed residual, the gray value, its gradient and its smoothed
        gradient, and their products (:func:`.error_moments.moment_volumes`).
    background : float
        ``r0`` of the scan pair (eq. 1), gray levels: the residual's noise has variance
        ``π r0² / 2`` (``2σ²`` for two scans of noise ``σ``).
    own_share : float
        Share of that variance that is the noise of the state the residual lives on (the one
        whose gradient is used): 1/2 for the same noise in both scans in the reference's gray
        levels. (A map's gain cannot tell which: a real rescaling of the loaded scan scales its
        noise too, the dilution of a least-squares map by noise does not.)
    correlation : NoiseCorrelation, optional
        The scans' noise correlation in space (:mod:`.noise_correlation`, measured on the
        pair's residual): the noise's pairings of ``g`` and ``h`` and the variance of the window
        sums follow it. None: white noise.
    """
    correlation = NoiseCorrelation.white() if correlation is None else correlation
    own_pairing = correlation.pairing("g", "g")  # σ²/2 I for white noise
    total = 0.5 * np.pi * float(background) ** 2  # the residual's noise variance
    sigma2 = total * float(own_share)  # the gradient's state's noise variance
    n = np.maximum(moments.count.astype(np.float64), 1.0)
    defined = (moments.count > 1) & np.all(np.isfinite(moments.means), axis=0)
    axes = ("gz", "gy", "gx")

    def cov(a, b):
        return np.where(defined, moments.covariance(a, b), 0.0)

    # covariances over the window (the gray offset out)
    h = np.empty((*moments.count.shape, 3, 3))
    for i, j in _PAIRS:
        h[..., i, j] = h[..., j, i] = cov(axes[i], axes[j])
    a = np.stack([cov(k, "G") for k in axes], axis=-1)
    b = np.stack([cov(k, "s") for k in axes], axis=-1)
    gray = cov("G", "G") - sigma2  # the texture's variance (noise out)
    contrasted = gray > MIN_TEXTURE_SHARE * (gray + sigma2)
    safe_gray = np.where(contrasted, gray, 1.0)
    # the moved texture's contrast against G's: s ≈ (k - 1) G + k g·e + β (G's noise is in s too)
    lift = np.where(contrasted, (cov("G", "s") + sigma2) / safe_gray, 0.0)
    contrast = np.maximum(1.0 + lift, MIN_CONTRAST)
    h_s = (
        h
        - a[..., :, None]
        * a[..., None, :]
        / safe_gray[..., None, None]
        * contrasted[..., None, None]
    )
    b_s = (b - a * lift[..., None]) / contrast[..., None]
    w, v = np.linalg.eigh(h_s)
    w = np.maximum(w, 0.0)
    noise_share = np.trace(own_pairing) / 3.0
    w_t = np.maximum(w - noise_share * sigma2, MIN_TEXTURE_SHARE * w)  # texture's part
    textured = np.all(w_t > 1e-12 * max(1.0, sigma2), axis=-1) & defined
    safe = np.where(textured[..., None], w_t, 1.0)
    coordinates = np.einsum("...ji,...j->...i", v, b_s) / safe  # plain Δu in the eigenbasis
    # the step with the instrument w = (g + h)/2 (see the module): its sensitivity, the
    # noise's pairings of w with g taken out (σ²/2 for central differences, c σ² for h)
    smooth = ("hz", "hy", "hx")
    pairing = 0.5 * sigma2 * (own_pairing + correlation.pairing("h", "g"))
    sensitivity = np.empty(h.shape)
    spread = np.empty(h.shape)
    for i in range(3):
        for j in range(3):
            sensitivity[..., i, j] = 0.5 * (h[..., i, j] + cov(smooth[i], axes[j]))
            spread[..., i, j] = 0.25 * (
                h[..., i, j]
                + cov(axes[i], smooth[j])
                + cov(smooth[i], axes[j])
                + cov(smooth[i], smooth[j])
            )
    sensitivity -= pairing
    a_w = 0.5 * (a + np.stack([cov(k, "G") for k in smooth], axis=-1))
    b_w = 0.5 * (b + np.stack([cov(k, "s") for k in smooth], axis=-1))
    sensitivity -= (
        a_w[..., :, None]
        * a[..., None, :]
        / safe_gray[..., None, None]
        * contrasted[..., None, None]
    )
    spread -= (
        a_w[..., :, None]
        * a_w[..., None, :]
        / safe_gray[..., None, None]
        * contrasted[..., None, None]
    )
    b_w = (b_w - a_w * lift[..., None]) / contrast[..., None]
    determinant = np.linalg.det(np.where(textured[..., None, None], sensitivity, 0.0))
    solvable = textured & (np.abs(determinant) > 0)
    inverse = np.linalg.inv(np.where(solvable[..., None, None], sensitivity, np.eye(3)))
    shift = np.einsum("...ij,...j->...i", inverse, b_w)
    covariance = inverse @ spread @ np.swapaxes(inverse, -1, -2)
    variance = total / n * np.trace(covariance, axis1=-2, axis2=-1) / contrast**2
    variance = variance * correlation.factor(moments.half)  # correlated noise: the step's scatter
    textured = solvable & np.isfinite(variance)
    variance = np.where(textured, variance, 0.0)
    resolution = np.where(textured, np.sqrt(variance), np.inf)
    squared = np.sum(shift * shift, axis=-1)
    resolved = np.sqrt(np.maximum(squared - variance, 0.0))
    # the residual's excess variance (gray offset and gain out) against what the step explains
    excess = cov("s", "s") - lift**2 * gray - total
    explained = contrast**2 * np.sum(w_t * coordinates * coordinates, axis=-1)
    noise = np.sqrt(2.0 * correlation.square_sum) * total / np.sqrt(n)
    unexplained = (
        defined
        & (1.0 + lift < MATCHED_CONTRAST)
        & (excess - explained > UNEXPLAINED_SIGMAS * noise)
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        beyond = np.sqrt(3.0 * np.maximum(excess, 0.0) / np.sum(w_t, axis=-1))
    beyond = np.where(textured, beyond, np.inf)
    resolved = np.where(unexplained, np.maximum(resolved, beyond), resolved)
    resolved = np.where(defined, resolved, np.nan)
    resolution = np.where(defined, resolution, np.nan)
    shift = np.where(textured[..., None], shift, np.nan)
    return ResidualError(shift, resolved, resolution, unexplained)


def noise_error(field) -> np.ndarray:
    """The error the imaging noise alone leaves in each match (voxels): ``|σ_u|``, the norm of
    the field's noise uncertainty (``field.uncertainty``, from the correlation), 0 where it is
    not known (inpainted nodes, fields from other tools: there only the residual speaks)."""
    if field.uncertainty is None:
        return np.zeros(field.shape)
    sigma = np.sqrt(np.sum(np.asarray(field.uncertainty, np.float64) ** 2, axis=-1))
    return np.where(np.isfinite(sigma), sigma, 0.0)


def error_estimate(
    field, moments, background: float, own_share: float = 0.5, correlation=None
) -> tuple[np.ndarray, np.ndarray]:
    """Estimated displacement error per node and the residual's resolution there (voxels);
    ``background``, ``own_share`` and ``correlation`` as in :func:`residual_error` (the
    correlation is used only where :data:`.noise_correlation.NOISE_CORRELATION_APPLIED`). ``moments`` is one
    :class:`ErrorMoments` or one per window, finest first (:mod:`.error_scales`; windows of
    known half-size also bound ``d``).

    Returns
    -------
    estimate : ndarray, shape field.shape
        ``√(e_r² + max(|σ_u|, d)²)`` (:func:`residual_error`, :func:`noise_error`,
        :func:`.node_roughness.node_roughness`); NaN where the node's window has no defined
        residual.
    resolution : ndarray, shape field.shape
        The noise of the residual's estimate: where ``estimate`` is not above it, the residual
        cannot see the node's error and ``estimate`` is an upper bound, not a rank.
    """
    windows = (moments,) if isinstance(moments, ErrorMoments) else tuple(moments)
    if (
        not noise_correlation.NOISE_CORRELATION_APPLIED
        or correlation is None
        or correlation.nearly_white
    ):
        correlation = None  # white noise (within 10 % of the resolution)
    residuals = [residual_error(m, background, own_share, correlation) for m in windows]
    deviation = node_deviation(field.u)
    roughness = np.nan_to_num(deviation_size(deviation), nan=0.0)
    halves = [m.half for m in windows]
    if None not in halves:  # the node's departure, as far as its windows' steps allow it
        bound = node_error_bound(residuals, halves, field.step, deviation)
        roughness = np.minimum(roughness, bound)
    resolved, resolution = finest_resolved(residuals)
    node = np.maximum(noise_error(field), roughness)
    estimate = np.sqrt(resolved**2 + node**2)
    return estimate, resolution


def probability_above(estimate, resolution=None, limit: float = LIKELY_BAD) -> np.ndarray:
    """Probability that each node's error exceeds ``limit`` voxels, given its estimate and the
    residual's resolution there.

    The estimate's noise along the error's direction is taken as Gaussian with the standard
    deviation ``resolution / √3`` (the resolution ``√tr C`` is the norm of the three
    components' noise): ``P = Φ((estimate − limit) / (resolution / √3))``. ``P ≥ ½`` is the
    estimate above ``limit``; ``P ≥ 0.16`` the estimate plus one standard deviation above it
    (a one-sided 84 % upper bound). Where the resolution is not finite or not given the
    estimate decides alone (1 above ``limit``, 0 below); a NaN estimate gives 1 (its region is
    not explained at all).

    Parameters
    ----------
    estimate, resolution : ndarray, same shape
        :func:`error_estimate`'s (voxels).
    limit : float
        Voxels.
    """
    from scipy.special import ndtr

    values = np.asarray(estimate, dtype=np.float64)
    sigma = (
        np.full(values.shape, np.nan)
        if resolution is None
        else np.asarray(resolution, dtype=np.float64) / np.sqrt(3.0)
    )
    known = np.isfinite(values) & np.isfinite(sigma) & (sigma > 0)
    z = np.where(known, (np.where(known, values, 0.0) - limit) / np.where(known, sigma, 1.0), 0.0)
    gauss = ndtr(z)
    step = np.where(np.isnan(values), 1.0, (np.nan_to_num(values, nan=np.inf) > limit) * 1.0)
    return np.where(known, gauss, step)


def error_summary(estimate, nodes=None, resolution=None) -> dict:
    """Median, 95th percentile and the shares of nodes likely and possibly above
    :data:`LIKELY_BAD` (:func:`probability_above` at least :data:`LIKELY` / :data:`POSSIBLY`),
    over ``nodes`` (a boolean grid mask, default all; NaN nodes count as likely bad: their
    region is not explained at all).

    With ``resolution`` (:func:`error_estimate`'s, same grid) also ``resolution`` (its median)
    and ``below_resolution``, the share of nodes whose estimate is not above it: there the
    residual cannot see the error and the estimate is a bound (NaN without ``resolution``).
    ``median_bound`` and ``p95_bound`` are the median and 95th percentile of
    ``max(estimate, resolution)``, what the nodes' errors are known to be under; the median
    (the 95th percentile) is itself only a bound when at least half (95 %) of the nodes are
    below the resolution: ``median_is_bound``, ``p95_is_bound`` (:func:`bounded_text`).
    """
    values = np.asarray(estimate, dtype=np.float64)
    limit = None if resolution is None else np.asarray(resolution, dtype=np.float64)
    if nodes is not None:
        values = values[np.asarray(nodes, bool)]
        limit = None if limit is None else limit[np.asarray(nodes, bool)]
    values = values.ravel()
    nan = float("nan")
    summary = {
        "resolution": nan,
        "below_resolution": nan,
        "median_bound": nan,
        "p95_bound": nan,
        "median_is_bound": False,
        "p95_is_bound": False,
    }
    if values.size == 0:
        empty = {"median": nan, "p95": nan, "likely_bad": nan, "possibly_bad": nan}
        return {**empty, **summary}
    filled = np.where(np.isfinite(values), values, np.inf)
    probability = probability_above(values, None if limit is None else limit.ravel())
    if limit is not None:
        limit = np.where(np.isnan(limit.ravel()), np.inf, limit.ravel())
        below = float(np.mean(filled <= limit))
        upper = np.maximum(filled, limit)
        summary = {
            "resolution": float(np.median(limit)),
            "below_resolution": below,
            "median_bound": float(np.median(upper)),
            "p95_bound": float(np.percentile(upper, 95.0, method="higher")),
            "median_is_bound": below >= 0.5,
            "p95_is_bound": below >= 0.95,
        }
    with np.errstate(invalid="ignore"):  # inf - inf between two undefined nodes
        return {
            "median": float(np.median(filled)),
            "p95": float(np.percentile(filled, 95.0, method="higher")),
            "likely_bad": float(np.mean(probability >= LIKELY)),
            "possibly_bad": float(np.mean(probability >= POSSIBLY)),
            **summary,
        }


def bounded_text(summary: dict, key: str, digits: int = 3) -> str:
    """``summary[key]`` (``"median"`` or ``"p95"`` of :func:`error_summary`) as text: the value,
    or ``"< bound"`` where the residual cannot resolve it (``"< 0.120"``)."""
    if summary.get(f"{key}_is_bound"):
        return f"< {summary[f'{key}_bound']:.{digits}f}"
    return f"{summary[key]:.{digits}f}"


def likely_text(summary: dict) -> str:
    """The shares of nodes likely and possibly above :data:`LIKELY_BAD`, with what they mean."""
    return (
        f"{100 * summary['likely_bad']:.0f} % of nodes likely > {LIKELY_BAD:g} voxel "
        f"(P ≥ ½), {100 * summary['possibly_bad']:.0f} % possibly (P ≥ 16 %)"
    )


#: Key of ``field.metadata`` where an evaluation leaves its estimate (View, exports).
METADATA_KEY = "error_estimate"


def attach_estimate(field, estimate, resolution=None, **info) -> None:
    """Keep ``estimate`` and the residual's ``resolution`` (voxels, the field's grid) in
    ``field.metadata["error_estimate"]`` (JSON-ready: NaN as None, an infinite resolution as
    None too), with ``info`` (e.g. the pair's r0, the residual's frame), so the View panel
    shows them and every export writes them as per-node columns."""
    entry = {"voxels": _grid_list(field, estimate, "estimate")}
    if resolution is not None:
        entry["resolution_voxels"] = _grid_list(field, resolution, "resolution")
    field.metadata[METADATA_KEY] = {**entry, **{k: v for k, v in info.items()}}


def _grid_list(field, values, what: str) -> list:
    values = np.asarray(values, dtype=np.float64)
    if values.shape != tuple(field.shape):
        raise ValueError(f"{what} {values.shape} is not on the field's grid {field.shape}")
    return _none_for_nan(np.where(np.isfinite(values), np.round(values, 6), np.nan).tolist())


def _none_for_nan(values):
    if isinstance(values, list):
        return [_none_for_nan(v) for v in values]
    return None if values != values else values


def estimate_of(field) -> np.ndarray | None:
    """The estimate an evaluation left on ``field`` (voxels, ``field.shape``; NaN where
    undefined), or None."""
    return _metadata_grid(field, "voxels")


def resolution_of(field) -> np.ndarray | None:
    """The residual's resolution an evaluation left on ``field`` next to its estimate (voxels,
    ``field.shape``; NaN where undefined or without texture), or None."""
    return _metadata_grid(field, "resolution_voxels")


def _metadata_grid(field, key: str) -> np.ndarray | None:
    entry = (getattr(field, "metadata", None) or {}).get(METADATA_KEY)
    if not isinstance(entry, dict) or key not in entry:
        return None
    values = np.asarray(entry[key], dtype=np.float64)  # None -> NaN
    return values if values.shape == tuple(field.shape) else None
