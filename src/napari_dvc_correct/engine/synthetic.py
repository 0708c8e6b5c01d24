"""Synthetic volumes with known displacement fields: for tests, benchmarks and the sample data.

Everything is deterministic given ``seed``. Deformed volumes are made by sampling the reference
pattern with a 5th-order spline (not the cubic B-spline the matcher uses), so tests do not reward an
interpolator for agreeing with itself.

A displacement is given as a function ``u(points) -> (N, 3)`` of reference positions (Lagrangian,
z, y, x voxels). The deformed volume satisfies ``F(X + u(X)) = G(X)``: each voxel ``x`` of F is
filled from ``G(X)`` with ``X`` the solution of ``X + u(X) = x`` (fixed-point iteration).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage

DisplacementFunction = Callable[[np.ndarray], np.ndarray]


def textured_volume(shape, feature_size: float = 2.0, seed: int = 0) -> np.ndarray:
    """Speckle-like volume with good texture: smoothed white noise scaled to [0, 1].

    Parameters
    ----------
    shape : tuple of 3 ints
        ``(nz, ny, nx)``.
    feature_size : float
        Gaussian smoothing sigma in voxels (the speckle size is about 2-3 times this).
    seed : int
        Random seed.

    Returns
    -------
    ndarray, float32, shape ``shape``
    """
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal(tuple(int(n) for n in shape))
    smooth = ndimage.gaussian_filter(noise, feature_size, mode="wrap")
    smooth -= smooth.min()
    smooth /= smooth.max()
    return smooth.astype(np.float32)


def two_phase_volume(
    shape,
    grain_fraction: float = 0.35,
    grain_size: float = 3.0,
    phase_grays: tuple[float, float] = (100.0, 170.0),
    texture: float = 8.0,
    seed: int = 0,
) -> np.ndarray:
    """Soil-like volume with poor texture: bright grains (quartz) in a darker matrix (clay).

    The grains are the thresholded level set of a smoothed random field, so they have rounded
    blobby shapes of about ``2 * grain_size`` voxels; a weak smooth texture of amplitude ``texture``
    gray levels lives inside both phases. Noise is not added here (see :func:`add_noise`).

    Returns
    -------
    ndarray, float32, gray values around ``phase_grays``.
    """
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in shape)
    field = ndimage.gaussian_filter(rng.standard_normal(shape), grain_size, mode="wrap")
    level = np.quantile(field, 1.0 - grain_fraction)
    # soft edge (about one voxel wide) so the phase boundary is band-limited
    edge = 1.0 / (1.0 + np.exp(-(field - level) / (0.15 * field.std())))
    fine = ndimage.gaussian_filter(rng.standard_normal(shape), 1.2, mode="wrap")
    fine /= fine.std()
    low, high = phase_grays
    volume = low + (high - low) * edge + texture * fine
    return volume.astype(np.float32)


def add_noise(volume: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
    """``volume`` plus Gaussian noise of standard deviation ``sigma`` (gray levels), float32."""
    rng = np.random.default_rng(seed)
    return (volume + rng.normal(0.0, sigma, volume.shape)).astype(np.float32)


def _node_positions(shape) -> np.ndarray:
    grids = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    return np.stack([g.ravel() for g in grids], axis=1)


def invert_displacement(
    displacement: DisplacementFunction,
    positions: np.ndarray,
    iterations: int = 60,
    tolerance: float = 1e-7,
) -> np.ndarray:
    """Reference positions ``X`` with ``X + u(X) = x`` for deformed positions ``x`` (N, 3).

    Fixed-point iteration ``X <- x - u(X)``; converges where the displacement gradient has a norm
    below one (any physically admissible field at the strains DVC measures).
    """
    positions = np.asarray(positions, dtype=np.float64)
    reference = positions - displacement(positions)
    for _ in range(iterations):
        updated = positions - displacement(reference)
        change = np.max(np.abs(updated - reference)) if len(reference) else 0.0
        reference = updated
        if change < tolerance:
            break
    return reference


def deform_volume(
    reference: np.ndarray,
    displacement: DisplacementFunction,
    chunk_voxels: int = 2_000_000,
    cval: float | None = None,
) -> np.ndarray:
    """Deformed volume ``F`` with ``F(X + u(X)) = G(X)`` for a known Lagrangian field ``u``.

    Parameters
    ----------
    reference : ndarray, shape (nz, ny, nx)
        The reference volume ``G``.
    displacement : callable
        ``u(points)`` for points (N, 3) in reference voxels (z, y, x), returning (N, 3) voxels.
    chunk_voxels : int
        Voxels processed at a time (bounds memory).
    cval : float, optional
        Gray value for material that comes from outside ``G`` (default: the mean of ``G``).

    Returns
    -------
    ndarray, float32, same shape as ``reference``.
    """
    reference = np.asarray(reference, dtype=np.float64)
    coefficients = ndimage.spline_filter(reference, order=5, mode="mirror")
    fill = float(reference.mean()) if cval is None else float(cval)
    out = np.empty(reference.shape, np.float32)
    flat = out.reshape(-1)
    positions_all = np.indices(reference.shape).reshape(3, -1)
    for start in range(0, flat.size, chunk_voxels):
        positions = positions_all[:, start : start + chunk_voxels].T.astype(np.float64)
        source = invert_displacement(displacement, positions)
        flat[start : start + len(positions)] = ndimage.map_coordinates(
            coefficients, source.T, order=5, mode="mirror", prefilter=False
        )
        outside = np.any((source < 0) | (source > np.array(reference.shape) - 1), axis=1)
        flat[start : start + len(positions)][outside] = fill
    return out


# --- displacement fields with a closed form --------------------------------------------------
def translation(shift) -> DisplacementFunction:
    """Rigid translation by ``shift`` (z, y, x) voxels."""
    shift = np.asarray(shift, dtype=np.float64)
    return lambda points: np.broadcast_to(shift, np.shape(points)).copy()


def affine(gradient, center, shift=(0.0, 0.0, 0.0)) -> DisplacementFunction:
    """``u(X) = shift + gradient @ (X - center)``; ``gradient[i, j] = du_i/dX_j`` (z, y, x)."""
    gradient = np.asarray(gradient, dtype=np.float64)
    center = np.asarray(center, dtype=np.float64)
    shift = np.asarray(shift, dtype=np.float64)
    return lambda points: shift + (np.asarray(points) - center) @ gradient.T


def rotation_z(angle_degrees: float, center, shift=(0.0, 0.0, 0.0)) -> DisplacementFunction:
    """Rigid rotation about the z axis through ``center``, then a translation by ``shift``."""
    angle = np.deg2rad(angle_degrees)
    rot = np.array(
        [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
    )
    return affine(rot - np.eye(3), center, shift)


def shear_band(
    center,
    width: float = 6.0,
    slip: float = 8.0,
    normal=(1.0, 0.0, 1.0),
    direction=(1.0, 0.0, -1.0),
    background_strain: float = 0.0,
    shift=(0.0, 0.0, 0.0),
) -> DisplacementFunction:
    """A shear band: one side slips by ``slip`` voxels relative to the other, smoothly.

    ``u(X) = shift + background_strain * (X - center) * (-1, 0.5, 0.5)`` (uniaxial compression along
    z, volume-preserving) ``+ slip/2 * tanh(d / width) * direction``, with ``d`` the signed
    distance of ``X`` to the band's mid-plane (through ``center``, unit normal ``normal``) and
    ``direction`` a unit vector in the plane. The peak engineering shear strain is about
    ``slip / (2 * width)``, i.e. an equivalent strain of about ``slip / (2 * sqrt(3) * width)``.
    """
    center = np.asarray(center, dtype=np.float64)
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    direction = np.asarray(direction, dtype=np.float64)
    direction = direction - normal * (direction @ normal)
    direction = direction / np.linalg.norm(direction)
    shift = np.asarray(shift, dtype=np.float64)
    compression = background_strain * np.array([-1.0, 0.5, 0.5])

    def u(points):
        relative = np.asarray(points, dtype=np.float64) - center
        distance = relative @ normal
        band = 0.5 * slip * np.tanh(distance / width)
        return shift + relative * compression + band[:, None] * direction

    return u


def sample_displacement(displacement: DisplacementFunction, points: np.ndarray) -> np.ndarray:
    """Evaluate ``displacement`` at ``points`` (..., 3), keeping the leading shape."""
    points = np.asarray(points, dtype=np.float64)
    return displacement(points.reshape(-1, 3)).reshape(points.shape)


def make_pair(
    pattern: Callable[[tuple], np.ndarray],
    shape,
    displacement: DisplacementFunction,
    margin: int = 12,
) -> tuple[np.ndarray, np.ndarray]:
    """Reference and deformed volumes of ``shape`` cut from a larger pattern.

    The pattern is made ``margin`` voxels larger on every side, deformed as a whole and both volumes
    are cropped, so the material that enters the field of view near the borders is the real
    continuation of the pattern (as in a CT scan of a larger specimen) rather than a fill value.
    ``displacement`` is expressed in the cropped volume's coordinates.

    Parameters
    ----------
    pattern : callable
        ``pattern(shape) -> ndarray`` (e.g. ``lambda s: textured_volume(s, 2.0, seed=1)``).
    shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the returned volumes.
    displacement : callable
        Lagrangian field ``u(points)`` in the cropped coordinates (voxels).
    margin : int
        Extra voxels on every side; keep it larger than the largest displacement near the border.

    Returns
    -------
    reference, deformed : ndarray, float32, shape ``shape``
    """
    shape = tuple(int(n) for n in shape)
    big = pattern(tuple(n + 2 * margin for n in shape))
    shifted = lambda points: displacement(np.asarray(points) - margin)  # noqa: E731
    deformed = deform_volume(big, shifted)
    crop = tuple(slice(margin, margin + n) for n in shape)
    return np.ascontiguousarray(big[crop]), np.ascontiguousarray(deformed[crop])


# --- specimens and fields like real CT tests -----------------------------------------------
def concrete_specimen(
    shape,
    aggregate_contrast: float = 0.04,
    matrix_gray: float = 100.0,
    background_gray: float = 20.0,
    texture: float = 3.0,
    radius_fraction: float = 0.45,
    seed: int = 0,
) -> np.ndarray:
    """Weak-contrast x-ray CT of concrete: faint aggregates in a matrix, dark air outside a cylinder.

    Aggregates (rounded blobs of about 6-8 voxels, 40 % of the volume) are ``aggregate_contrast``
    (fraction of ``matrix_gray``) brighter than the matrix; both phases hold a fine texture of
    amplitude ``texture`` gray levels (sand, pores). Outside a cylinder along z of radius
    ``radius_fraction * min(ny, nx)`` the volume is ``background_gray`` (air, no texture). Noise is
    not added (see :func:`add_noise`, :func:`ct_noise_sigma`).

    Returns
    -------
    ndarray, float32, shape ``shape``
    """
    shape = tuple(int(n) for n in shape)
    volume = two_phase_volume(
        shape,
        grain_fraction=0.4,
        grain_size=3.0,
        phase_grays=(matrix_gray, matrix_gray * (1.0 + aggregate_contrast)),
        texture=texture,
        seed=seed,
    )
    y, x = np.ogrid[: shape[1], : shape[2]]
    radius = radius_fraction * min(shape[1], shape[2])
    distance = np.hypot(y - (shape[1] - 1) / 2.0, x - (shape[2] - 1) / 2.0)
    inside = 1.0 / (1.0 + np.exp((distance - radius) / 0.7))  # one-voxel soft edge
    volume = background_gray + (volume - background_gray) * inside[None]
    return volume.astype(np.float32)


def band_rotation_bending(
    center,
    width: float,
    slip: float,
    rotation_degrees: float = 6.0,
    shift=(2.0, -1.5, 3.0),
    bending: float = 1.5,
    compression: float = 0.0,
    normal=(1.0, 0.0, 1.0),
    direction=(1.0, 0.0, -1.0),
) -> DisplacementFunction:
    """A shear band on top of a rotation about z, a translation, bending and compression.

    ``u = band(X) + (R - I)(X - c) + shift + bending * ((x - c_x) / c_x)^2 e_z`` with the band of
    :func:`shear_band` (tanh profile of half-width ``width``, slip ``slip``; peak engineering shear
    ``slip / (2 width)``; full width about ``2 width``) and ``R`` the rotation by
    ``rotation_degrees`` about z. ``compression`` is the band's background strain.
    """
    band = shear_band(
        center,
        width=width,
        slip=slip,
        normal=normal,
        direction=direction,
        background_strain=compression,
    )
    rotation = rotation_z(rotation_degrees, center, shift)
    center = np.asarray(center, dtype=np.float64)

    def u(points):
        points = np.asarray(points, dtype=np.float64)
        total = band(points) + rotation(points)
        total[:, 0] += bending * ((points[:, 2] - center[2]) / center[2]) ** 2
        return total

    return u


# --- CT-like volumes: weak contrast, dark background, noise on both scans ---------------------
def concrete_ct_volume(
    shape,
    aggregate_fraction: float = 0.4,
    aggregate_size: float = 3.0,
    grays: tuple[float, float, float] = (0.1, 0.6, 0.63),
    texture: float = 0.03,
    texture_size: float = 1.5,
    radius_fraction: float = 0.46,
    seed: int = 0,
) -> np.ndarray:
    """X-ray-CT-like concrete: faint aggregates in a matrix, inside a cylinder on a dark background.

    The specimen is a cylinder along z (radius ``radius_fraction`` of the smaller of ny, nx,
    centred in y, x) with a soft one-voxel edge. Inside it, aggregates (the thresholded level set
    of a smoothed random field, about ``2 * aggregate_size`` voxels across) are a few percent
    brighter than the matrix, and a fine texture of amplitude ``texture`` (white noise smoothed
    with sigma ``texture_size`` voxels: pores, sand, the scanner's blur) lives in both phases. No imaging noise here: add it with
    :func:`add_noise` to each scan (:func:`ct_noise_sigma`).

    Parameters
    ----------
    shape : tuple of 3 ints
        ``(nz, ny, nx)``.
    aggregate_fraction : float
        Volume fraction of aggregates inside the specimen.
    aggregate_size : float
        Smoothing sigma (voxels) of the field whose level set gives the aggregates.
    grays : (background, matrix, aggregate)
        Gray values; the default aggregates are 5 % brighter than the matrix.
    texture, texture_size : float
        Standard deviation (gray) and smoothing sigma (voxels) of the fine texture.
    radius_fraction : float
        Cylinder radius over ``min(ny, nx)``.
    seed : int
        Random seed.

    Returns
    -------
    ndarray, float32, shape ``shape``
    """
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in shape)
    field = ndimage.gaussian_filter(rng.standard_normal(shape), aggregate_size, mode="wrap")
    level = np.quantile(field, 1.0 - aggregate_fraction)
    aggregates = 1.0 / (1.0 + np.exp(-(field - level) / (0.15 * field.std())))
    fine = ndimage.gaussian_filter(rng.standard_normal(shape), texture_size, mode="wrap")
    fine /= fine.std()
    background, matrix, aggregate = grays
    specimen = matrix + (aggregate - matrix) * aggregates + texture * fine
    yy, xx = np.meshgrid(
        np.arange(shape[1]) - (shape[1] - 1) / 2.0,
        np.arange(shape[2]) - (shape[2] - 1) / 2.0,
        indexing="ij",
    )
    radius = radius_fraction * min(shape[1], shape[2])
    inside = 1.0 / (1.0 + np.exp(-(radius - np.sqrt(yy**2 + xx**2)) / 0.5))
    volume = background + (specimen - background) * inside[None]
    return volume.astype(np.float32)


def ct_noise_sigma(volume: np.ndarray, fraction: float = 0.06) -> float:
    """Noise standard deviation as a fraction of the volume's p1-p99 gray range."""
    low, high = np.percentile(np.asarray(volume, dtype=np.float64), [1.0, 99.0])
    return float(fraction * (high - low))


def noisy_ct_pair(
    shape,
    displacement: DisplacementFunction,
    noise: float = 0.06,
    seed: int = 0,
    margin: int = 12,
    **volume_options,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Reference and deformed CT-like scans (:func:`concrete_ct_volume`) with noise on both.

    The deformed scan is made with a 5th-order spline (:func:`make_pair`), then independent
    Gaussian noise of standard deviation ``noise × (p99 − p1)`` of the clean reference is added
    to each scan.

    Returns
    -------
    reference, deformed : ndarray, float32, shape ``shape``
    sigma : float
        The noise standard deviation added to each scan (gray levels).
    """
    reference, deformed = make_pair(
        lambda s: concrete_ct_volume(s, seed=seed, **volume_options), shape, displacement, margin
    )
    sigma = ct_noise_sigma(reference, noise)
    if sigma > 0:
        reference = add_noise(reference, sigma, seed=seed + 1001)
        deformed = add_noise(deformed, sigma, seed=seed + 2002)
    return reference, deformed, sigma
