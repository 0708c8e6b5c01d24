"""An error estimate in voxels per node, from the gray residual.

The accuracy index of eq. 2 measures the gray mismatch in units of the phase contrast: any field
with errors under a voxel scores above 0.99, so it cannot tell a field that is 0.5 voxel off in
a band from a good one. This module turns the same gray-level-corrected residual into a
displacement error, node by node:

- a displacement error ``e`` (voxels) moves the residual by ``grad G · e``; over a node's region,
  with the error's direction random against the texture's gradients, the misplaced texture adds
  a gray difference of variance ``e² <|grad G|²> / 3``;
- the imaging noise leaves a residual ``|n|`` of mean ``r0`` (eq. 1's background residual,
  ``r0 = sqrt(2/π) σ`` for Gaussian noise of standard deviation ``σ``);
- with both Gaussian, the mean residual over the region is
  ``R = sqrt(2/π) sqrt(σ² + e² g² / 3)``, ``g² = <|grad G|²>``, so

  ``e_res = sqrt(3 π / 2 · max(R² − r0², 0)) / g``.

It is combined in quadrature with the noise-based uncertainty of the match
(``field.uncertainty``, the error the imaging noise alone leaves where the residual cannot see
it): ``e = sqrt(e_res² + |σ_u|²)``. Measured against true errors in ``docs/evaluation.md``
(``benchmarks/bench_error_estimate.py``). Arrays are on the field's grid ``(nz, ny, nx)``.
"""

from __future__ import annotations

import numpy as np

#: Nodes whose estimated error exceeds this many voxels are counted as likely bad.
LIKELY_BAD = 0.5

#: The texture's gradient is kept above this share of the measured one (noise included).
MIN_TEXTURE_SHARE = 0.05

#: ``3 π / 2``: turns the excess of the squared mean residual over the noise's into the
#: misplaced texture's variance (see the module).
_FACTOR = 1.5 * np.pi


def error_region_half(field) -> int:
    """Half-size of a node's region for the error estimate: the field's subvolume region
    (:func:`.local_accuracy.region_half`), where the match measured the node. Measured against
    the node's own cell (edge ``2 ceil(step / 2) + 1``) in ``benchmarks/bench_error_estimate.py``:
    on faint CT texture at 3 % noise the cell's residual is too noisy (13 % of the nodes of the
    exact field flagged above 0.5 voxel, against 1 % with the subvolume region), while the
    subvolume still catches 98-99 % of the nodes off by more than 0.5 voxel in a 12-voxel band.
    """
    from .local_accuracy import region_half

    return region_half(field)


def noise_sigma(background: float) -> float:
    """Standard deviation of one scan's noise from eq. 1's ``r0 = E|n_F - n_G| = 2σ/√π``."""
    return float(background) * np.sqrt(np.pi) / 2.0


def texture_gradient(local_gradient, background: float) -> np.ndarray:
    """The texture's RMS gradient: the measured one less the noise's (central differences of
    white noise of variance ``σ²`` have ``|grad n|²`` of mean ``1.5 σ²``), kept above
    :data:`MIN_TEXTURE_SHARE` of the measured one."""
    g2 = np.asarray(local_gradient, dtype=np.float64) ** 2
    sigma = noise_sigma(background)
    return np.sqrt(np.maximum(g2 - 1.5 * sigma * sigma, MIN_TEXTURE_SHARE * g2))


