"""A line profile across a band, without Qt: values of a field quantity along a segment.

The picture a geomechanics paper shows: displacement and strain along a line drawn across a shear
band, before and after correction. The line is given in world coordinates (z, y, x, the units of
the layers' scale); the values are interpolated linearly between the grid nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import layers as L
from ..engine.fields.field import DisplacementField


@dataclass
class Profile:
    """Values of one quantity of one field along a line.

    Attributes
    ----------
    source : str
        The field's name (``"uncorrected"``, ``"corrected"``...).
    quantity, unit : str
    distance : ndarray (n,)
        Distance from the line's start, world units.
    values : ndarray (n,)
        NaN where the line leaves the grid or crosses a node without a displacement.
    distance_unit : str
        Unit of ``distance``: the field's length unit (``"mm"``...), ``"vx"`` (voxels).
    """

    source: str
    quantity: str
    unit: str
    distance: np.ndarray
    values: np.ndarray
    distance_unit: str = ""


def line_profile(
    field: DisplacementField,
    source: str,
    quantity: str,
    start,
    end,
    n: int = 200,
    values_cache: dict | None = None,
) -> Profile:
    """Sample ``quantity`` of ``field`` at ``n`` points from ``start`` to ``end`` (world z, y, x).

    The field is placed by its ``metadata["voxel_size"]`` and ``["offset"]``, as its layers are.
    ``values_cache`` (a dict kept by the caller) keeps the field's quantity values between calls.
    """
    from scipy.ndimage import map_coordinates

    start = np.asarray(start, float)[-3:]
    end = np.asarray(end, float)[-3:]
    if np.allclose(start, end):
        raise ValueError("the line has no length: click two different points")
    key = (id(field), quantity)
    cached = values_cache.get(key) if values_cache is not None else None
    if cached is not None and cached[0] is field:
        values = cached[1]
    else:
        values = L.quantity_values(field, quantity).astype(np.float64)
        if values_cache is not None:
            values_cache[key] = (field, values)
    placement = L.grid_placement(
        field, field.metadata.get("voxel_size"), field.metadata.get("offset")
    )
    scale, translate = np.asarray(placement["scale"]), np.asarray(placement["translate"])
    t = np.linspace(0.0, 1.0, int(n))
    world = start + t[:, None] * (end - start)
    index = (world - translate) / scale  # fractional node indices
    outside = np.any((index < 0) | (index > np.asarray(field.shape) - 1), axis=1)
    sampled = map_coordinates(values, index.T, order=1, mode="nearest")
    sampled[outside] = np.nan
    return Profile(
        source=source,
        quantity=quantity,
        unit=L.unit_of(quantity, field),
        distance=t * float(np.linalg.norm(end - start)),
        values=sampled,
        distance_unit=L.unit_of("|u|", field),  # a length, in the units of the layers' scale
    )


def strain_quantity(quantity: str) -> str:
    """The strain to plot with the displacement: the chosen one if it is a strain, else εeq."""
    return quantity if "strain" in L.QUANTITIES.get(quantity, ("", ""))[1] else "εeq"


def profiles(
    fields: dict, quantity: str, start, end, n: int = 200, values_cache: dict | None = None
) -> list[list[Profile]]:
    """``[displacement profiles, strain profiles]``, one profile per field of ``fields``.

    The displacement is ``|u|`` (or the chosen component when ``quantity`` is one), the strain
    :func:`strain_quantity`.
    """
    displacement = quantity if quantity in ("uz", "uy", "ux") else "|u|"
    strain = strain_quantity(quantity)
    return [
        [line_profile(f, s, displacement, start, end, n, values_cache) for s, f in fields.items()],
        [line_profile(f, s, strain, start, end, n, values_cache) for s, f in fields.items()],
    ]
