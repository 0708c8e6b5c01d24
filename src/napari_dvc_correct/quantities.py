"""What a field layer can show, without Qt or napari layers: the quantities and their values.

:data:`QUANTITIES` lists them (displacement, its components, every strain component, principal,
volumetric, maximum-shear and equivalent strain, ZNCC, status, uncertainty, residual);
:func:`quantity_values` computes one on the grid of a :class:`DisplacementField` in physical units
(the field's ``metadata["voxel_size"]`` and ``["unit"]``), :func:`quantity_style` its colours.
"""

from __future__ import annotations

import weakref

import numpy as np

from .engine.fields.field import DisplacementField, Status

#: Colours of the status codes in the status quantity (converged stays transparent).
STATUS_COLORS = {
    None: "transparent",
    int(Status.CONVERGED): "transparent",
    int(Status.MAX_ITERATIONS): "yellow",
    int(Status.DIVERGED): "red",
    int(Status.OUT_OF_BOUNDS): "magenta",
    int(Status.MASKED): "gray",
    int(Status.LOW_TEXTURE): "cyan",
    int(Status.SINGULAR): "orange",
    int(Status.LOW_ZNCC): "blue",
    int(Status.OUTLIER_REPLACED): "lime",
    int(Status.NOT_COMPUTED): "white",
    int(Status.DISCONTINUITY): "#ff1493",
}


def as_triple(value, default: float) -> np.ndarray:
    """Three floats (z, y, x) from ``value`` (its last three entries), ``default`` if None."""
    if value is None:
        return np.full(3, default, dtype=np.float64)
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    return array[-3:] if array.size >= 3 else np.broadcast_to(array, (3,)).astype(np.float64)


