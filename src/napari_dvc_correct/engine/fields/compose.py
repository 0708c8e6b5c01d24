"""Composition of displacement fields (displacement superposition).

If material at ``X`` first moves by ``a(X)`` to ``y = X + a(X)`` and then by ``b(y)`` (a field
measured at the positions reached by the first motion), the total Lagrangian displacement is

    ``w(X) = a(X) + b(X + a(X))``,

with ``b`` interpolated at the displaced positions by cubic splines on its grid
(:class:`.field_spline.FieldSpline`). This is the exact update of the self-correction and the
"displacement superposition" of incremental scan series. The paper's plain sum
``w(X) = a(X) + b(X)`` at the same node is kept as ``mode="sum"``; it is exact only when ``b`` is
uniform.
"""

from __future__ import annotations

import copy

import numpy as np

from .field import GOOD_STATUSES, DisplacementField, Provenance
from .field_spline import FieldSpline

COMPOSE_MODES = ("exact", "sum")


def _nearest_nodes(field: DisplacementField, points: np.ndarray) -> tuple[np.ndarray, ...]:
    """Grid indices of the node of ``field`` nearest to each of ``points`` (N, 3), clipped."""
    index = np.rint((points - np.asarray(field.origin)) / np.asarray(field.step))
    index = np.nan_to_num(index, nan=0.0)
    return tuple(np.clip(index[:, a], 0, field.shape[a] - 1).astype(np.intp) for a in range(3))


def compose(
    first: DisplacementField,
    second: DisplacementField,
    *,
    mode: str = "exact",
) -> DisplacementField:
    """The displacement ``first`` followed by ``second``, on the grid of ``first``.

    Parameters
    ----------
    first : DisplacementField
        ``a(X)``, Lagrangian displacement from the reference positions ``X`` (its nodes).
        Nodes with non-finite values give non-finite results.
    second : DisplacementField
        ``b(y)``, displacement defined at the positions ``y = X + a(X)`` reached by ``first``
        (e.g. the next increment of a scan series, measured with the previous state as
        reference). Its nodes must all be finite (clean it first); it is extrapolated beyond
        its hull (see :mod:`.warp`).
    mode : {"exact", "sum"}
        ``"exact"``: ``w(X) = a(X) + b(X + a(X))``. ``"sum"``: the paper's ``w = a + b`` at the
        same node (needs the same grid).

    Returns
    -------
    DisplacementField
        On ``first``'s grid. ``u = w``; ``zncc`` is the lower of the two (``second``'s taken at
        the node nearest to ``X + a(X)``), ``status`` and ``provenance`` are ``first``'s where it
        is not a good measurement and ``second``'s otherwise, ``iterations`` are ``second``'s.
        ``gradient`` follows the chain rule ``∇w = ∇a + ∇b(X + a)(I + ∇a)`` when both fields
        have one (``∇a + ∇b`` for ``"sum"``), else None. ``uncertainty`` adds both fields' in
        quadrature (``second``'s at the nearest node) when both have one, else None. ``params`` are ``first``'s;
        ``metadata["composition"]`` records the mode.
    """
    if mode not in COMPOSE_MODES:
        raise ValueError(f"mode must be one of {COMPOSE_MODES}, got {mode!r}")
    grid = first.shape
    points = first.points
    a = first.displacement
    finite = np.all(np.isfinite(a), axis=1)
    if mode == "sum":
        if not first.same_grid(second):
            raise ValueError(
                "mode='sum' adds the fields node by node: both must be on the same grid "
                f"(got {first.shape} at {first.origin} step {first.step} and {second.shape} at "
                f"{second.origin} step {second.step}); use mode='exact'"
            )
        displaced = points
        b = second.displacement
        nearest = tuple(np.unravel_index(np.arange(first.n_points), grid))
    else:
        displaced = points + a
        b = np.full_like(a, np.nan)
        b[finite] = FieldSpline.from_field(second)(displaced[finite])
        nearest = _nearest_nodes(second, displaced)
    u = (a + b).reshape(*grid, 3)

    zncc = np.fmin(first.zncc.reshape(-1), second.zncc[nearest]).reshape(grid)
    first_good = np.isin(first.status.reshape(-1), [int(s) for s in GOOD_STATUSES])
    status = np.where(first_good, second.status[nearest], first.status.reshape(-1)).reshape(grid)
    first_measured = first.provenance.reshape(-1) == Provenance.MEASURED
    provenance = np.where(
        first_measured, second.provenance[nearest], first.provenance.reshape(-1)
    ).reshape(grid)
    iterations = second.iterations[nearest].reshape(grid)

    gradient = None
    if first.gradient is not None and second.gradient is not None:
        ga = first.gradient.reshape(-1, 3, 3)
        if mode == "sum":
            gb = second.gradient.reshape(-1, 3, 3)
            gradient = (ga + gb).reshape(*grid, 3, 3)
        elif np.all(np.isfinite(second.gradient)):
            gb = np.full_like(ga, np.nan)
            spline = FieldSpline(
                second.origin, second.step, second.gradient.reshape(*second.shape, 9)
            )
            gb[finite] = spline(displaced[finite]).reshape(-1, 3, 3)
            gradient = (ga + gb @ (np.eye(3) + ga)).reshape(*grid, 3, 3)

    uncertainty = None  # independent errors add in quadrature (a scan series' increments)
    if first.uncertainty is not None and second.uncertainty is not None:
        sb = second.uncertainty[nearest]
        uncertainty = np.hypot(first.uncertainty.reshape(-1, 3), sb).reshape(*grid, 3)

    metadata = copy.deepcopy(first.metadata)
    metadata["composition"] = {"mode": mode}
    return DisplacementField(
        origin=first.origin,
        step=first.step,
        u=u,
        zncc=zncc,
        status=status,
        iterations=iterations,
        provenance=provenance,
        gradient=gradient,
        uncertainty=uncertainty,
        params=copy.deepcopy(first.params),
        metadata=metadata,
    )
