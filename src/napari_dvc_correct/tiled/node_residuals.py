"""The judge's numbers out of core: node residuals and gradients of the correction, block by block.

:class:`TiledResiduals` gives what :class:`..engine.correction.acceptance.ReferenceResiduals` gives in
memory — the box means of the reference-frame residual ``|F(X + D(X)) - G(X)|`` at every node
(cells and subvolumes), eq. 1's sums for the noise floor, and the box means of the Gaussian gray
gradient of ``G`` — for a tiled correction (:class:`.correction.TiledVolumes`): the grid is cut
into blocks of ``node_block`` nodes per axis, and each block (a Dask task) reads only the region
its nodes' boxes need.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy import ndimage

from ..engine.evaluation.local_accuracy import local_mean_residual
from ..engine.evaluation.phases import NO_PHASE, label_phases
from ..engine.fields.field import DisplacementField
from ..engine.fields.field_spline import FieldSpline
from ..engine.fields.warp import pull_back_block
from ..engine.progress import run_to_completion
from .volumes import LazySampler

#: Reach of the Gaussian gradient of :class:`..engine.correction.acceptance.ReferenceResiduals`
#: (sigma 1 voxel, truncated at 4 sigma).
GRADIENT_REACH = 4

#: Working bytes per voxel of a node block's region (G, F~, residual, box filters, F's region
#: and its coefficients, positions).
BYTES_PER_NODE_REGION_VOXEL = 120


# --- block tasks (run on workers) ----------------------------------------------------------------
def _node_residual_block(reference, deformed, spline, job):
    """Box means of the reference-frame residual at one block's nodes, and eq. 1's sums over the
    block's own voxels."""
    g = reference.read_region(job.region)
    moved = job.gray_levels.apply(
        pull_back_block(LazySampler(deformed), spline, job.region), job.region
    )
    residual = np.abs(moved - g)
    means = [local_mean_residual(residual, job.nodes, half) for half in job.halves]
    total, count = 0.0, 0
    if job.thresholds is not None:
        own_g, own_moved, own = g[job.owned], moved[job.owned], residual[job.owned]
        labels = label_phases(own_g, job.thresholds[0])
        # the moved volume is in the reference's gray levels: the reference's thresholds
        keep = (labels == label_phases(own_moved, job.thresholds[0])) & (labels < NO_PHASE)
        keep &= np.isfinite(own)
        total, count = float(np.sum(own[keep], dtype=np.float64)), int(keep.sum())
    return job.index, means, total, count


def _node_signed_block(reference, deformed, spline, job):
    """Box means of the signed residual ``G - map(F~)`` at one block's nodes."""
    g = reference.read_region(job.region)
    moved = pull_back_block(LazySampler(deformed), spline, job.region)
    signed = g - job.gray_levels.apply(moved, job.region)
    return job.index, local_mean_residual(signed, job.nodes, job.halves[0])


def _node_gradient_block(reference, job):
    """Box means of the Gaussian gray gradient magnitude of ``G`` at one block's nodes."""
    g = reference.read_region(job.region)
    gradient = ndimage.gaussian_gradient_magnitude(g, 1.0)[job.inner]
    return job.index, local_mean_residual(gradient, job.nodes, job.halves[0])


