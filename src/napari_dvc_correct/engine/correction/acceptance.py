"""Local acceptance of a correction pass, judged against the imaging-noise floor.

A pass of the self-correction (:mod:`.self_correction`) proposes a new value at every node. Here each
node's proposal is judged from the images alone: the reference-frame residual
``r(X) = |F(X + D(X)) - G(X)|`` is averaged over the node's cell (the box of edge
``2 ceil(step / 2) + 1`` around it) before and after; the proposal is refused where that local
residual rose by more than resampling the imaging noise can explain, given the noise floor ``r0``
(eq. 1 of the paper, or the lower quartile of the local residuals where that is smaller). A node
*improves above the floor* when the residual over its subvolume fell by more than the noise allows
and more than a :data:`MIN_USEFUL_CHANGE` displacement explains. Nodes whose local residual no
error below :data:`FLAG_ERROR` voxels explains are flagged. A node whose update would read the
correcting field more than :data:`MEASURED_REACH` grid steps beyond its outermost good nodes (an
extrapolation, not a measurement) is refused before any residual is looked at
(:func:`unsupported_updates`). See ``docs/method.md``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..correlation.correlate import EXACT_IN_FLOAT32
from ..evaluation.gray_levels import GrayLevelMap
from ..evaluation.local_accuracy import NodeBoxMeans
from ..evaluation.phase_sums import PhaseRows
from ..evaluation.phases import label_phases, phase_thresholds
from ..fields import warp
from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance, Status
from ..fields.field_spline import FieldSpline
from ..slabs import iter_slabs
from .cleaning import clean

#: One-sided z-score of the local acceptance test: a node's local residual must rise by more than
#: this many standard deviations of what resampling the imaging noise can do before its correction
#: is refused, and fall by as much for the node to count as improved above the noise floor.
NOISE_Z = 2.0

#: Correlation volume (voxels) of the residual's noise: B-spline resampling and the scanner's
#: point spread make neighbouring residual voxels dependent, so a region of ``n`` voxels holds
#: about ``n / NOISE_CORRELATION_VOXELS`` independent noise samples (conservative: 2 x 2 x 2).
NOISE_CORRELATION_VOXELS = 8.0

#: Standard deviation over mean of the absolute difference of two Gaussian noises (half-normal
#: distribution, ``sqrt(pi / 2 - 1)``): turns the noise floor ``r0`` into the residual's spread.
HALF_NORMAL_SPREAD = float(np.sqrt(np.pi / 2.0 - 1.0))

#: Sweeps of the local acceptance per pass: after mixing accepted and refused nodes, the mixed
#: field's residual is checked again (neighbouring nodes share their regions).
ACCEPTANCE_SWEEPS = 3

#: A region counts as improved by a pass only if its residual fell by more than a displacement
#: change of this many voxels explains (besides the noise): a hundredth of a voxel is the
#: matcher's own accuracy on clean scans.
MIN_USEFUL_CHANGE = 0.01

#: Nodes whose local residual exceeds the noise floor by more than an error of this many voxels
#: explains (from the local gray gradient) are flagged ``OUTLIER_REPLACED`` and refilled.
FLAG_ERROR = 1.0

#: A flagged node is a :attr:`~.field.Status.DISCONTINUITY` when the signed residual
#: ``G - map(F~)`` over its cell carries at least this fraction of its excess over the noise floor:
#: material appeared or vanished there (a crack opened or closed, a void collapsed), where a wrong
#: displacement of intact texture leaves a residual of both signs that averages out. On the
#: fractured rock of ``../shared/data/real-rock`` the flagged nodes along the crack carry 0.9-1.5
#: of their excess in the sign of the opening (docs/method.md).
DISCONTINUITY_SIGN = 0.5

#: Fewest touching nodes of a discontinuity (:func:`surfaces`): a 3 x 3 patch of a surface.
MIN_DISCONTINUITY_NODES = 9

#: Good measured nodes within this many grid steps of a discontinuity keep their values
#: (:func:`crack_shield`).
CRACK_SHIELD_NODES = 2

#: A correction is applied in full only where it stands this many uncertainties of its
#: correcting match above zero (:func:`shrink_to_support`).
SUPPORT_Z = 0.5

#: Half-width (nodes) of the neighbourhood over which :func:`noise_only_corrections` pools a
#: pass's corrections against their matches' noise: the node and the 26 around it, whose
#: subvolumes overlap its own at the usual steps (a half to a third of the subvolume).
NOISE_REGION_NODES = 1

#: How far (grid steps of the correcting field) beyond its outermost good measured nodes a node's
#: update may read it. Further out the spline extrapolates the correcting field linearly: on the
#: shear band of docs/method.md (17-voxel displacements, step 5) updates read 0-6 voxels beyond the
#: hull cut the error 0.6 -> 0.1-0.3 voxel, those 7-13 voxels beyond raised it 0.4 -> 0.6-1.5.
MEASURED_REACH = 1.0


class ReferenceResiduals:
    """The volume access of :class:`Judge` for whole arrays: residuals and gradients at nodes.

    ``local_means(field, halves)`` gives, per node, the mean of the reference-frame residual
    ``|F(X + u(X)) - G(X)|`` over the ``(2h + 1)^3`` box around the node for each ``h`` of
    ``halves``, and eq. 1's background residual of that residual (inf where it is undefined);
    ``gradient_means(field, half)`` the mean gray gradient magnitude of ``G`` (Gaussian,
    sigma 1 voxel) over each node's box. ``napari_dvc_correct.tiled.correction`` gives the same
    numbers block by block from lazily read volumes.

    Only the last field's pull-back is held whole: the mapped pull-back, the residual and the
    gradient are made and used slab by slab (:class:`.local_accuracy.NodeBoxMeans`), the same
    numbers as from whole volumes. ``reference`` may be of any real dtype whose values float32
    holds exactly (it is read as float32, a slab at a time).
    """

    def __init__(self, reference, deformed, deformed_coefficients, gray_levels=None):
        reference = np.asarray(reference)
        if reference.dtype.type not in (np.float32, *EXACT_IN_FLOAT32):
            reference = np.ascontiguousarray(reference, dtype=np.float32)
        self.reference = reference
        self.deformed = deformed
        self.coefficients = deformed_coefficients
        self.gray_levels = (
            GrayLevelMap.identity(reference.shape) if gray_levels is None else (gray_levels)
        )
        try:
            self.thresholds_g = phase_thresholds(self.reference, "auto", 2, "reference volume")
            self.labels_g = label_phases(self.reference, self.thresholds_g)
        except ValueError:  # a volume with a single gray value: no phases, no eq. 1
            self.labels_g = None
        self._gradient = {}  # (grid, half) -> the nodes' mean gradient
        self._halves = set()  # the halves asked of local_means: their gradients come together
        self._last = None  # the last field pulled back and its pull-back (one volume)

    def remember(self, field: DisplacementField, pulled_back: np.ndarray) -> None:
        """Take ``pulled_back = F(X + u(X))`` (NaN where undefined, before the gray-level map)
        as the pull-back of ``field``, computed elsewhere with the same volume and coefficients
        (the gray-level fit's), so that the next residual of that field does not pull back
        again."""
        self._last = (_field_key(field), np.array(field.u, copy=True), pulled_back)

    def forget(self) -> None:
        """Drop the pull-back held for the last field (a volume): nothing will judge that field
        again soon (e.g. while a correcting DVC runs)."""
        self._last = None

    def pulled_back(self, field: DisplacementField) -> np.ndarray:
        """``F(X + u(X))`` (NaN where undefined, the loaded scan's gray levels); the last field's
        pull-back is kept, so judging the same field again (the setup's checks, the final
        discontinuity test) costs no warp."""
        last = self._last
        if last is not None and last[0] == _field_key(field) and np.array_equal(last[1], field.u):
            return last[2]
        self._last = last = None  # the old pull-back is freed before the new one is made
        spline = FieldSpline.from_field(field)
        moved = warp.pull_back(self.deformed, spline, coefficients=self.coefficients, cval=np.nan)
        self.remember(field, moved)
        return moved

    def moved(self, field: DisplacementField) -> np.ndarray:
        """``F(X + u(X))`` in the reference's gray levels (the gray-level map applied), NaN where
        undefined."""
        return self.gray_levels.apply(self.pulled_back(field))

    def _slabs(self, field: DisplacementField | None = None):
        """``(planes, G, map(F~))`` slab by slab (:func:`.slabs.iter_slabs`), float32; without
        ``field``, ``map(F~)`` is None."""
        pulled = None if field is None else self.pulled_back(field)
        shape = self.reference.shape
        for zs in iter_slabs(shape):
            own = np.ascontiguousarray(self.reference[zs], dtype=np.float32)
            if pulled is None:
                yield zs, own, None
                continue
            region = (zs, slice(0, shape[1]), slice(0, shape[2]))
            yield zs, own, self.gray_levels.apply(pulled[zs], region)

    def local_means(self, field: DisplacementField, halves) -> tuple[list, float]:
        """Per-node box means of the gray-level-corrected residual ``|map(F~) - G|`` of
        ``field`` for each half-size, and eq. 1's r0 of that residual."""
        self._halves.update(int(h) for h in halves)
        means = NodeBoxMeans(field, self.reference.shape, halves)
        rows = None if self.labels_g is None else PhaseRows(self.reference.shape[0])
        for zs, own, moved in self._slabs(field):
            if rows is None:
                residual = np.abs(moved - own)
            else:  # eq. 1 (inf where no voxel holds the same phase in both states); the moved
                # volume is in the reference's gray levels, so the reference's thresholds phase it
                residual, _ = rows.add(zs, own, moved, self.labels_g[zs], self.thresholds_g)
            means.add(zs, residual)
        floor = float("inf")
        if rows is not None:
            floor = rows.total().same_phase_mean
            floor = floor if np.isfinite(floor) else float("inf")
        return means.means(), floor

    def signed_means(self, field: DisplacementField, half: int) -> np.ndarray:
        """Per-node mean of the signed residual ``G - map(F~)`` over the node's box (reference
        gray levels; NaN where the box holds no defined voxel)."""
        means = NodeBoxMeans(field, self.reference.shape, (half,))
        for zs, own, moved in self._slabs(field):
            means.add(zs, own - moved)
        return means.means()[0]

    def gradient_means(self, field: DisplacementField, half: int) -> np.ndarray:
        """Per-node mean gray gradient magnitude of ``G`` over the node's box (kept per grid and
        half; the halves of :meth:`local_means` computed with it, in one pass)."""
        key = (_field_key(field), int(half))
        if key not in self._gradient:
            halves = sorted(self._halves | {int(half)})
            means = NodeBoxMeans(field, self.reference.shape, halves)
            for zs, _, _ in self._slabs():
                means.add(zs, _gradient_magnitude(self.reference, zs))
            for h, values in zip(halves, means.means(), strict=True):
                self._gradient[(key[0], h)] = values
        return self._gradient[key]


#: Planes beyond a slab that its Gaussian gradient (sigma 1 voxel, scipy's truncation at 4 sigma)
#: reads: with them, a slab's gradient equals the whole volume's to the bit.
GRADIENT_REACH = int(4.0 * 1.0 + 0.5)


def _gradient_magnitude(volume, zs: slice) -> np.ndarray:
    """``ndimage.gaussian_gradient_magnitude(volume as float32, 1.0)[zs]``, from the planes
    ``zs`` and :data:`GRADIENT_REACH` on either side."""
    low = max(0, zs.start - GRADIENT_REACH)
    high = min(volume.shape[0], zs.stop + GRADIENT_REACH)
    block = np.ascontiguousarray(volume[low:high], dtype=np.float32)
    return ndimage.gaussian_gradient_magnitude(block, 1.0)[zs.start - low : zs.stop - low]


def _field_key(field: DisplacementField) -> tuple:
    """What besides ``u`` a field's spline depends on: its grid."""
    return (
        tuple(float(o) for o in field.origin),
        tuple(float(d) for d in field.step),
        tuple(int(n) for n in field.shape),
    )


class Judge:
    """Local residuals and the noise floor, in the reference frame, for the acceptance test.

    The residual ``r(X) = |F(X + D(X)) - G(X)|`` is measured on reference voxels whatever the
    pass's frame. A node's region is its own cell, the box of edge ``2 * ceil(step / 2) + 1``
    around it (at least 5): the field there is mostly that node's value, where a whole subvolume
    would mix in the neighbours' (and let a ruined neighbour hide a ruined node).
    """

    def __init__(
        self, reference, deformed, deformed_coefficients, step, region_half: int, *, residuals=None
    ):
        # the volume access (in memory unless told otherwise, e.g. tiled.correction's block by
        # block one); the decisions below only see per-node numbers
        self.residuals = (
            ReferenceResiduals(reference, deformed, deformed_coefficients)
            if residuals is None
            else residuals
        )
        self.half = max(2, int(np.ceil(max(step) / 2.0)))
        self.floor = float("inf")
        self._useful = None
        self.region_half = int(region_half)
        self.last_region = None
        self.region_spread = (
            np.sqrt(2.0)
            * HALF_NORMAL_SPREAD
            / np.sqrt((2 * self.region_half + 1) ** 3 / NOISE_CORRELATION_VOXELS)
        )
        size = 2 * self.half + 1
        # the largest change of a region's mean residual that resampling the noise can make:
        # two independent noise draws, each of spread HALF_NORMAL_SPREAD * r0 over n / Vc samples
        self.spread = (
            np.sqrt(2.0) * HALF_NORMAL_SPREAD / np.sqrt(size**3 / NOISE_CORRELATION_VOXELS)
        )

    def local(self, field: DisplacementField) -> np.ndarray:
        """Per-node local mean residual of ``field`` (gray levels); updates the noise floor.

        The floor is the smaller of eq. 1's background residual and the lower quartile of the
        nodes' local residuals (eq. 1 is inflated where a flat region agrees in phase with
        textured material), and the smallest seen so far: the noise belongs to the scans.
        """
        (local, self.last_region), floor = self.residuals.local_means(
            field, (self.half, self.region_half)
        )
        if np.isfinite(local).any():
            floor = min(floor, float(np.nanpercentile(local, 25.0)))
        if np.isfinite(floor):
            self.floor = min(self.floor, floor)
        elif not np.isfinite(self.floor):
            self.floor = 0.0
        return local

    @property
    def tolerance(self) -> float:
        """How much a node's cell residual may change by noise alone (gray levels)."""
        return self.tolerance_at(self.floor)

    def tolerance_at(self, level: float) -> float:
        """:attr:`tolerance` for cells whose noise leaves a residual of ``level`` gray levels."""
        return NOISE_Z * self.spread * level

    @property
    def region_tolerance(self) -> float:
        """How much the residual over a node's subvolume may change by noise alone."""
        return NOISE_Z * self.region_spread * self.floor

    def _local_gradient(self, field: DisplacementField, half: int) -> np.ndarray:
        return self.residuals.gradient_means(field, half)

    def useful(self, field: DisplacementField) -> np.ndarray:
        """Per node, the residual change that :data:`MIN_USEFUL_CHANGE` voxels explain.

        On clean scans the noise floor is tiny and any change would count as an improvement;
        a region counts as improved only if its residual also fell by more than this.
        """
        if self._useful is None:
            gradient = self._local_gradient(field, self.region_half)
            self._useful = 0.5 * MIN_USEFUL_CHANGE * np.nan_to_num(gradient)
        return self._useful

    def unexplained(self, field: DisplacementField, local: np.ndarray) -> np.ndarray:
        """Nodes whose local residual only an error of more than ~1 voxel explains.

        An error ``e`` of the field misplaces the texture by ``|grad G . e|``, on average
        ``|grad G| |e| / 2`` over directions; nodes whose local residual exceeds the noise floor
        by more than :data:`FLAG_ERROR` voxels' worth of that are flagged (a subvolume half in a
        textureless region, or half outside the specimen, lands here whatever its value). The
        excess must also stand above what the imaging noise alone scatters a cell's mean by
        (:attr:`tolerance`): under heavy noise the cells' residuals spread by a third of the
        floor, and the cells on the high side of that spread are no more wrong than the others
        (measured on the narrow band under noise 0.8 x the texture's std: the 9 nodes flagged
        without this term were 0.07-0.52 voxel off, median 0.24, against a median of 0.21 for
        all nodes). On clean scans the term is a small fraction of the floor, itself small.

        The excess is taken over the floor or over the lower quartile of the cells' residuals,
        whichever is higher: eq. 1 leaves out the voxels that the noise pushes across a phase
        threshold, so where the noise is large against the phases' contrast it reads below what
        a right field leaves (docs/heldout.md: a 3 % noise on a smoothed real rock, a right field
        leaves cells of 7.4-8.6 gray levels over a floor of 5.1, and 99 % of the nodes were
        flagged at 0.2 voxel off); the noise scatter then scales with the same level.
        """
        gradient = self._local_gradient(field, self.half)
        level = self.floor
        if np.isfinite(local).any():
            level = max(level, float(np.nanpercentile(local, 25.0)))
        excess = local - level
        return np.isfinite(excess) & (
            excess > 0.5 * FLAG_ERROR * gradient + self.tolerance_at(level)
        )

    def discontinuous(
        self, field: DisplacementField, local: np.ndarray, flagged: np.ndarray
    ) -> np.ndarray:
        """Of the ``flagged`` nodes (:meth:`unexplained`), those whose residual excess is
        one-signed (:data:`DISCONTINUITY_SIGN`) and that form a surface (:func:`surfaces`):
        material that appeared or vanished, not texture misplaced by a wrong value. ``local``
        is the nodes' cell residual.
        """
        flagged = np.asarray(flagged, bool)
        if not flagged.any():  # nothing flagged: no pull-back of the signed residual
            return flagged
        signed = self.residuals.signed_means(field, self.half)
        excess = local - self.floor
        one_signed = np.isfinite(signed) & (excess > 0)
        one_signed &= np.abs(signed) > DISCONTINUITY_SIGN * excess
        return surfaces(one_signed & flagged)


def surfaces(nodes: np.ndarray) -> np.ndarray:
    """The nodes of ``nodes`` (bool, the grid's shape) in groups of at least
    :data:`MIN_DISCONTINUITY_NODES` touching nodes (26-connectivity): a crack is a surface
    that crosses many nodes; a lone node with a one-signed residual is an outlier (a coarse
    two-phase texture misplaced inside one small cell can read one-signed)."""
    nodes = np.asarray(nodes, bool)
    if not nodes.any():
        return nodes
    labels, count = ndimage.label(nodes, structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(labels.reshape(-1), minlength=count + 1)
    large = sizes >= MIN_DISCONTINUITY_NODES
    large[0] = False
    return large[labels]


def crack_shield(field: DisplacementField, crack: np.ndarray) -> np.ndarray:
    """The nodes a correction must not change because of a discontinuity: the crack's own
    nodes, and the good measured nodes within :data:`CRACK_SHIELD_NODES` grid steps of one.

    The passes warp with a field densified by cubic splines, through the crack's refilled
    nodes; near the crack that warp is wrong whatever the nodes' values, and a correcting match
    there would move good nodes towards the crack's smeared motion (measured: 0.01 -> 0.4-0.6
    voxel on the synthetic crack of tests/engine/test_correction.py).
    """
    crack = np.asarray(crack, bool)
    if not crack.any():
        return np.zeros(field.shape, bool)
    near = ndimage.binary_dilation(
        crack, structure=np.ones((3, 3, 3), bool), iterations=CRACK_SHIELD_NODES
    )
    good = np.isin(field.status, [int(s) for s in GOOD_STATUSES])
    good &= field.provenance == Provenance.MEASURED
    return crack | (near & good)


def flag_and_refill(judge, field, local, masked, clean_options):
    """Give unexplained nodes ``OUTLIER_REPLACED`` and refill them from their neighbours."""
    flagged = judge.unexplained(field, local) & ~masked
    if not flagged.any() or flagged.all():
        return field, local, 0
    marked = field.copy()
    marked.status[flagged] = Status.OUTLIER_REPLACED
    try:
        refilled = clean(marked, **clean_options)
    except ValueError:
        return field, local, 0
    refilled.status[flagged] = Status.OUTLIER_REPLACED
    refilled.provenance[flagged] = Provenance.REPLACED
    return refilled, judge.local(refilled), int(flagged.sum())


def mix_fields(current: DisplacementField, candidate: DisplacementField, accept: np.ndarray):
    """``candidate`` where ``accept``, ``current`` elsewhere (values and quality arrays)."""
    mixed = candidate.copy()
    keep = ~accept
    mixed.u[keep] = current.u[keep]
    for name in ("zncc", "status", "iterations", "provenance"):
        getattr(mixed, name)[keep] = getattr(current, name)[keep]
    if mixed.uncertainty is not None:
        if current.uncertainty is not None:
            mixed.uncertainty[keep] = current.uncertainty[keep]
        else:
            mixed.uncertainty = None
    if mixed.gradient is not None:
        if current.gradient is not None:
            mixed.gradient[keep] = current.gradient[keep]
        else:
            mixed.gradient = None
    return mixed


def shrink_to_support(current: DisplacementField, candidate: DisplacementField, sigma):
    """Apply each node's correction in proportion to how far it stands above its noise.

    A correction ``c = candidate - current`` measured with uncertainty ``σ`` (the correcting
    match's, voxels, norm of the three components) is applied as ``s · c`` with
    ``s = max(0, 1 - (SUPPORT_Z σ / |c|)²)``: in full where it is many times its uncertainty
    (clean scans: nothing changes), shrunk where it is comparable, and not at all where the
    noise alone explains it (heavy noise on weak texture, where applying it in full moved nodes
    by their matching noise and made the field worse). Nodes of unknown ``σ`` (interpolated
    matches) keep their correction whole.

    Parameters
    ----------
    current, candidate : DisplacementField
        The field before the pass and its proposed update (same grid).
    sigma : ndarray, shape ``current.shape``
        Uncertainty of each node's correcting match (voxels; NaN: unknown).

    Returns
    -------
    shrunk : DisplacementField
        ``candidate`` with the shrunk values (quality arrays unchanged).
    unsupported : ndarray of bool, ``current.shape``
        Nodes whose correction the noise explains (``s = 0``): to be refused.
    """
    change = candidate.u - current.u
    size = np.linalg.norm(change, axis=-1)
    sigma = np.asarray(sigma, dtype=np.float64).reshape(size.shape)
    known = np.isfinite(sigma) & np.isfinite(size) & (size > 0)
    factor = np.ones(size.shape)
    factor[known] = np.clip(1.0 - (SUPPORT_Z * sigma[known] / size[known]) ** 2, 0.0, 1.0)
    shrunk = candidate.copy()
    shrunk.u = current.u + factor[..., None] * change
    if shrunk.gradient is not None and current.gradient is not None:
        shrunk.gradient = current.gradient + factor[..., None, None] * (
            candidate.gradient - current.gradient
        )
    return shrunk, known & (factor <= 0.0)


def noise_only_corrections(
    current: DisplacementField, candidate: DisplacementField, sigma, bend
) -> np.ndarray:
    """Measured nodes where a pass has nothing to correct that the noise lets it see.

    A correcting match re-measures a node on the same images that gave its value, so its noise
    is not news: under heavy noise a pass re-applies the matching noise (the correction of a node
    is then no smaller than its own error, and points the wrong way as often as not) and makes
    a field that needed nothing worse. Node by node :func:`shrink_to_support` cannot tell such a
    correction from a real one of the same size. Pooled over the node's neighbourhood
    (:data:`NOISE_REGION_NODES`) it can: where the corrections hold no more energy than their
    matches' uncertainties let noise give them (``Σ|c|²`` at most :data:`NOISE_Z` spreads above
    ``Σσ²``; the noise energy of ``n`` nodes spreads by ``sqrt(2 / 3n) Σσ²``) *and* the field's
    own bend over the correcting subvolume stays below the node's ``σ`` everywhere in that
    neighbourhood (no shape-function bias the noise would let a match find), the region holds
    only noise, and its measured nodes keep their values. Nodes whose value is not a measurement (refilled, interpolated) are not
    judged here: their correcting match is the first measurement they get.

    Parameters
    ----------
    current, candidate : DisplacementField
        The field before the pass and its proposed update (same grid), before any shrink.
    sigma : ndarray, shape ``current.shape``
        Uncertainty of each node's correcting match (voxels, norm; NaN: unknown).
    bend : ndarray, shape ``current.shape``
        What an affine shape function on the correcting subvolume leaves of ``current``'s
        curvature at each node (voxels, :func:`.pass_method.node_bend`; NaN: unknown, and
        then no node near it is refused).

    Returns
    -------
    ndarray of bool, ``current.shape``
        Nodes to refuse: their correction is the noise's.
    """
    change = np.asarray(candidate.u, dtype=np.float64) - current.u
    energy = np.sum(change**2, axis=-1)
    sigma = np.asarray(sigma, dtype=np.float64).reshape(energy.shape)
    known = np.isfinite(sigma) & np.isfinite(energy)
    size = 2 * NOISE_REGION_NODES + 1
    pooled = ndimage.uniform_filter(np.where(known, energy, 0.0), size, mode="constant")
    noise = ndimage.uniform_filter(np.where(known, sigma**2, 0.0), size, mode="constant")
    count = ndimage.uniform_filter(known.astype(np.float64), size, mode="constant") * size**3
    # pure noise scatters the pooled energy of n nodes (3 components each) around Σσ² by
    # sqrt(2 / 3n) of it: a region shows a correction only NOISE_Z such deviations above
    margin = 1.0 + NOISE_Z * np.sqrt(2.0 / (3.0 * np.maximum(count, 1.0)))
    bend = np.asarray(bend, dtype=np.float64)
    bend = np.where(np.isfinite(bend), bend, np.inf)  # an unknown bend may be any: not judged
    bent = ndimage.maximum_filter(bend, size, mode="nearest")
    measured = np.isin(current.status, [int(s) for s in GOOD_STATUSES])
    measured &= np.isin(current.provenance, [Provenance.MEASURED, Provenance.CORRECTED])
    return known & measured & (pooled <= margin * noise) & ~(bent > sigma)


def unsupported_updates(delta: DisplacementField, read_points: np.ndarray) -> np.ndarray:
    """Nodes whose update reads ``delta`` too far outside the region it was measured in.

    Parameters
    ----------
    delta : DisplacementField
        The correcting field ``ΔD`` (after cleaning), on its own grid.
    read_points : ndarray, shape (n_nodes, 3)
        Where each node's update reads ``ΔD`` (voxels, (z, y, x)): ``X + D(X)`` for the exact
        update in the loaded frame, the node ``X`` itself otherwise.

    Returns
    -------
    ndarray of bool, shape (n_nodes,)
        True where a read point lies more than :data:`MEASURED_REACH` grid steps (per axis)
        outside the bounding box of ``delta``'s good measured nodes (status in
        :data:`.field.GOOD_STATUSES`, provenance ``MEASURED``), or is not finite. There ``ΔD`` is
        the spline's extrapolation of the border nodes (large displacements carry the faces'
        nodes one or two steps beyond the correcting grid), which nothing in the images
        supports; the node keeps its previous value.
    """
    points = np.asarray(read_points, dtype=np.float64).reshape(-1, 3)
    good = np.isin(delta.status.reshape(-1), [int(s) for s in GOOD_STATUSES]) & (
        delta.provenance.reshape(-1) == Provenance.MEASURED
    )
    if not good.any():
        return np.ones(len(points), bool)
    measured = delta.points[good]
    lo, hi = measured.min(axis=0), measured.max(axis=0)
    beyond = np.maximum(lo - points, points - hi) / np.asarray(delta.step, dtype=np.float64)
    return ~(np.max(beyond, axis=1) <= MEASURED_REACH)


def accept_locally(judge: Judge, current, local_current, candidate, refuse=None):
    """Node by node: keep the candidate's value unless its local residual rose above the noise.

    ``refuse`` (bool, the grid's shape, optional) marks nodes refused whatever their residual
    (:func:`unsupported_updates`). Returns the mixed field, its local residual, the accepted and
    the improved node masks.
    """
    tolerance = judge.tolerance
    region_current = judge.last_region
    local = judge.local(candidate)
    rose = local > local_current + tolerance
    rose |= np.isnan(local)  # a region the candidate sends out of the scan cannot be judged
    if refuse is not None:
        rose |= np.asarray(refuse, bool).reshape(rose.shape)
    accept = ~rose
    mixed, local_mixed = candidate, local
    for _ in range(ACCEPTANCE_SWEEPS):
        if accept.all():
            break
        mixed = mix_fields(current, candidate, accept)
        local_mixed = judge.local(mixed)
        worse = accept & ((local_mixed > local_current + tolerance) | np.isnan(local_mixed))
        if not worse.any():
            break
        accept &= ~worse
    else:
        mixed = mix_fields(current, candidate, accept)
        local_mixed = judge.local(mixed)
    improved = accept & (
        judge.last_region < region_current - judge.region_tolerance - judge.useful(mixed)
    )
    return mixed, local_mixed, accept, improved
