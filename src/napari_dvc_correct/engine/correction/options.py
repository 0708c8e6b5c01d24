"""The options of the cleaning and of the self-correction, as checked records.

Plain Python and numpy only, so that the command line can build its parsers and print its
defaults without loading numba or scipy. :func:`.cleaning.clean` reads :class:`CleaningOptions`
and :func:`.self_correction.correct_iter` reads :class:`CorrectionOptions`: the defaults live here and
nowhere else.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

#: Frames the correction can warp into (see :class:`CorrectionOptions`).
FRAMES = ("reference", "loaded")

#: The largest smoothing sigma, in grid nodes: a wider Gaussian smooths any grid to its mean.
MAX_SMOOTHING = 1000.0

#: How a correction ``ΔD`` updates the field ``D`` (see :class:`CorrectionOptions`).
UPDATES = ("exact", "sum")


def _finite(value) -> bool:
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


@dataclass(frozen=True)
class CleaningOptions:
    """How a field is cleaned (paper step b): the outlier test and what is filled.

    Attributes
    ----------
    threshold : float
        Median-test threshold (2 is the usual choice; larger rejects less), > 0.
    radius, epsilon : int, float
        Median-test neighbourhood (nodes, >= 1) and noise level (voxels, >= 0), see
        :func:`.cleaning.normalized_median_test`.
    zncc_floor : float, optional
        Absolute ZNCC threshold: also reject nodes whose ZNCC is below this value. Not the
        matcher's relative :attr:`.correlation.params.CorrelationParams.min_zncc` (a fraction of
        the ZNCC a perfect match reaches at the scans' noise), with which the matcher already
        flags ``LOW_ZNCC``. None: no such test.
    passes : int
        Times the median test is repeated with the rejected nodes left out of the
        neighbourhoods (a cluster of outliers can pass a single test), >= 1.
    fill_masked : bool
        Also fill nodes outside the mask (their provenance stays ``MASKED`` so they are never
        taken for measurements; useful before densifying, which needs every node).
    smoothing : float
        Gaussian sigma in nodes for an optional smoothing after the replacement (0 = none, at
        most :data:`MAX_SMOOTHING`).
    """

    threshold: float = 2.0
    radius: int = 1
    epsilon: float = 0.1
    zncc_floor: float | None = None
    passes: int = 2
    fill_masked: bool = False
    smoothing: float = 0.0

    def __post_init__(self) -> None:
        if not (_finite(self.threshold) and self.threshold > 0):
            raise ValueError(f"threshold must be > 0, got {self.threshold!r}")
        if int(self.radius) < 1:
            raise ValueError(f"radius must be >= 1 node, got {self.radius!r}")
        if not (_finite(self.epsilon) and self.epsilon >= 0):
            raise ValueError(f"epsilon must be >= 0 voxel, got {self.epsilon!r}")
        if self.zncc_floor is not None and not (
            _finite(self.zncc_floor) and -1.0 <= self.zncc_floor <= 1.0
        ):
            raise ValueError(f"zncc_floor must be a ZNCC in [-1, 1], got {self.zncc_floor!r}")
        if int(self.passes) < 1:
            raise ValueError(f"passes must be >= 1, got {self.passes!r}")
        if not (_finite(self.smoothing) and 0 <= self.smoothing <= MAX_SMOOTHING):
            raise ValueError(
                f"smoothing must be a sigma from 0 to {MAX_SMOOTHING:g} grid nodes, got "
                f"{self.smoothing!r}"
            )

    def replace(self, **changes) -> CleaningOptions:
        """A copy with ``changes`` (checked like a new one)."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """Plain JSON-ready values, as recorded in ``metadata["cleaning"]``."""
        return {
            "threshold": float(self.threshold),
            "radius": int(self.radius),
            "epsilon": float(self.epsilon),
            "zncc_floor": None if self.zncc_floor is None else float(self.zncc_floor),
            "passes": int(self.passes),
            "fill_masked": bool(self.fill_masked),
            "smoothing": float(self.smoothing),
        }


@dataclass(frozen=True)
class CorrectionOptions:
    """How the self-correction runs its passes (paper steps c–f).

    Attributes
    ----------
    frame : {"loaded", "reference"}
        Warp ``G`` forward to the loaded state as in the paper (default), or pull ``F`` back to
        the reference (no inversion, but the correcting match then sees the error multiplied by
        the inverse deformation gradient; see docs/method.md).
    update : {"exact", "sum"}
        Compose ``D`` with ``ΔD`` (default) or add them node by node as in the paper.
    max_passes : int
        Most correction passes (each is one DVC run), >= 1.
    min_improvement : float
        Another pass runs only if the last one removed more than this fraction of the local
        residual in excess of the noise floor, in [0, 1).
    noise_fit : bool
        After the passes, replace a node's value by the generalised-least-squares affine fit over
        its 3³ neighbourhood where the data say that neighbourhood holds only matching noise
        (:mod:`.noise_fit`). Off by default: on the real rock it raised the gray-corrected
        residual in the fifth digit (docs/method.md).
    """

    frame: str = "loaded"
    update: str = "exact"
    max_passes: int = 3
    min_improvement: float = 0.01
    noise_fit: bool = False

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {self.frame!r}")
        if self.update not in UPDATES:
            raise ValueError(f"update must be one of {UPDATES}, got {self.update!r}")
        if int(self.max_passes) < 1:
            raise ValueError(f"max_passes must be >= 1, got {self.max_passes!r}")
        if not (_finite(self.min_improvement) and 0.0 <= self.min_improvement < 1.0):
            raise ValueError(f"min_improvement must be in [0, 1), got {self.min_improvement!r}")
        if self.noise_fit not in (True, False):
            raise ValueError(f"noise_fit must be True or False, got {self.noise_fit!r}")

    def as_dict(self) -> dict:
        """Plain JSON-ready values, as recorded in ``metadata["correction"]``."""
        return {
            "frame": self.frame,
            "update": self.update,
            "max_passes": int(self.max_passes),
            "min_improvement": float(self.min_improvement),
            "noise_fit": bool(self.noise_fit),
        }


def defaults() -> dict:
    """Every default of :class:`CorrectionOptions` and :class:`CleaningOptions` by name."""
    values = {}
    for options in (CorrectionOptions, CleaningOptions):
        for option in dataclasses.fields(options):
            values.setdefault(option.name, option.default)
    return values
