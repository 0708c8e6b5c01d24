"""The scans' noise correlation in space, measured on the pair's residual, for the error estimate.

Real CT noise is not white: reconstruction filters and detector blur correlate it over a voxel or
two. The error estimate (:mod:`.error_estimate`) takes two things out of, or into, its step that
depend on it:

- **the noise's pairings** at a voxel: the noise of the central-difference gradient ``g`` with
  itself (``σ²(1 − ρ(2))/2`` per axis, ``σ²/2`` for white noise) and of the smoothed gradient
  ``h`` with ``g`` (``c σ²``, :func:`.error_moments.instrument_noise_pairing` for white noise):
  in general ``E[(a∗n)(b∗n)] = σ² Σ_m (a ⋆ b)(m) ρ(m)`` for two filters ``a``, ``b``
  (:meth:`NoiseCorrelation.pairing`);
- **the resolution**: a window sum ``Σ w n`` of correlated noise has the variance
  ``σ² Σ_ij w_i w_j ρ(i − j)``, ``n σ² W f`` with ``f = Σ_k ρ(k) ρ_w(k)`` (``ρ_w`` the
  autocorrelation of the instrument ``w`` less its local mean): :attr:`NoiseCorrelation.window_factor`
  multiplies the step's noise covariance (1 for white noise), and ``Σ_k ρ(k)²`` the variance of
  the residual's variance (:attr:`NoiseCorrelation.square_sum`).

``ρ`` cannot be read from one scan: its finest texture and a correlated noise look alike (the
mixed differences of a two-phase texture under white noise read as a lag-1 correlation of 0.3).
The two scans share the texture and not the noise, so ``ρ`` is read on the pair's residual
``s = map(F~) − G`` with the best field (the one ``r0`` is measured with, :mod:`.accuracy_pair`),
on the central block of :func:`.gray_noise.noise_box` (the same block in memory and tiled): its
autocovariance at lags up to :data:`MAX_LAG` along each axis (3-D, robust to outliers), over the
block's flattest :data:`FLAT_SHARE` of voxels (:func:`flat_voxels`: a field's own error ``e``
leaves ``∇G·e`` in the residual, correlated as the texture's gradient is, and least where the
texture is flat; white noise with a 0.5-voxel band in the field then reads white, tested). The
pull-back's cubic B-spline correlates ``F``'s noise at fractional positions (a lag-1
correlation of 0.16 at a fraction 0.3, 0.26 at 0.5); with both scans' noise of one correlation
and variance, ``R_s = σ² (ρ + Γ ⋆ ρ)``, ``Γ`` the interpolation's autocorrelation at the field's
fractional parts, which is solved for ``ρ`` (:func:`measure_noise_correlation`). Lags whose
correlation is within :data:`SIGNIFICANCE` standard errors of 0 are set to 0, so white noise
reads exactly white. Arrays are ``(z, y, x)``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

#: Largest lag (voxels) of the correlation along each axis.
MAX_LAG = 3

#: A lag's measured correlation counts where it is at least this many standard errors
#: (``1/√pairs``) from 0.
SIGNIFICANCE = 5.0

#: The residual's voxels farther than this many robust standard deviations from its median are
#: left out (a crack, a missed region).
CLIP = 3.5

#: The correlation is read on this share of the block's voxels: those where the texture is
#: flattest (:func:`flat_voxels`), where a field's own error leaves least in the residual.
FLAT_SHARE = 0.4

#: Gaussian smoothing (voxels) of the texture before its gradient, and of the gradient's
#: energy after, that rank the voxels by flatness (:func:`flat_voxels`).
FLAT_SMOOTHING = (1.0, 2.0)

_L = MAX_LAG
_BOX = 2 * MAX_LAG + 1


def _white() -> np.ndarray:
    rho = np.zeros((_BOX,) * 3)
    rho[_L, _L, _L] = 1.0
    return rho


#: Whether :func:`.error_estimate.error_estimate` uses the pair's measured noise correlation
#: (this module's; a nearly white one, within 10 % of the resolution, never). Off
#: (white noise, as before): read on the flattest voxels of the best field's residual, the
#: white-noise cases of the benchmarks read white, but where the texture has no flat region (a
#: noise-free two-phase texture, our DVC's fields of the narrow band cases) the correlation still
#: reads the field's own error, and applied it loses catches near 0.5 voxel (docs/evaluation.md,
#: "Spatially correlated noise"); the pair still measures and reports it.
NOISE_CORRELATION_APPLIED = False


@dataclass(frozen=True)
class NoiseCorrelation:
    """One scan's noise correlation ``ρ`` (lags ``−MAX_LAG…MAX_LAG`` per axis, ``ρ[L, L, L] =
    1``) and the variance factor of the estimate's window sums (see the module).

    Attributes
    ----------
    rho : ndarray, shape (2L+1, 2L+1, 2L+1)
        Normalised autocorrelation of each scan's noise, axes (z, y, x).
    factors : dict of int -> float
        Window half-size -> what the step's white-noise variance is multiplied by
        (:func:`window_factors`; empty: 1).
    """

    rho: np.ndarray
    factors: dict

    @classmethod
    def white(cls) -> NoiseCorrelation:
        return cls(_white(), {})

    @property
    def is_white(self) -> bool:
        return bool(np.array_equal(self.rho, _white()) and not self.factors)

    def factor(self, half: int | None) -> float:
        """The step's variance factor in a window of half-size ``half`` (the nearest measured
        one; None: the largest), 1 without any."""
        if not self.factors:
            return 1.0
        halves = sorted(self.factors)
        near = halves[-1] if half is None else min(halves, key=lambda h: (abs(h - half), -h))
        return float(self.factors[near])

    def along(self, axis: int) -> np.ndarray:
        """``ρ`` at lags 1…L along ``axis`` (0: z)."""
        index = [_L, _L, _L]
        out = []
        for k in range(1, _L + 1):
            index[axis] = _L + k
            out.append(float(self.rho[tuple(index)]))
        return np.array(out)

    @property
    def square_sum(self) -> float:
        """``Σ_k ρ(k)²``: the variance of a window's mean square is this times the white one's."""
        return float(np.sum(self.rho**2))

    def pairing(self, first: str, second: str) -> np.ndarray:
        """``E[a_i b_j] / σ²`` (3×3) of the noise filtered by ``first`` and ``second`` (``"g"``:
        central differences, ``"h"``: the smoothed gradient), components (z, y, x). White noise:
        ``I/2`` for ``g`` with ``g``, ``c I`` for ``h`` with ``g``
        (:func:`.error_moments.instrument_noise_pairing`), to the last digit."""
        if np.array_equal(self.rho, _white()) and (first, second) in (("g", "g"), ("h", "g")):
            from .error_moments import instrument_noise_pairing

            return (0.5 if first == "g" else instrument_noise_pairing()) * np.eye(3)
        return _pairing(first, second, _key(self.rho))

    @property
    def spread(self) -> float:
        """``√`` of the largest window factor: how many times the white-noise resolution the
        resolution under this noise is, at most (1 without factors)."""
        return float(np.sqrt(max(self.factors.values(), default=1.0)))

    @property
    def nearly_white(self) -> bool:
        """White, or changing the resolution by less than 10 % (:attr:`spread` in 0.9–1.1):
        the error estimate then takes the noise as white (:func:`.error_estimate.error_estimate`)."""
        return self.is_white or 0.9 <= self.spread < 1.1

    def describe(self, applied: bool | None = None) -> str:
        """One line for the reports: the correlation one voxel apart along z, y, x and what it
        does to the error estimate's resolution. ``applied``: whether the estimate uses it
        (None: :data:`NOISE_CORRELATION_APPLIED`); a nearly white one is taken
        as white either way (:attr:`nearly_white`)."""
        if self.is_white:
            return "scan noise white in space (no correlation 1–3 voxels apart)"
        if applied is None:
            applied = NOISE_CORRELATION_APPLIED
        one = "/".join(f"{self.along(axis)[0]:.2f}" for axis in range(3))
        spread = self.spread
        if self.nearly_white:
            return (
                f"scan noise nearly white in space (ρ one voxel apart, z/y/x: {one}): the error "
                "estimate's white-noise resolution holds within 10 %"
            )
        head = f"scan noise correlated in space (ρ one voxel apart, z/y/x: {one})"
        if applied:
            bound = "up to" if spread >= 1.1 else "down to"
            return (
                head + f": the error estimate takes it into account (its resolution {bound} "
                f"{spread:.1f}× the white-noise one)"
            )
        side = "small" if spread >= 1.1 else "large"
        by = spread if spread >= 1.1 else 1.0 / max(spread, 1e-3)
        return (
            head + f": the error estimate takes it as white, so its resolution may read up to "
            f"{by:.1f}× {side}"
        )

    def to_dict(self) -> dict:
        return {
            "lags_zyx": [self.along(a).round(4).tolist() for a in range(3)],
            "window_factors": {str(k): round(float(v), 4) for k, v in self.factors.items()},
            "rho": np.round(self.rho, 6).tolist(),
        }

    @classmethod
    def from_dict(cls, values: dict | None) -> NoiseCorrelation | None:
        if not values:
            return None
        factors = {int(k): float(v) for k, v in values.get("window_factors", {}).items()}
        return cls(np.asarray(values["rho"], np.float64), factors)


def _key(rho: np.ndarray) -> tuple:
    return tuple(np.asarray(rho, np.float64).ravel().tolist())


def _responses(kind: str, size: int) -> np.ndarray:
    from .accuracy_blocks import gradient_components
    from .error_moments import smoothed_gradient

    impulse = np.zeros((size,) * 3)
    impulse[size // 2, size // 2, size // 2] = 1.0
    if kind == "g":
        return gradient_components(impulse).astype(np.float64)
    return smoothed_gradient(impulse).astype(np.float64)


@functools.lru_cache(maxsize=32)
def _pairing(first: str, second: str, rho_key: tuple) -> np.ndarray:
    from .error_moments import INSTRUMENT_RADIUS

    rho = np.asarray(rho_key).reshape((_BOX,) * 3)
    size = 4 * INSTRUMENT_RADIUS + 3 + 2 * _L
    a, b = _responses(first, size), _responses(second, size)
    out = np.zeros((3, 3))
    for j in range(3):
        spread = ndimage.convolve(b[j], rho, mode="constant")  # ρ is symmetric
        for i in range(3):
            out[i, j] = float(np.sum(a[i] * spread))
    return out


def autocovariance(values: np.ndarray, valid: np.ndarray | None = None):
    """Autocovariance of ``values`` (3-D) at lags ``−L…L`` per axis over the voxels ``valid``
    (and finite), its mean taken out, and the number of voxel pairs at each lag.

    Returns
    -------
    covariance, pairs : ndarray, shape (2L+1, 2L+1, 2L+1)
    """
    from scipy import fft

    v = np.asarray(values, np.float64)
    mask = np.isfinite(v) if valid is None else (np.asarray(valid, bool) & np.isfinite(v))
    if mask.sum() < 2:
        return np.zeros((_BOX,) * 3), np.zeros((_BOX,) * 3)
    centred = np.where(mask, v - v[mask].mean(), 0.0)
    size = [fft.next_fast_len(n + _L, real=True) for n in v.shape]  # linear up to lag L
    lags = np.ix_(*(np.arange(-_L, _L + 1) % n for n in size))

    def correlation(a):
        spectrum = fft.rfftn(a, s=size)
        return fft.irfftn(spectrum * np.conj(spectrum), s=size)[lags]

    products = correlation(centred)
    pairs = np.rint(correlation(mask.astype(np.float64)))
    with np.errstate(invalid="ignore", divide="ignore"):
        covariance = np.where(pairs > 0, products / np.maximum(pairs, 1.0), 0.0)
    return covariance, pairs


def _cardinal_table(samples: int = 65) -> tuple[np.ndarray, np.ndarray]:
    """``t`` and the autocorrelation ``γ_t(m) = Σ_j η(t − j) η(t + m − j)``, ``m = −L−1…L+1``, of
    white noise sampled by the cubic B-spline interpolant (``η`` its cardinal function) at a
    fractional position ``t``."""
    delta = np.zeros(65)
    delta[32] = 1.0
    coefficients = ndimage.spline_filter1d(delta, order=3, mode="mirror")
    t = np.linspace(0.0, 1.0, samples)
    offsets = np.arange(-20, 21)
    eta = ndimage.map_coordinates(
        coefficients,
        (32.0 + t[:, None] + offsets[None, :]).reshape(1, -1),
        order=3,
        prefilter=False,
        mode="mirror",
    ).reshape(samples, offsets.size)
    lags = np.arange(-_L - 1, _L + 2)
    gamma = np.zeros((samples, lags.size))
    for k, m in enumerate(lags):
        gamma[:, k] = np.sum(eta * np.roll(eta, -m, axis=1), axis=1)
    return t, gamma


_TABLE_T, _TABLE_GAMMA = _cardinal_table()

#: At most this many nodes' fractional parts make the interpolation's autocorrelation.
_MAX_NODES = 4096


def interpolation_autocorrelation(displacement) -> np.ndarray:
    """``Γ``: the autocorrelation (lags ``−L−1…L+1`` per axis) of white noise of unit variance
    sampled at ``X + u``, averaged over the nodes ``displacement`` (N, 3), voxels (the product
    of the three axes' ``γ``; a whole-voxel field gives ``δ``)."""
    u = np.asarray(displacement, np.float64).reshape(-1, 3)
    u = u[np.all(np.isfinite(u), axis=1)]
    size = 2 * _L + 3
    if not len(u):
        out = np.zeros((size,) * 3)
        out[(_L + 1,) * 3] = 1.0
        return out
    if len(u) > _MAX_NODES:
        u = u[np.linspace(0, len(u) - 1, _MAX_NODES).astype(int)]
    fraction = u - np.floor(u)
    per_axis = [
        np.stack([np.interp(fraction[:, a], _TABLE_T, _TABLE_GAMMA[:, k]) for k in range(size)], 1)
        for a in range(3)
    ]
    return np.einsum("na,nb,nc->abc", *per_axis) / len(u)


def _unmix(covariance: np.ndarray, interpolation: np.ndarray) -> np.ndarray:
    """``x`` on the lags ``−L…L`` with ``x + Γ ⋆ x = covariance`` there (``x`` taken 0 beyond)."""
    lags = np.stack(np.meshgrid(*(np.arange(-_L, _L + 1),) * 3, indexing="ij"), -1).reshape(-1, 3)
    difference = lags[:, None, :] - lags[None, :, :]
    reach = _L + 1
    inside = np.all(np.abs(difference) <= reach, axis=-1)
    index = np.clip(difference + reach, 0, 2 * reach)
    matrix = np.where(inside, interpolation[index[..., 0], index[..., 1], index[..., 2]], 0.0)
    matrix += np.eye(len(lags))
    return np.linalg.solve(matrix, covariance.ravel()).reshape(covariance.shape)


def correlated_noise(rho: np.ndarray, shape, seed: int) -> np.ndarray:
    """Gaussian noise of unit variance whose autocorrelation is ``rho`` (lags ``−L…L``; its
    spectrum's negative part clipped), on ``shape`` (periodic)."""
    padded = np.zeros(shape)
    for index in np.ndindex(rho.shape):
        if rho[index] != 0.0:
            padded[tuple((i - _L) % n for i, n in zip(index, shape))] = rho[index]
    filter_ = np.sqrt(np.maximum(np.fft.rfftn(padded).real, 0.0))
    white = np.random.default_rng(seed).standard_normal(shape)
    noise = np.fft.irfftn(np.fft.rfftn(white) * filter_, s=shape)
    return noise / max(float(noise.std()), 1e-12)


#: Half-sizes (voxels) at which :func:`window_factors` gives the factor (a window of another
#: half-size takes the nearest).
FACTOR_HALVES = (2, 3, 4, 5, 6, 8, 10, 12)

#: Size (voxels) of the local mean taken out of the instrument before its autocorrelation (a
#: window of the estimate's middle size: half-size 3).
LOCAL_MEAN = 7


def instrument_autocorrelation(own: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """``ρ_w``: the autocorrelation (lags ``−L…L``) of the instrument ``w = (g + h)/2`` of the
    state ``own`` less its local mean (:data:`LOCAL_MEAN` voxels), averaged over its three
    components, over ``valid`` voxels at least :data:`.error_moments.INSTRUMENT_RADIUS` from the
    block's faces."""
    from .accuracy_blocks import gradient_components
    from .error_moments import INSTRUMENT_RADIUS, smoothed_gradient

    values = np.asarray(own, np.float64)
    w = 0.5 * (gradient_components(values).astype(np.float64) + smoothed_gradient(values))
    keep = np.zeros(values.shape, bool)
    r = INSTRUMENT_RADIUS
    keep[r:-r, r:-r, r:-r] = True
    if valid is not None:
        keep &= np.asarray(valid, bool)
    out = np.zeros((_BOX,) * 3)
    used = 0
    for component in w:
        local = component - ndimage.uniform_filter(component, LOCAL_MEAN, mode="nearest")
        covariance, _ = autocovariance(local, keep)
        if covariance[_L, _L, _L] > 0:
            out += covariance / covariance[_L, _L, _L]
            used += 1
    return out / used if used else _white()


def window_factors(rho: np.ndarray, instrument: np.ndarray) -> dict:
    """Per window half-size ``h``, the variance of a window sum ``Σ w n`` of noise of
    autocorrelation ``rho`` against white noise's: ``Σ_k ρ(k) ρ_w(k) Π_c (N − |k_c|)/N``,
    ``N = 2h + 1`` (pairs of voxels ``k`` apart inside the window), ``ρ_w`` the instrument's
    autocorrelation (:func:`instrument_autocorrelation`)."""
    lags = np.abs(np.arange(-_L, _L + 1))
    out = {}
    for half in FACTOR_HALVES:
        n = 2 * half + 1
        inside = np.clip((n - lags) / n, 0.0, None)
        edge = inside[:, None, None] * inside[None, :, None] * inside[None, None, :]
        out[half] = max(float(np.sum(rho * instrument * edge)), 0.0)
    return out


def flat_voxels(residual: np.ndarray, own: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The :data:`FLAT_SHARE` of the ``valid`` voxels where the texture is flattest: the lowest
    energy ``|∇ m|²`` of the two scans' mean ``m = G + s/2 = (G + map(F~))/2``, both smoothed
    (:data:`FLAT_SMOOTHING`).

    A field wrong by ``e`` leaves ``∇G·e`` in the residual, which is correlated in space as the
    texture's gradient is, and reads as correlated noise; where the texture is flat it leaves
    (nearly) nothing, while the scans' noise is there as everywhere. ``m`` rather than ``G``:
    its noise ``(n_F + n_G)/2`` is uncorrelated with the residual's ``n_F − n_G`` (the same
    noise in both scans), so the voxels are not picked by the residual's own noise, which ``G``
    alone (holding ``n_G``) would do; the smoothing makes the choice depend on the noise only
    through averages over many voxels (white noise reads white on them, tested, also on a
    texture-free pair). Where the "noise" is not stationary (a noise-free pair: the
    interpolators' difference, smallest where the texture is flat) the flat voxels read it
    differently from the rest (docs/evaluation.md)."""
    from .accuracy_blocks import gradient_components

    before, after = FLAT_SMOOTHING
    mean = np.asarray(own, np.float64) + 0.5 * np.where(valid, residual, 0.0)
    mean = ndimage.gaussian_filter(np.nan_to_num(mean), before, mode="nearest")
    energy = np.sum(gradient_components(mean).astype(np.float64) ** 2, axis=0)
    energy = ndimage.gaussian_filter(energy, after, mode="nearest")
    if valid.sum() < 8:
        return valid
    return valid & (energy <= np.quantile(energy[valid], FLAT_SHARE))


def measure_noise_correlation(
    residual: np.ndarray, own: np.ndarray, displacement
) -> NoiseCorrelation:
    """The scans' :class:`NoiseCorrelation` from the pair's residual on a block.

    Parameters
    ----------
    residual : ndarray, shape (nz, ny, nx)
        ``map(F~) − G`` with the pair's best field on the block (:func:`.gray_noise.noise_box`),
        NaN where undefined.
    own : ndarray, shape (nz, ny, nx)
        ``G`` on the same block (the instrument's autocorrelation: :func:`window_factors`).
    displacement : ndarray, shape (N, 3)
        The best field's node displacements (voxels): the pull-back's fractional parts.
    """
    s = np.asarray(residual, np.float64)
    valid = np.isfinite(s)
    if valid.sum() < 8 or min(s.shape) < 2 * _L + 2:
        return NoiseCorrelation.white()
    centre = np.median(s[valid])
    spread = 1.4826 * np.median(np.abs(s[valid] - centre))
    if spread > 0:
        valid &= np.abs(np.where(valid, s, centre) - centre) <= CLIP * spread
    covariance, pairs = autocovariance(s, flat_voxels(s, own, valid))
    if covariance[_L, _L, _L] <= 0:
        return NoiseCorrelation.white()
    unmixed = _unmix(covariance, interpolation_autocorrelation(displacement))
    if unmixed[_L, _L, _L] <= 0:
        return NoiseCorrelation.white()
    rho = unmixed / unmixed[_L, _L, _L]
    noise = SIGNIFICANCE / np.sqrt(np.maximum(pairs, 1.0))
    rho = np.where(np.abs(rho) >= noise, rho, 0.0)
    rho = 0.5 * (rho + rho[::-1, ::-1, ::-1])  # an autocorrelation is symmetric
    rho[_L, _L, _L] = 1.0
    if np.array_equal(rho, _white()):
        return NoiseCorrelation.white()
    return NoiseCorrelation(rho, window_factors(rho, instrument_autocorrelation(own, valid)))