def residual_error(local_residual, local_gradient, background: float) -> np.ndarray:
    """The error the residual's excess over the noise explains, per node (voxels).

    Parameters
    ----------
    local_residual : ndarray, shape (nz, ny, nx)
        Mean gray-level-corrected residual over each node's cell ``R`` (reference gray levels;
        NaN where undefined).
    local_gradient : ndarray, shape (nz, ny, nx)
        RMS gray gradient ``sqrt(<|grad G|²>)`` over the same cells (gray levels per voxel),
        noise included (:func:`texture_gradient` takes it out).
    background : float
        ``r0`` of the scan pair (eq. 1), gray levels.

    Returns
    -------
    ndarray, float64, voxels
        ``sqrt(3π/2 · max(R² − r0², 0)) / g``; NaN where ``R`` is undefined, ``inf`` where the
        region has an excess but no gradient (flat texture: the residual cannot say).
    """
    r = np.asarray(local_residual, dtype=np.float64)
    g = texture_gradient(local_gradient, background)
    r0 = float(background)
    excess = np.maximum(r * r - r0 * r0, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        error = np.sqrt(_FACTOR * excess) / g
    error = np.where((excess == 0) & np.isfinite(r), 0.0, error)
    return np.where(np.isfinite(r), error, np.nan)


def noise_error(field, local_gradient=None, background: float | None = None) -> np.ndarray:
    """The error the imaging noise alone leaves in each match (voxels).

    ``|σ_u|``, the norm of the field's noise uncertainty where it is known
    (``field.uncertainty``, from the correlation); elsewhere (inpainted nodes, fields from
    other tools) the translation uncertainty of a subvolume of ``n`` voxels with the texture's
    gradient ``g`` and noise ``σ`` on both scans, ``|σ_u| = 3 √2 σ / (g √n)`` (the
    least-squares covariance ``2 σ² (Σ ∂G ∂Gᵀ)⁻¹`` with isotropic texture); 0 without
    ``local_gradient``.
    """
    floor = np.zeros(field.shape)
    if local_gradient is not None and background is not None:
        from .local_accuracy import region_half

        n = (2 * region_half(field) + 1) ** 3
        g = texture_gradient(local_gradient, background)
        with np.errstate(divide="ignore", invalid="ignore"):
            floor = 3.0 * np.sqrt(2.0) * noise_sigma(background) / (g * np.sqrt(n))
        floor = np.where(np.isfinite(floor), floor, 0.0)
    if field.uncertainty is None:
        return floor
    sigma = np.sqrt(np.sum(np.asarray(field.uncertainty, np.float64) ** 2, axis=-1))
    return np.where(np.isfinite(sigma), sigma, floor)


def error_estimate(field, local_residual, local_gradient, background: float) -> np.ndarray:
    """Estimated displacement error per node (voxels): :func:`residual_error` and
    :func:`noise_error` in quadrature. NaN where the node's cell has no defined residual."""
    e_res = residual_error(local_residual, local_gradient, background)
    return np.sqrt(e_res**2 + noise_error(field, local_gradient, background) ** 2)


def error_summary(estimate, nodes=None) -> dict:
    """Median, 95th percentile and share of nodes above :data:`LIKELY_BAD` (over ``nodes``, a
    boolean grid mask, default all; NaN nodes count as likely bad: their region is not
    explained at all)."""
    values = np.asarray(estimate, dtype=np.float64)
    if nodes is not None:
        values = values[np.asarray(nodes, bool)]
    values = values.ravel()
    if values.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "likely_bad": float("nan")}
    filled = np.where(np.isfinite(values), values, np.inf)
    with np.errstate(invalid="ignore"):  # inf - inf between two undefined nodes
        return {
            "median": float(np.median(filled)),
            "p95": float(np.percentile(filled, 95.0, method="higher")),
            "likely_bad": float(np.mean(filled > LIKELY_BAD)),
        }


#: Key of ``field.metadata`` where an evaluation leaves its estimate (View, exports).
METADATA_KEY = "error_estimate"


def attach_estimate(field, estimate, **info) -> None:
    """Keep ``estimate`` (voxels, the field's grid) in ``field.metadata["error_estimate"]``
    (JSON-ready: NaN as None), with ``info`` (e.g. the pair's r0, the residual's frame), so the
    View panel shows it and every export writes it as a per-node column."""
    values = np.asarray(estimate, dtype=np.float64)
    if values.shape != tuple(field.shape):
        raise ValueError(f"estimate {values.shape} is not on the field's grid {field.shape}")
    as_list = np.where(np.isfinite(values), np.round(values, 6), np.nan).tolist()
    field.metadata[METADATA_KEY] = {
        "voxels": _none_for_nan(as_list),
        **{k: v for k, v in info.items()},
    }


def _none_for_nan(values):
    if isinstance(values, list):
        return [_none_for_nan(v) for v in values]
    return None if values != values else values


def estimate_of(field) -> np.ndarray | None:
    """The estimate an evaluation left on ``field`` (voxels, ``field.shape``; NaN where
    undefined), or None."""
    entry = (getattr(field, "metadata", None) or {}).get(METADATA_KEY)
    if not isinstance(entry, dict) or "voxels" not in entry:
        return None
    values = np.asarray(entry["voxels"], dtype=np.float64)  # None -> NaN
    return values if values.shape == tuple(field.shape) else None