def _finite_limits(values: np.ndarray, fallback=(0.0, 1.0)) -> list[float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return list(fallback)
    low, high = float(finite.min()), float(finite.max())
    return [low, high] if high > low else [low, low + 1.0]


# -- quantities --------------------------------------------------------------------------------
#: What a field layer can show: key -> (what it is, kind). The kind sets the units and colours.
QUANTITIES = {
    "|u|": ("displacement magnitude", "magnitude"),
    "uz": ("displacement along z", "displacement"),
    "uy": ("displacement along y", "displacement"),
    "ux": ("displacement along x", "displacement"),
    "εzz": ("normal strain zz", "strain"),
    "εyy": ("normal strain yy", "strain"),
    "εxx": ("normal strain xx", "strain"),
    "εzy": ("shear strain zy (tensor)", "strain"),
    "εzx": ("shear strain zx (tensor)", "strain"),
    "εyx": ("shear strain yx (tensor)", "strain"),
    "ε1": ("major principal strain", "strain"),
    "ε2": ("intermediate principal strain", "strain"),
    "ε3": ("minor principal strain", "strain"),
    "εvol": ("volumetric strain (trace)", "strain"),
    "γmax": ("maximum shear strain ε1 − ε3", "positive strain"),
    "εeq": ("equivalent strain (paper eq. 3)", "positive strain"),
    "ZNCC": ("zero-normalised cross-correlation", "zncc"),
    "status": ("matching status of each POI", "status"),
    "uncertainty": ("displacement uncertainty", "magnitude"),
    "error estimate": (
        "estimated displacement error (Evaluate); where not above the error resolution it is "
        "a bound, not a rank",
        "magnitude",
    ),
    "error resolution": (
        "the error estimate's resolution (Evaluate): errors below it do not show in the residual",
        "magnitude",
    ),
    "residual": ("gray residual |F(X + u) − G(X)|", "residual"),
}
#: What a new field layer shows.
DEFAULT_QUANTITY = "|u|"
_TENSOR_INDEX = {"εzz": (0, 0), "εyy": (1, 1), "εxx": (2, 2), "εzy": (0, 1), "εzx": (0, 2)}
_TENSOR_INDEX["εyx"] = (1, 2)
_DISPLACEMENT_KINDS = ("magnitude", "displacement")


def field_uncertainty(field: DisplacementField) -> np.ndarray | None:
    """Per-node displacement uncertainty (voxels, ``(nz, ny, nx)``), if the field has one."""
    value = getattr(field, "uncertainty", None)
    if value is None:
        return None
    value = np.asarray(value, dtype=np.float64)
    if value.shape == (*field.shape, 3):
        return np.linalg.norm(value, axis=-1)
    return value if value.shape == field.shape else None


def available_quantities(field: DisplacementField, residual: bool = False) -> list[str]:
    """The keys of :data:`QUANTITIES` that ``field`` can show (``residual`` once evaluated)."""
    from .engine.evaluation.error_estimate import estimate_of, resolution_of

    optional = ("uncertainty", "error estimate", "error resolution", "residual")
    keys = [key for key in QUANTITIES if key not in optional]
    if field_uncertainty(field) is not None:
        keys.append("uncertainty")
    if estimate_of(field) is not None:
        keys.append("error estimate")
    if resolution_of(field) is not None:
        keys.append("error resolution")
    if residual:
        keys.append("residual")
    return keys


def unit_of(quantity: str, field: DisplacementField | None = None) -> str:
    """Units of ``quantity``: the field's length unit or a plain word.

    Displacements without a unit are in voxels when the voxel size is 1, else in the units of
    the layers' scale (``"scale units"``).
    """
    kind = QUANTITIES[quantity][1]
    if kind in _DISPLACEMENT_KINDS:
        unit = field.metadata.get("unit") if field is not None else None
        if unit:
            return str(unit)
        size = as_triple(field.metadata.get("voxel_size") if field is not None else None, 1.0)
        return "vx" if np.allclose(size, 1.0) else "scale units"
    return {"zncc": "–", "status": "code", "residual": "gray levels"}.get(kind, "strain, –")


def physical_strain(field: DisplacementField) -> np.ndarray:
    """Small-strain tensor ``(nz, ny, nx, 3, 3)`` in physical axes (anisotropic voxels included).

    ``du_i/dX_j`` measured in voxels becomes ``du_i/dX_j * vs_i / vs_j`` with ``vs`` the field's
    ``metadata["voxel_size"]``; NaN at nodes without a usable displacement.
    """
    from .engine.evaluation.strain import displacement_gradient, small_strain

    vs = as_triple(field.metadata.get("voxel_size"), 1.0)
    gradient = displacement_gradient(field) * (vs[:, None] / vs[None, :])
    return small_strain(gradient)


#: Values computed ahead (:func:`compute_ahead`): id(field) -> (weak reference, {quantity: values}).
_AHEAD: dict[int, tuple] = {}


def compute_ahead(field: DisplacementField, quantity: str) -> None:
    """Compute ``quantity`` of ``field`` now and keep it while the field lives.

    A panel's worker calls it for a new result with the quantity on view, so showing the result
    (main thread) finds the strain ready in :func:`quantity_values`.
    """
    values = quantity_values(field, quantity)
    key = id(field)
    entry = _AHEAD.get(key)
    if entry is None or entry[0]() is not field:
        entry = (weakref.ref(field, lambda ref, key=key: _AHEAD.pop(key, None)), {})
        _AHEAD[key] = entry
    entry[1][quantity] = values


def quantity_values(
    field: DisplacementField, quantity: str, cache: dict | None = None
) -> np.ndarray:
    """The values of ``quantity`` on the grid of ``field``, ``(nz, ny, nx)`` float32.

    Displacements are in the units of :func:`unit_of` (voxels times the field's voxel size),
    strains dimensionless, NaN where the node has no usable displacement. ``cache`` (a dict
    kept by the caller) keeps the strain tensor between calls.
    """
    if quantity not in QUANTITIES or quantity == "residual":
        raise ValueError(f"{quantity!r} is not a grid quantity; choose one of {list(QUANTITIES)}")
    ahead = _AHEAD.get(id(field))
    if ahead is not None and ahead[0]() is field and quantity in ahead[1]:
        return ahead[1][quantity]
    kind = QUANTITIES[quantity][1]
    vs = as_triple(field.metadata.get("voxel_size"), 1.0)
    if quantity == "ZNCC":
        return field.zncc.astype(np.float32)
    if quantity == "status":
        return field.status.astype(np.float32)
    if quantity == "uncertainty":
        values = field_uncertainty(field)
        if values is None:
            raise ValueError("this field has no uncertainty")
        values = values * float(np.mean(vs))
    elif quantity == "error estimate":
        from .engine.evaluation.error_estimate import estimate_of

        values = estimate_of(field)
        if values is None:
            raise ValueError("this field has no error estimate: run Evaluate on it first")
        values = values * float(np.mean(vs))
    elif quantity == "error resolution":
        from .engine.evaluation.error_estimate import resolution_of

        values = resolution_of(field)
        if values is None:
            raise ValueError("this field has no error resolution: run Evaluate on it first")
        values = values * float(np.mean(vs))
    elif kind in _DISPLACEMENT_KINDS:
        u = field.u * vs
        values = (
            np.linalg.norm(u, axis=-1) if quantity == "|u|" else u[..., "zyx".index(quantity[1])]
        )
    else:
        cache = {} if cache is None else cache
        key = ("strain", id(field))
        if key not in cache:
            cache.clear()
            cache[key] = physical_strain(field)
        tensor = cache[key]
        if quantity in _TENSOR_INDEX:
            values = tensor[(..., *_TENSOR_INDEX[quantity])]
        elif quantity == "εvol":
            values = np.trace(tensor, axis1=-2, axis2=-1)
        elif quantity == "εeq":
            from .engine.evaluation.strain import equivalent_strain

            values = equivalent_strain(tensor)
        else:
            from .engine.evaluation.strain import principal_strains

            principal = principal_strains(tensor)
            index = {"ε1": 0, "ε2": 1, "ε3": 2}
            values = (
                principal[..., 0] - principal[..., 2]
                if quantity == "γmax"
                else principal[..., index[quantity]]
            )
    values = np.asarray(values, dtype=np.float32).copy()
    values[~field.valid] = np.nan
    return values


def point_quantities(points_field) -> dict[str, np.ndarray]:
    """Every quantity of :data:`QUANTITIES` a field at scattered points can show, per point.

    ``points_field`` is a :class:`..engine.fields.scattered.ScatteredField`. Displacements are in the
    units of :func:`unit_of` (voxels times ``metadata["voxel_size"]``); strains come from each
    point's matched displacement gradient (the subvolume's own first-order warp, physical axes),
    not from neighbouring points; NaN where the point has no usable value. Returns float64
    arrays ``(N,)`` by quantity key, in :data:`QUANTITIES` order.
    """
    from .engine.evaluation.strain import equivalent_strain, principal_strains, small_strain

    vs = as_triple(points_field.metadata.get("voxel_size"), 1.0)
    valid = np.asarray(points_field.valid, dtype=bool)
    u = np.where(valid[:, None], points_field.u, np.nan) * vs
    values = {"|u|": np.linalg.norm(u, axis=1)}
    for axis, name in enumerate(("uz", "uy", "ux")):
        values[name] = u[:, axis]
    if points_field.gradient is not None:
        gradient = np.asarray(points_field.gradient, dtype=np.float64) * (vs[:, None] / vs[None, :])
        gradient[~valid] = np.nan
        tensor = small_strain(gradient)
        for name, index in _TENSOR_INDEX.items():
            values[name] = tensor[(..., *index)]
        principal = principal_strains(tensor)
        values.update(
            {
                "ε1": principal[:, 0],
                "ε2": principal[:, 1],
                "ε3": principal[:, 2],
                "εvol": np.trace(tensor, axis1=-2, axis2=-1),
                "γmax": principal[:, 0] - principal[:, 2],
                "εeq": equivalent_strain(tensor),
            }
        )
    values["ZNCC"] = np.asarray(points_field.zncc, dtype=np.float64)
    values["status"] = np.asarray(points_field.status, dtype=np.float64)
    order = list(QUANTITIES)
    return {key: values[key] for key in sorted(values, key=order.index)}


def status_colormap():
    """A napari colormap for the status codes (converged transparent), for an Image layer."""
    from napari.utils.colormaps import Colormap

    codes = list(range(max(int(s) for s in Status) + 1))
    colors = []
    for code in codes:
        name = STATUS_COLORS.get(code, "white")
        colors.append([0, 0, 0, 0] if name == "transparent" else name)
    from napari.utils.colormaps.standardize_color import transform_color

    rgba = [c if isinstance(c, list) else list(transform_color(c)[0]) for c in colors]
    controls = np.linspace(0.0, 1.0, len(codes) + 1)
    return Colormap(rgba, controls=controls, interpolation="zero", name="DVC status")


def quantity_style(quantity: str, values: np.ndarray, limits=None) -> dict:
    """Colormap, contrast limits and rendering of ``quantity`` (napari Image keyword arguments).

    Signed quantities get a diverging map centred on zero; ``limits`` overrides the automatic
    range (e.g. one range shared by the fields compared).
    """
    kind = QUANTITIES[quantity][1]
    finite = values[np.isfinite(values)]
    if kind == "status":
        n = max(int(s) for s in Status) + 1
        return {"colormap": "DVC status", "contrast_limits": [-0.5, n - 0.5], "rendering": "mip"}
    if limits is None:
        if kind in ("displacement", "strain"):
            high = float(np.percentile(np.abs(finite), 99.5)) if finite.size else 1.0
            high = high if high > 0 else 1.0
            limits = [-high, high]
        elif kind == "zncc":
            limits = [min(0.5, _finite_limits(values, (0.0, 1.0))[0]), 1.0]
        else:
            high = float(np.percentile(finite, 99.5)) if finite.size else 1.0
            limits = [0.0, high if high > 0 else 1.0]
    colormap = {
        "displacement": "coolwarm",
        "strain": "coolwarm",
        "magnitude": "viridis",
        "positive strain": "inferno",
        "zncc": "magma",
        "residual": "magma",
    }[kind]
    rendering = "mip" if kind in ("magnitude", "positive strain", "residual") else "average"
    return {
        "colormap": colormap,
        "contrast_limits": [float(v) for v in limits],
        "rendering": rendering,
    }
