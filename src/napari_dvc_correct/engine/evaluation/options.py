"""The options of an accuracy evaluation, as one checked record.

Plain Python, so that the command line can build its parser and print its defaults without
loading numba or scipy. :func:`.accuracy.evaluate_iter` and the tiled evaluation take these
options (:meth:`EvaluationOptions.keywords`); their defaults and checks live here and nowhere
else.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

#: Where the gray residual lives (:func:`.residual.gray_residual`).
RESIDUAL_MODES = ("reference", "loaded")
#: Displacement-gradient estimators on the grid (:func:`.strain.displacement_gradient`).
GRADIENT_METHODS = ("central", "least-squares", "shape-function")
#: Strain measures (:func:`.strain.strain_tensor`).
STRAIN_MEASURES = ("small", "green-lagrange")
#: Most phases (multi-Otsu's cost grows as its bins to the power ``N - 1``).
MAX_PHASES = 8


def _thresholds(value, name: str):
    if value is None or (isinstance(value, str) and value == "auto"):
        return value
    if isinstance(value, str):
        raise ValueError(f"{name} must be 'auto' or a list of gray thresholds, got {value!r}")
    try:
        values = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 'auto' or gray numbers, got {value!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must hold finite gray thresholds, got {value!r}")
    return values


@dataclass(frozen=True)
class EvaluationOptions:
    """How the fields of a pair are evaluated (paper eqs. 1–3, Figs. 5–8).

    Attributes
    ----------
    phases : "auto" or sequence of float
        Gray thresholds of both states (``"auto"``: multi-Otsu with ``n_phases`` per state).
    phases_deformed : "auto", sequence of float, or None
        Thresholds of the deformed state when they differ (None: as ``phases``).
    n_phases : int
        Number of phases for ``"auto"``, 2 to :data:`MAX_PHASES`.
    phase_pair : (int, int), optional
        Phases whose gray contrast enters eq. 2 (None: the two most abundant).
    mode : {"reference", "loaded"}
        Where the residual lives: ``|F(X+u) - G(X)|`` on reference voxels, or the paper's
        ``|F - G'|`` in the loaded state.
    strain_measure : {"small", "green-lagrange"}
    strain_method : {"central", "least-squares", "shape-function"}
        Displacement-gradient estimator on the grid.
    strain_window : int
        Least-squares window, odd number of nodes >= 3.
    n_bins : int
        Equivalent-strain bins (>= 1; ignored with ``bin_edges``).
    bin_edges : sequence of float, optional
        Explicit strain-bin edges.
    shared_background : bool
        One background residual ``r0`` (the pair's smallest) for every field; False: each its
        own.
    bin_by : str, optional
        Name of the field whose equivalent strain bins every field's residual.
    gray_levels : bool
        Map the loaded scan's gray levels onto the reference's before the residual (False: the
        raw ``|F~ - G|``).
    """

    phases: str | tuple = "auto"
    phases_deformed: str | tuple | None = None
    n_phases: int = 2
    phase_pair: tuple[int, int] | None = None
    mode: str = "reference"
    strain_measure: str = "small"
    strain_method: str = "central"
    strain_window: int = 5
    n_bins: int = 10
    bin_edges: Sequence[float] | None = None
    shared_background: bool = True
    bin_by: str | None = None
    gray_levels: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "phases", _thresholds(self.phases, "phases"))
        if self.phases is None:
            raise ValueError("phases must be 'auto' or a list of gray thresholds, got None")
        object.__setattr__(
            self, "phases_deformed", _thresholds(self.phases_deformed, "phases_deformed")
        )
        if isinstance(self.n_phases, bool) or not isinstance(self.n_phases, int):
            raise ValueError(f"n_phases must be a whole number, got {self.n_phases!r}")
        if not 2 <= self.n_phases <= MAX_PHASES:
            raise ValueError(
                f"the number of phases must be an integer in 2..{MAX_PHASES}, got {self.n_phases!r}"
            )
        if self.phase_pair is not None:
            pair = tuple(self.phase_pair)
            if len(pair) != 2 or not all(isinstance(p, int) and p >= 0 for p in pair):
                raise ValueError(f"phase_pair must be two phase numbers, got {self.phase_pair!r}")
            object.__setattr__(self, "phase_pair", pair)
        if self.mode not in RESIDUAL_MODES:
            raise ValueError(f"mode must be 'reference' or 'loaded', got {self.mode!r}")
        if self.strain_measure not in STRAIN_MEASURES:
            raise ValueError(
                f"unknown strain measure {self.strain_measure!r}: use one of {STRAIN_MEASURES}"
            )
        if self.strain_method not in GRADIENT_METHODS:
            raise ValueError(
                f"unknown gradient method {self.strain_method!r}: use one of {GRADIENT_METHODS}"
            )
        if self.strain_method == "least-squares" and (
            int(self.strain_window) < 3 or int(self.strain_window) % 2 == 0
        ):
            raise ValueError(
                f"the strain window must be an odd number of nodes >= 3, got {self.strain_window!r}"
            )
        if self.bin_edges is None and int(self.n_bins) < 1:
            raise ValueError(f"n_bins must be >= 1, got {self.n_bins}")

    def keywords(self) -> dict:
        """The keyword arguments of :func:`.accuracy.evaluate_iter` these options set."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def replace(self, **changes) -> EvaluationOptions:
        """A copy with ``changes`` (checked like a new one)."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """Plain JSON-ready values (sessions, provenance)."""
        values = self.keywords()
        for key in ("phases", "phases_deformed", "phase_pair", "bin_edges"):
            if values[key] is not None and not isinstance(values[key], str):
                values[key] = list(values[key])
        return values

    @classmethod
    def from_dict(cls, values: dict) -> EvaluationOptions:
        """The record of :meth:`as_dict` (unknown keys ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})
