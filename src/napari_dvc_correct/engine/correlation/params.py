"""Parameters of a DVC run, validated once at the boundary."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

#: The smallest subvolume edge (voxels): a 5³ subvolume still holds more voxels than the 30
#: parameters of a second-order match.
MIN_SUBVOLUME = 5


#: Radius of a subvolume's Gaussian window, in standard deviations
#: (:meth:`CorrelationParams.subvolume_weights`): voxels farther than ``WINDOW_TRUNCATE · std``
#: from the POI (weight below ``exp(−4.5)`` ≈ 0.011) count 0. On a 15³ box under std 3 they
#: are 19 % of the voxels and 0.8 % of the weight (0.015 % of ``Σ w²``); a voxel of weight 0
#: is neither gathered nor sampled, so the match's per-voxel work falls by that share.
WINDOW_TRUNCATE = 3.0


def gaussian_window(half: int, std: float, truncate: float | None = None) -> np.ndarray:
    """Gaussian weights ``exp(−|ξ|² / (2 std²))`` over the box ``[−half, half]³``.

    Parameters
    ----------
    half : int
        Box half-size ``M`` (voxels; edge ``2M + 1``).
    std : float
        Standard deviation of the window (voxels), > 0.
    truncate : float or None
        Radius of the window in standard deviations, > 0: voxels with ``|ξ| > truncate · std``
        (voxels) weigh 0, a truncated Gaussian. None: the whole box is weighted.

    Returns
    -------
    ndarray (2M + 1, 2M + 1, 2M + 1) float64, axes (z, y, x), 1 at the centre.
    """
    if not (np.isfinite(std) and std > 0):
        raise ValueError(f"the window's standard deviation must be > 0 voxels, got {std!r}")
    if int(half) < 1:
        raise ValueError(f"the box half-size must be >= 1 voxel, got {half!r}")
    if truncate is not None and not (np.isfinite(truncate) and truncate > 0):
        raise ValueError(f"the window's radius must be > 0 standard deviations, got {truncate!r}")
    r = np.arange(-int(half), int(half) + 1, dtype=np.float64)
    r2 = r[:, None, None] ** 2 + r[None, :, None] ** 2 + r[None, None, :] ** 2
    weights = np.exp(-r2 / (2.0 * float(std) ** 2))
    if truncate is not None:
        weights[r2 > (float(truncate) * float(std)) ** 2] = 0.0
    return weights


@dataclass(frozen=True)
class CorrelationParams:
    """Parameters of local subvolume DVC. The self-correction reuses them unchanged.

    Parameters
    ----------
    subvolume : int
        Odd subvolume edge ``2M + 1`` in voxels.
    step : int
        POI spacing in voxels (same along z, y, x).
    order : {1, 2}
        Shape function order: 1 = affine (12 parameters), 2 = quadratic (30 parameters).
    search_radius : int or None
        Largest displacement (voxels) the integer search should find around the global rigid
        shift estimated from the whole volume. None picks ``max(8, subvolume // 2)``; radii larger
        than the subvolume use a coarse-to-fine pyramid.
    max_iterations : int
        IC-GN iteration limit per POI.
    tolerance : float
        Convergence threshold (voxels) on the largest displacement of the incremental warp at the
        subvolume corners.
    min_mask_fraction : float
        A POI is matched only if at least this fraction of its subvolume is inside the mask.
    min_texture : float
        Subvolumes whose gray standard deviation is below this fraction of the volume's gray
        standard deviation are flagged ``LOW_TEXTURE`` and not matched.
    min_zncc : float
        Relative ZNCC threshold: matches that converge with a ZNCC below ``min_zncc`` times
        ``ZNCC*``, the ZNCC a perfect match reaches at the scans' noise level, are flagged
        ``LOW_ZNCC`` (:func:`.noise.noise_aware_thresholds`). Where ``ZNCC*`` is not estimated
        (the seeds and coarse levels of the initial guess, the reliability-guided repair, too
        few matched points) and on noise-free scans (``ZNCC* = 1``) the threshold is
        ``min_zncc`` itself. Not the cleaning's absolute
        :attr:`.correction.options.CleaningOptions.zncc_floor`.
    batch_size : int
        POIs per progress batch.
    noise_tolerance : float
        Noise stop of IC-GN (:func:`.icgn._noise_converged`): a match also counts as converged
        once its remaining translation error is estimated below this fraction of its own noise
        uncertainty. 0 turns it off (only ``tolerance`` decides). No effect on noise-free scans.
    min_max_update : float
        A match is ``DIVERGED`` when IC-GN moves its translation farther than
        ``max(M, min_max_update)`` voxels from the initial guess (``M`` the subvolume half-size at
        the pyramid level).
    median_test_min_pois : int
        The neighbour median test that screens seeds and repairs runs only with at least this
        many good POIs.
    repair_attempts : int
        Times the reliability-guided repair may re-match one bad POI from different neighbours.
    repair_attempts_out_of_bounds : int
        The same for a POI whose deformed subvolume left the volume (its guess may be wrong, but
        it is usually at the border for good).
    window : float or None
        Gaussian weights over the subvolume at full resolution: a voxel at ``ξ`` from the POI
        counts ``exp(−|ξ|² / (2 window²))`` in the match (standard deviation in voxels;
        :mod:`.icgn_weighted`) within ``WINDOW_TRUNCATE · window`` of it, 0 beyond.
        None (default): every voxel of the subvolume counts the same.
    """

    subvolume: int = 31
    step: int = 8
    order: int = 1
    search_radius: int | None = None
    max_iterations: int = 50
    tolerance: float = 1e-3
    min_mask_fraction: float = 0.5
    min_texture: float = 0.05
    min_zncc: float = 0.5
    batch_size: int = 256
    noise_tolerance: float = 0.1
    min_max_update: float = 4.0
    median_test_min_pois: int = 9
    repair_attempts: int = 3
    repair_attempts_out_of_bounds: int = 1
    window: float | None = None

    def __post_init__(self) -> None:
        problems = []
        if not isinstance(self.subvolume, (int, np.integer)) or self.subvolume < MIN_SUBVOLUME:
            problems.append(
                f"subvolume must be an odd integer >= {MIN_SUBVOLUME}, got {self.subvolume!r}"
            )
        elif self.subvolume % 2 == 0:
            problems.append(f"subvolume must be odd (2M+1), got {self.subvolume}")
        if not isinstance(self.step, (int, np.integer)) or self.step < 1:
            problems.append(f"step must be an integer >= 1, got {self.step!r}")
        if self.order not in (1, 2):
            problems.append(f"order must be 1 or 2, got {self.order!r}")
        if self.search_radius is not None and (
            not isinstance(self.search_radius, (int, np.integer)) or self.search_radius < 0
        ):
            problems.append(f"search_radius must be an integer >= 0, got {self.search_radius!r}")
        if not isinstance(self.max_iterations, (int, np.integer)) or self.max_iterations < 1:
            problems.append(f"max_iterations must be >= 1, got {self.max_iterations!r}")
        if not (np.isfinite(self.tolerance) and self.tolerance > 0):
            problems.append(f"tolerance must be > 0, got {self.tolerance!r}")
        if not 0.0 < self.min_mask_fraction <= 1.0:
            problems.append(f"min_mask_fraction must be in (0, 1], got {self.min_mask_fraction!r}")
        if not 0.0 <= self.min_texture < 1.0:
            problems.append(f"min_texture must be in [0, 1), got {self.min_texture!r}")
        if not -1.0 <= self.min_zncc <= 1.0:
            problems.append(f"min_zncc must be in [-1, 1], got {self.min_zncc!r}")
        if not isinstance(self.batch_size, (int, np.integer)) or self.batch_size < 1:
            problems.append(f"batch_size must be >= 1, got {self.batch_size!r}")
        if not (np.isfinite(self.noise_tolerance) and 0.0 <= self.noise_tolerance < 1.0):
            problems.append(f"noise_tolerance must be in [0, 1), got {self.noise_tolerance!r}")
        if not (np.isfinite(self.min_max_update) and self.min_max_update > 0):
            problems.append(f"min_max_update must be > 0 voxels, got {self.min_max_update!r}")
        for name in ("median_test_min_pois", "repair_attempts", "repair_attempts_out_of_bounds"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 0:
                problems.append(f"{name} must be an integer >= 0, got {value!r}")
        if self.window is not None and not (
            isinstance(self.window, (int, float, np.integer, np.floating))
            and np.isfinite(self.window)
            and self.window > 0
        ):
            problems.append(
                f"window must be None (no weights) or a standard deviation > 0 voxels, "
                f"got {self.window!r}"
            )
        if problems:
            raise ValueError("; ".join(problems))

    @property
    def half(self) -> int:
        """Subvolume half-size ``M`` in voxels."""
        return self.subvolume // 2

    def subvolume_weights(self) -> np.ndarray | None:
        """The subvolume's weights, shape ``(subvolume,)*3`` (None where :attr:`window` is):
        the Gaussian of std :attr:`window` truncated at :data:`WINDOW_TRUNCATE` std."""
        if self.window is None:
            return None
        return gaussian_window(self.half, float(self.window), WINDOW_TRUNCATE)

    @property
    def effective_search_radius(self) -> int:
        if self.search_radius is not None:
            return int(self.search_radius)
        return max(8, self.half)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> CorrelationParams:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})

    def replace(self, **changes) -> CorrelationParams:
        return dataclasses.replace(self, **changes)