class TiledResiduals:
    """:class:`..engine.correction.acceptance.ReferenceResiduals`' numbers, node block by node block."""

    def __init__(self, volumes, thresholds, gray_levels):
        self.volumes = volumes
        self.thresholds = thresholds
        self.gray_levels = gray_levels
        self._gradients: dict = {}

    def _jobs(self, field, halves, reach_extra=0, owned=False):
        shape = np.asarray(self.volumes.shape, np.int64)
        centers = np.clip(np.rint(field.points).astype(np.int64), 0, shape - 1)
        centers = centers.reshape(*field.shape, 3)
        origin, step = np.asarray(field.origin, float), np.asarray(field.step, float)
        flat = np.arange(field.n_points).reshape(field.shape)
        reach = max(halves)
        b = self.volumes.node_block
        jobs = []
        for i0 in range(0, field.shape[0], b):
            for j0 in range(0, field.shape[1], b):
                for k0 in range(0, field.shape[2], b):
                    start = np.array([i0, j0, k0])
                    stop = np.minimum(start + b, field.shape)
                    window = tuple(slice(a, c) for a, c in zip(start, stop))
                    points = centers[window].reshape(-1, 3)
                    lo = np.maximum(points.min(axis=0) - reach, 0)
                    hi = np.minimum(points.max(axis=0) + reach + 1, shape)
                    own_lo = np.where(
                        start == 0, 0, np.clip(np.rint(origin + (start - 0.5) * step), 0, shape)
                    ).astype(np.int64)
                    own_hi = np.where(
                        stop == field.shape,
                        shape,
                        np.clip(np.rint(origin + (stop - 0.5) * step), 0, shape),
                    ).astype(np.int64)
                    if owned:
                        lo, hi = np.minimum(lo, own_lo), np.maximum(hi, own_hi)
                    # the region read: with the filter's reach where the volume goes on
                    read_lo = np.maximum(lo - reach_extra, 0)
                    read_hi = np.minimum(hi + reach_extra, shape)
                    jobs.append(
                        SimpleNamespace(
                            index=flat[window].reshape(-1),
                            # the block's nodes as a grid in the region's voxels (whole-voxel
                            # grids, so rounding commutes with the shift)
                            nodes=DisplacementField.zeros(
                                tuple(float(v) for v in origin + start * step - lo),
                                tuple(float(v) for v in step),
                                tuple(int(n) for n in stop - start),
                            ),
                            halves=tuple(int(h) for h in halves),
                            region=tuple(slice(int(a), int(c)) for a, c in zip(read_lo, read_hi)),
                            inner=tuple(
                                slice(int(a - r), int(c - r)) for a, c, r in zip(lo, hi, read_lo)
                            ),
                            owned=tuple(
                                slice(int(a - r), int(c - r))
                                for a, c, r in zip(own_lo, own_hi, read_lo)
                            ),
                            thresholds=self.thresholds,
                            gray_levels=self.gray_levels,
                        )
                    )
        return jobs

    def local_means(self, field: DisplacementField, halves):
        volumes = self.volumes
        jobs = self._jobs(field, halves, owned=True)
        spline = FieldSpline.from_field(field)
        results = run_to_completion(
            volumes._tasks(
                _node_residual_block,
                [volumes.reference, volumes.deformed, spline],
                jobs,
                "local residual",
            )
        )
        means = [np.full(field.n_points, np.nan) for _ in halves]
        total, count = 0.0, 0
        for index, block_means, block_total, block_count in results:
            for out, values in zip(means, block_means):
                out[index] = values.reshape(-1)
            total, count = total + block_total, count + block_count
        floor = total / count if self.thresholds is not None and count else float("inf")
        return [m.reshape(field.shape) for m in means], floor

    def _node_means(self, field, function, shared, jobs, stage) -> np.ndarray:
        """Run ``function(*shared, job)`` per node block; gather its ``(index, means)``."""
        results = run_to_completion(self.volumes._tasks(function, shared, jobs, stage))
        means = np.full(field.n_points, np.nan)
        for index, values in results:
            means[index] = values.reshape(-1)
        return means.reshape(field.shape)

    def signed_means(self, field: DisplacementField, half: int):
        volumes = self.volumes
        shared = [volumes.reference, volumes.deformed, FieldSpline.from_field(field)]
        jobs = self._jobs(field, (half,))
        return self._node_means(field, _node_signed_block, shared, jobs, "signed residual")

    def gradient_means(self, field: DisplacementField, half: int):
        key = (tuple(field.origin), tuple(field.step), field.shape, int(half))
        if key not in self._gradients:
            jobs = self._jobs(field, (half,), reach_extra=GRADIENT_REACH)
            self._gradients[key] = self._node_means(
                field, _node_gradient_block, [self.volumes.reference], jobs, "local gradient"
            )
        return self._gradients[key]


# --- memory --------------------------------------------------------------------------------------
def node_bytes(step, node_block: int, half: int, reach: float) -> float:
    edge = np.asarray(step, np.float64) * node_block + 2 * half + 1
    region = np.prod(edge + 2 * (reach + GRADIENT_REACH))
    return float(region) * BYTES_PER_NODE_REGION_VOXEL
