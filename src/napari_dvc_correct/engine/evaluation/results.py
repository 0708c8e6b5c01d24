"""What an accuracy evaluation returns: per field (:class:`FieldEvaluation`) and for the pair
(:class:`Evaluation`), and which nodes count as measured."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dataclass_field

import numpy as np

from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance
from .accuracy_blocks import (  # noqa: F401 (part of this module's interface)
    BackgroundResidual,
    background_residual,
    corrected_residual,
)
from .accuracy_pair import PairStatistics
from .binning import StrainBins
from .gray_levels import GrayLevelMap
from .local_accuracy import (  # noqa: F401 (part of this module's interface)
    honest_accuracy,
    local_accuracy_map,
    local_mean_residual,
    region_half,
)

#: Below this share of measured nodes an evaluation says first that p is not meaningful: it
#: would judge values inpainted from a few matches.
MIN_MEASURED_FRACTION = 0.5


def measured_mask(field: DisplacementField) -> np.ndarray:
    """Nodes measured by a match (good status, provenance measured or corrected)."""
    good = np.isin(field.status, [int(s) for s in GOOD_STATUSES])
    kept = np.isin(field.provenance, [int(Provenance.MEASURED), int(Provenance.CORRECTED)])
    return good & kept & np.all(np.isfinite(field.u), axis=-1)


# --- the whole chain --------------------------------------------------------------------------
@dataclass
class FieldEvaluation:
    """The accuracy evaluation of one displacement field.

    Attributes
    ----------
    name : str
        Label of the field in tables and plots (e.g. ``"uncorrected"``).
    field : DisplacementField
        The field evaluated.
    equivalent_strain : ndarray, shape field.shape, float64
        Equivalent strain (eq. 3) on the grid, NaN at invalid nodes.
    mean_residual : float
        Mean gray residual over the voxels where it is defined (gray levels).
    voxels : int
        Voxels where the residual is defined.
    background : BackgroundResidual
        This field's own same-phase residual (eq. 1).
    background_used : float
        The ``r0`` used for ``r'`` and the index (see :func:`evaluate_iter`, ``shared_background``).
    accuracy : float
        Accuracy index (eq. 2) of the whole residual volume.
    bins : StrainBins
        Mean residual per equivalent-strain bin.
    bin_accuracy : ndarray, shape (B,)
        Accuracy index per bin (NaN for empty bins).
    local_residual : ndarray, shape field.shape
        Mean residual over each node's subvolume region (:func:`local_mean_residual`; the
        subvolume of ``field.params``, else ``2 * step + 1``), NaN where undefined.
    local_accuracy : ndarray, shape field.shape
        Local accuracy index per node (:func:`local_accuracy_map`): where the field is wrong.
    local_accuracy_index : float
        :func:`honest_accuracy` of the map: the mean over every node with undefined regions at
        0. It falls where a field ruins a region so badly that its residual becomes undefined,
        which ``accuracy`` (eq. 2 over the defined voxels) cannot see.
    residual : ndarray or None
        Residual volume ``|map(F~) - G|`` (reference gray levels; float32, NaN where undefined;
        kept with ``keep_volumes``).
    labels_mapped : ndarray or None
        Phases of the other state brought onto the residual's voxels by the field, uint8
        (:data:`~.phases.NO_PHASE` where undefined; kept with ``keep_volumes``).
    local_gradient, cell_residual : ndarray, shape field.shape
        RMS gray gradient and mean residual over each node's window
        (:func:`.error_estimate.error_region_half`; gray levels per voxel, gray levels).
    error_estimate : ndarray, shape field.shape
        Estimated displacement error per node, voxels (:mod:`.error_estimate`).
    error_resolution : ndarray, shape field.shape
        The residual's resolution per node, voxels: where ``error_estimate`` is not above it,
        the estimate is a bound (:func:`.error_estimate.error_estimate`).
    """

    name: str
    field: DisplacementField
    equivalent_strain: np.ndarray
    mean_residual: float
    voxels: int
    background: BackgroundResidual
    background_used: float
    accuracy: float
    bins: StrainBins
    bin_accuracy: np.ndarray
    local_residual: np.ndarray | None = None
    local_accuracy: np.ndarray | None = None
    local_accuracy_index: float = float("nan")
    residual: np.ndarray | None = None
    labels_mapped: np.ndarray | None = None
    local_gradient: np.ndarray | None = None
    cell_residual: np.ndarray | None = None
    error_estimate: np.ndarray | None = None
    error_resolution: np.ndarray | None = None

    @property
    def mean_corrected_residual(self) -> float:
        """``mean(r') = mean(r) - r0`` (gray levels)."""
        return self.mean_residual - self.background_used

    @property
    def measured_nodes(self) -> int:
        """Nodes whose displacement a match measured (good status, measured or corrected):
        inpainted, interpolated, failed and masked nodes do not count."""
        return int(np.count_nonzero(measured_mask(self.field)))

    @property
    def measured_fraction(self) -> float:
        """Share of the grid's nodes that were measured (:attr:`measured_nodes`)."""
        return self.measured_nodes / max(1, int(self.field.n_points))

    @property
    def meaningful(self) -> bool:
        """False when most nodes were not measured: p then judges an inpainted field."""
        return self.measured_fraction >= MIN_MEASURED_FRACTION

    @property
    def error(self) -> dict:
        """:func:`.error_estimate.error_summary` of :attr:`error_estimate` (voxels)."""
        from .error_estimate import error_summary

        if self.error_estimate is None:
            return error_summary(np.array([]))
        return error_summary(self.error_estimate, resolution=self.error_resolution)


@dataclass
class Evaluation:
    """Phases, contrast and per-field results of :func:`evaluate_fields`.

    Attributes
    ----------
    mode : str
        ``"reference"`` (residual ``|F(X + u) - G(X)|`` on reference voxels) or ``"loaded"``
        (the paper's ``|F - G'|`` on loaded-state voxels).
    thresholds_reference, thresholds_deformed : ndarray, shape (N - 1,)
        Gray thresholds of each state.
    phases_reference, phases_deformed : list of PhaseStats
        Table 1 rows of each state.
    contrast : float
        ``|g1 - g2|`` (gray levels) of ``phase_pair``, mean over both states.
    phase_pair : (int, int)
        Phases whose contrast is used in eq. 2.
    edges : ndarray, shape (B + 1,)
        Equivalent-strain bin edges shared by all fields.
    options : dict
        The strain and binning options used.
    fields : list of FieldEvaluation
    labels_reference, labels_deformed : ndarray or None
        Phase label volumes (uint8), kept with ``keep_volumes``.
    pair : PairStatistics or None
        The scan pair's gray-level map and ``r0`` (:mod:`.accuracy_pair`), measured with the best
        field known on the pair, whichever fields are evaluated.
    """

    mode: str
    thresholds_reference: np.ndarray
    thresholds_deformed: np.ndarray
    phases_reference: list
    phases_deformed: list
    contrast: float
    phase_pair: tuple
    edges: np.ndarray
    options: dict
    fields: list = dataclass_field(default_factory=list)
    labels_reference: np.ndarray | None = None
    labels_deformed: np.ndarray | None = None
    pair: PairStatistics | None = None

    @property
    def gray_levels(self) -> GrayLevelMap:
        """The pair's gray-level map (identity without one)."""
        return GrayLevelMap.identity() if self.pair is None else self.pair.gray_levels

    @property
    def residual_text(self) -> str:
        """What every mean gray residual of this evaluation is: its definition and frame."""
        f = "F" if self.gray_levels.is_identity else "map(F)"
        if self.mode == "reference":
            text, where = f"|{f}(X + u) − G(X)|", "reference frame"
        else:
            text, where = f"|{f} − G'|", "loaded frame"
        levels = "raw gray levels" if self.gray_levels.is_identity else "reference gray levels"
        return f"{text}, {where}, {levels}"

    def __getitem__(self, name: str) -> FieldEvaluation:
        for item in self.fields:
            if item.name == name:
                return item
        raise KeyError(f"no field named {name!r} (fields: {[f.name for f in self.fields]})")
