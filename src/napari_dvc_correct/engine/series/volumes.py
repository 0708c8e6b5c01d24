"""The volume operations of a scan series on a grid, behind one small interface.

:func:`.strategies.series_volumes_iter` is the one series loop (total or incremental strategy, the
self-correction of increments and/or totals, the composition of the increments, the cleaning,
the provenance and the summary's gray residuals). Everything it does to the *volumes* goes
through a :class:`SeriesVolumes`; the fields (node arrays) always stay in memory:

* :meth:`~SeriesVolumes.correlate`: the DVC of states ``i`` and ``j`` on the series' grid;
* :meth:`~SeriesVolumes.correct`: the self-correction of a field of states ``i`` and ``j``;
* :meth:`~SeriesVolumes.carry_mask`: the first state's material mask moved by a total field
  ``U_0→k`` to state ``k`` (the mask of the increment ``k→k+1``);
* :meth:`~SeriesVolumes.mean_residual`: the mean gray residual of a total field against states
  0 and ``k`` (:func:`.residual.mean_gray_residual`, reference frame, over the grid's hull);
* :meth:`~SeriesVolumes.release` and :meth:`~SeriesVolumes.close`: drop a carried mask, and
  everything at the end (also on error or cancel).

:class:`InMemorySeries` is the in-memory back-end (whole arrays; the results of
:func:`.strategies.series_iter`). The out-of-core back-end, lazily read volumes in spatial batches on
Dask, is ``napari_dvc_correct.tiled.series.TiledSeries`` (above the engine).
"""

from __future__ import annotations

from collections.abc import Generator, Sequence

import numpy as np

from ..correction.self_correction import correct_iter
from ..correlation.correlate import correlate_iter
from ..correlation.params import CorrelationParams
from ..evaluation.residual import mean_gray_residual
from ..fields import warp
from ..fields.field import DisplacementField
from ..progress import Progress


class SeriesVolumes:
    """What the series loop needs of the states' volumes (the interface; see the module).

    Attributes
    ----------
    n_states : int
        Number of states ``V0, V1, ...`` (>= 2).
    mask : object or None
        The first state's material mask (non-zero = inside) in the back-end's own form, or None.
    """

    n_states: int
    mask = None

    def correlate(self, i: int, j: int, mask) -> Generator[Progress, None, DisplacementField]:
        """DVC of ``V_i`` (reference) and ``V_j`` (deformed) on the series' grid, with ``mask``
        (``self.mask``, a mask from :meth:`carry_mask`, or None)."""
        raise NotImplementedError

    def correct(
        self, i: int, j: int, field: DisplacementField, mask
    ) -> Generator[Progress, None, DisplacementField]:
        """Self-correct ``field`` of ``V_i`` and ``V_j`` (the series' correction options)."""
        raise NotImplementedError

    def carry_mask(self, total: DisplacementField) -> Generator[Progress, None, object]:
        """``self.mask`` moved to the state of ``total`` (``U_0→k``, cleaned and filled): the
        forward warp of the mask, inside where it exceeds 0.5; None where no voxel is inside."""
        raise NotImplementedError

    def mean_residual(self, k: int, total: DisplacementField) -> Generator[Progress, None, float]:
        """Mean of ``|V_k(X + U(X)) - V_0(X)|`` over the grid's hull (gray levels) for ``total``
        (``U_0→k``, cleaned and filled)."""
        raise NotImplementedError

    def release(self, mask) -> None:
        """``mask`` (from :meth:`carry_mask`) is no longer needed."""

    def close(self) -> None:
        """Free what the back-end holds (temporary files, connections); called once at the end."""


def _value(value):
    """A generator that yields nothing and returns ``value`` (an operation without progress)."""
    return value
    yield  # pragma: no cover - makes this a generator


class InMemorySeries(SeriesVolumes):
    """The states as arrays (memory maps are fine), every operation on whole volumes.

    Parameters
    ----------
    volumes : sequence of ndarray, each shape (nz, ny, nx)
        ``V0, V1, ...`` (checked by the caller), any real dtype.
    params : CorrelationParams
        DVC parameters of every correlation and correction.
    grid : (origin, step, shape)
        The POI grid in the first state's voxels.
    mask : ndarray, shape (nz, ny, nx), optional
        The first state's material mask (non-zero = inside).
    correction_options : dict, optional
        Keyword arguments of :func:`.self_correction.correct_iter`.
    """

    def __init__(
        self,
        volumes: Sequence[np.ndarray],
        params: CorrelationParams,
        grid: tuple,
        mask: np.ndarray | None = None,
        correction_options: dict | None = None,
    ):
        self.volumes = list(volumes)
        self.n_states = len(self.volumes)
        self.params = params
        self.grid = grid
        self.mask = mask
        self.options = dict(correction_options or {})

    def correlate(self, i, j, mask):
        return correlate_iter(
            self.volumes[i], self.volumes[j], self.params, mask=mask, grid=self.grid
        )

    def correct(self, i, j, field, mask):
        return correct_iter(
            self.volumes[i], self.volumes[j], field, self.params, mask=mask, **self.options
        )

    def carry_mask(self, total):
        inside = (np.asarray(self.mask) != 0).astype(np.float32)  # non-zero = material
        moved = warp.warp_forward(inside, total, cval=0.0) > 0.5
        return _value(moved if moved.any() else None)

    def mean_residual(self, k, total):
        return _value(mean_gray_residual(self.volumes[0], self.volumes[k], total))
