"""The window moments of the error estimate (:mod:`.error_estimate`): what each node's window
sums, and the smoothed gradient ``h`` that is the step's instrument.

Per voxel, the signed residual ``s``, the state's gray value ``G``, its central-difference
gradient ``g`` and its smoothed gradient ``h`` (the derivative of a Gaussian of
:data:`INSTRUMENT_SIGMA` voxel), then their products (:data:`MOMENTS`); block by block they are
summed over each node's windows (:mod:`.accuracy_blocks`) into :class:`ErrorMoments`.
:func:`instrument_noise_pairing` is the white noise's pairing of ``h`` with ``g`` at a voxel, which
the step takes out. Arrays are ``(z, y, x)``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

#: Standard deviation (voxels) of the Gaussian whose derivative gives the smoothed gradient
#: ``h`` of the state, the instrument of the step (see :func:`.error_estimate.residual_error`), and the
#: truncation of its kernel in standard deviations: the kernel reaches
#: :data:`INSTRUMENT_RADIUS` voxels, the halo a block reads for it.
INSTRUMENT_SIGMA = 1.0
INSTRUMENT_TRUNCATE = 3.0
INSTRUMENT_RADIUS = int(INSTRUMENT_TRUNCATE * INSTRUMENT_SIGMA + 0.5)

#: Order of the moments gathered per node (:class:`ErrorMoments`): the signed residual ``s``, the
#: state's gray value ``G``, its gradient ``g = (gz, gy, gx)`` and its smoothed gradient
#: ``h = (hz, hy, hx)``, then their products.
MOMENTS = (
    "s", "G", "gz", "gy", "gx",
    "gzgz", "gzgy", "gzgx", "gygy", "gygx", "gxgx",
    "gzG", "gyG", "gxG", "GG",
    "gzs", "gys", "gxs", "Gs", "ss",
    "hz", "hy", "hx",
    "hzgz", "hzgy", "hzgx", "hygz", "hygy", "hygx", "hxgz", "hxgy", "hxgx",
    "hzhz", "hzhy", "hzhx", "hyhy", "hyhx", "hxhx",
    "hzG", "hyG", "hxG",
    "hzs", "hys", "hxs",
)  # fmt: skip
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def smoothed_gradient(values: np.ndarray) -> np.ndarray:
    """``h``: the gradient of ``values`` smoothed by a Gaussian of :data:`INSTRUMENT_SIGMA`
    voxels (its derivative, components ``(z, y, x)``, float32; the volume's edges repeated).
    A voxel's value depends on the voxels within :data:`INSTRUMENT_RADIUS` only, so a block read
    with that halo gives the whole volume's values."""
    from scipy import ndimage

    values = np.asarray(values, dtype=np.float64)
    out = np.zeros((3, *values.shape), np.float32)
    for axis in range(3):
        order = [0, 0, 0]
        order[axis] = 1
        out[axis] = ndimage.gaussian_filter(
            values, INSTRUMENT_SIGMA, order=order, mode="nearest", truncate=INSTRUMENT_TRUNCATE
        )
    return out


@functools.cache
def instrument_noise_pairing() -> float:
    """``E[h_i g_i] / σ²`` for white noise of variance ``σ²``: the pairing of the noise's
    smoothed gradient with its central difference at the same voxel (the same noise in both;
    0 across components)."""
    n = 4 * INSTRUMENT_RADIUS + 3
    impulse = np.zeros((n, n, n))
    impulse[n // 2, n // 2, n // 2] = 1.0
    smoothed = smoothed_gradient(impulse)[0].astype(np.float64)
    central = np.gradient(impulse, axis=0)
    return float(np.sum(smoothed * central))


def moment_volumes(signed: np.ndarray, own: np.ndarray, gradient: np.ndarray):
    """The voxel quantities whose window means make :class:`ErrorMoments`, one at a time in
    :data:`MOMENTS`'s order (a generator of float32 arrays, NaN where ``signed`` is: a block
    holds one product at a time, not forty).

    Parameters
    ----------
    signed : ndarray, shape (nz, ny, nx)
        Signed residual ``s`` (gray levels; NaN where undefined).
    own : ndarray, shape (nz, ny, nx)
        The state the residual lives on, ``G`` (gray levels).
    gradient : ndarray, shape (3 or 6, nz, ny, nx)
        Its gradient ``g``, components ``(z, y, x)`` (gray levels per voxel), then (6
        components) its smoothed gradient ``h`` (:func:`smoothed_gradient`, read with a halo:
        :func:`.accuracy_blocks.halo_gradient`); with 3, ``h`` is taken from ``own`` alone.
    """
    s = np.asarray(signed, np.float32)
    valid = np.isfinite(s)
    nan = np.float32(np.nan)
    gray = np.where(valid, np.asarray(own, np.float32), nan)
    gradient = np.asarray(gradient, np.float32)
    if gradient.shape[0] == 3:
        gradient = np.concatenate([gradient, smoothed_gradient(own)])
    g = np.where(valid[None], gradient[:3], nan)
    h = np.where(valid[None], gradient[3:6], nan)
    yield from (s, gray, g[0], g[1], g[2])
    for i, j in _PAIRS:
        yield g[i] * g[j]
    for i in range(3):
        yield g[i] * gray
    yield gray * gray
    for i in range(3):
        yield g[i] * s
    yield gray * s
    yield s * s
    yield from (h[0], h[1], h[2])
    for i in range(3):
        for j in range(3):
            yield h[i] * g[j]
    for i, j in _PAIRS:
        yield h[i] * h[j]
    for i in range(3):
        yield h[i] * gray
    for i in range(3):
        yield h[i] * s


@dataclass(frozen=True)
class ErrorMoments:
    """Window means per node of the quantities of :func:`moment_volumes`.

    Attributes
    ----------
    count : ndarray, shape (nz, ny, nx), int64
        Voxels with a defined residual in each node's window.
    means : ndarray, shape (len(MOMENTS), nz, ny, nx), float64
        Their means, in :data:`MOMENTS`'s order (NaN where ``count`` is 0).
    half : int or None
        The windows' half-size in voxels (None: not known; the estimate then reads this one
        window alone).
    """

    count: np.ndarray
    means: np.ndarray
    half: int | None = None

    @classmethod
    def from_sums(
        cls, sums: np.ndarray, count: np.ndarray, half: int | None = None
    ) -> ErrorMoments:
        """From the window sums ``(len(MOMENTS), nz, ny, nx)``, the voxel count and the half-size."""
        count = np.asarray(count, np.int64)
        with np.errstate(invalid="ignore", divide="ignore"):
            means = np.where(count > 0, sums / np.maximum(count, 1), np.nan)
        return cls(count, means, None if half is None else int(half))

    def mean(self, name: str) -> np.ndarray:
        return self.means[MOMENTS.index(name)]

    def covariance(self, a: str, b: str) -> np.ndarray:
        """``<a b> - <a><b>`` over each window (``a``, ``b`` among ``s, G, gz, gy, gx, hz, hy,
        hx``)."""
        key = a + b if a + b in MOMENTS else b + a
        return self.mean(key) - self.mean(a) * self.mean(b)

    @property
    def rms_gradient(self) -> np.ndarray:
        """``sqrt(<|grad G|²>)`` (gray levels per voxel), noise included."""
        return np.sqrt(self.mean("gzgz") + self.mean("gygy") + self.mean("gxgx"))
