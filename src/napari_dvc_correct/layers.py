"""napari layer data tuples built from a :class:`DisplacementField` and the evaluation volumes.

Every builder returns ``(data, kwargs, layer_type)`` tuples (what npe2 readers and sample data
return), placed over the volume they come from:

* grid quantities (``|u|``, components, ZNCC, status, εeq) are Image/Labels layers with
  ``scale = step * voxel_size`` and ``translate = offset + origin * voxel_size``;
* the Vectors layer holds node positions in grid units (node indices) and vectors in grid units
  (``u / step``) with the same ``scale``/``translate``, so the drawn arrows have their true length
  in world units;
* dense quantities (gray residual, phase labels) have ``scale = voxel_size`` and
  ``translate = offset``.

``voxel_size`` is the physical size of a voxel (z, y, x) and ``offset`` the world position of the
volume's first voxel: the ``scale`` and ``translate`` of the reference Image layer.

Layer names say which field they come from, e.g. ``"εeq (corrected)"``, and every layer carries
``metadata["dvc_correct"]`` with its ``kind``, its ``source`` (``"uncorrected"``,
``"corrected"``...) and, for field layers, the :class:`DisplacementField` itself (``"field"``),
which the writer and the panels read back. :func:`show_layers` replaces layers of the same name
the plugin made before instead of piling up new ones.

No Qt here; napari is imported only by :func:`show_layers`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .engine.field import DisplacementField, Status

#: Key of the plugin's entry in a layer's ``metadata``.
MARKER = "dvc_correct"

#: Colours of the status codes in the status Labels layer (converged stays transparent).
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
}

LayerDataTuple = tuple[Any, dict, str]


def layer_name(quantity: str, source: str) -> str:
    """Layer name for ``quantity`` of the field ``source``, e.g. ``"εeq (corrected)"``."""
    return f"{quantity} ({source})"


def _triple(value, default: float) -> np.ndarray:
    if value is None:
        return np.full(3, default, dtype=np.float64)
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    return array[-3:] if array.size >= 3 else np.broadcast_to(array, (3,)).astype(np.float64)


def grid_placement(field: DisplacementField, voxel_size=None, offset=None) -> dict:
    """``scale`` and ``translate`` of a grid quantity of ``field`` in world units.

    Parameters
    ----------
    field : DisplacementField
    voxel_size : sequence of 3 floats, optional
        Physical voxel size (z, y, x); default 1.
    offset : sequence of 3 floats, optional
        World position (z, y, x) of the volume's voxel (0, 0, 0); default 0.
    """
    vs, off = _triple(voxel_size, 1.0), _triple(offset, 0.0)
    return {
        "scale": tuple(float(v) for v in np.asarray(field.step) * vs),
        "translate": tuple(float(v) for v in off + np.asarray(field.origin) * vs),
    }


def dense_placement(voxel_size=None, offset=None) -> dict:
    """``scale`` and ``translate`` of a quantity on the voxels of the volume."""
    vs, off = _triple(voxel_size, 1.0), _triple(offset, 0.0)
    return {"scale": tuple(float(v) for v in vs), "translate": tuple(float(v) for v in off)}


def _meta(kind: str, source: str, field: DisplacementField | None = None, **extra) -> dict:
    entry = {"kind": kind, "source": source, **extra}
    if field is not None:
        entry["field"] = field
    return {MARKER: entry}


def vector_stride(shape, max_vectors: int) -> int:
    """Smallest grid stride (same along every axis) that shows at most ``max_vectors`` arrows."""
    stride = 1
    while int(np.prod([-(-n // stride) for n in shape])) > max_vectors:
        stride += 1
    return stride


def vectors_layer(
    field: DisplacementField,
    source: str,
    *,
    voxel_size=None,
    offset=None,
    max_vectors: int = 4000,
    exaggerate: bool = True,
) -> LayerDataTuple:
    """Displacement arrows, subsampled for display and coloured by magnitude.

    Nodes without a usable displacement (:attr:`DisplacementField.valid` false) are left out.
    With ``exaggerate`` the layer's ``length`` is set so the longest arrow spans one grid step
    when the largest displacement is under half a step (the magnitude colours stay true; the
    layer controls show the factor).

    Returns
    -------
    tuple
        ``(data, kwargs, "vectors")`` with data of shape (N, 2, 3): node index positions and
        ``u / step``, both in grid units (z, y, x).
    """
    stride = vector_stride(field.shape, max_vectors)
    index = np.stack(
        np.meshgrid(*[np.arange(0, n, stride) for n in field.shape], indexing="ij"), axis=-1
    ).reshape(-1, 3)
    u = field.u[index[:, 0], index[:, 1], index[:, 2]]
    keep = field.valid[index[:, 0], index[:, 1], index[:, 2]]
    index, u = index[keep], u[keep]
    data = np.stack([index.astype(np.float64), u / np.asarray(field.step)], axis=1)
    magnitude = np.linalg.norm(u, axis=1)
    length = 1.0
    if exaggerate and magnitude.size and 0 < magnitude.max() < 0.5 * min(field.step):
        length = float(min(field.step) / magnitude.max())
    kwargs = {
        "name": layer_name("displacement", source),
        "features": {"magnitude": magnitude},
        "edge_color": "magnitude",
        "edge_colormap": "viridis",
        "edge_width": 0.12,
        "vector_style": "arrow",
        "length": length,
        "metadata": _meta("vectors", source, field, stride=stride),
        **grid_placement(field, voxel_size, offset),
    }
    return data, kwargs, "vectors"


def _finite_limits(values: np.ndarray, fallback=(0.0, 1.0)) -> list[float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return list(fallback)
    low, high = float(finite.min()), float(finite.max())
    return [low, high] if high > low else [low, low + 1.0]


def magnitude_layer(field, source, *, voxel_size=None, offset=None) -> LayerDataTuple:
    """``|u|`` on the grid (voxels), an Image layer."""
    magnitude = field.magnitude.astype(np.float32)
    magnitude[~field.valid] = np.nan
    kwargs = {
        "name": layer_name("|u|", source),
        "colormap": "viridis",
        "contrast_limits": _finite_limits(magnitude),
        "metadata": _meta("magnitude", source, field),
        "blending": "additive",
        "opacity": 0.6,
        **grid_placement(field, voxel_size, offset),
    }
    return magnitude, kwargs, "image"


def component_layers(field, source, *, voxel_size=None, offset=None) -> list[LayerDataTuple]:
    """``uz``, ``uy``, ``ux`` on the grid (voxels), hidden Image layers."""
    out = []
    for axis, name in enumerate(("uz", "uy", "ux")):
        component = field.u[..., axis].astype(np.float32)
        component[~field.valid] = np.nan
        limit = max(abs(v) for v in _finite_limits(component))
        kwargs = {
            "name": layer_name(name, source),
            "colormap": "PiYG",
            "contrast_limits": [-limit, limit],
            "visible": False,
            "metadata": _meta(f"component {name}", source, field),
            **grid_placement(field, voxel_size, offset),
        }
        out.append((component, kwargs, "image"))
    return out


def zncc_layer(field, source, *, voxel_size=None, offset=None) -> LayerDataTuple:
    """Per-POI ZNCC on the grid, an Image layer (NaN where not matched)."""
    kwargs = {
        "name": layer_name("ZNCC", source),
        "colormap": "magma",
        "contrast_limits": [min(0.5, _finite_limits(field.zncc, (0.0, 1.0))[0]), 1.0],
        "visible": False,
        "metadata": _meta("zncc", source, field),
        **grid_placement(field, voxel_size, offset),
    }
    return field.zncc.copy(), kwargs, "image"


def status_layer(field, source, *, voxel_size=None, offset=None) -> LayerDataTuple:
    """Per-POI :class:`Status` codes, a Labels layer; converged nodes are transparent."""
    kwargs = {
        "name": layer_name("status", source),
        "colormap": dict(STATUS_COLORS),
        "features": {
            "index": [int(s) for s in Status],
            "status": [s.label for s in Status],
        },
        "opacity": 0.6,
        "visible": False,
        "metadata": _meta("status", source, field),
        **grid_placement(field, voxel_size, offset),
    }
    return field.status.copy(), kwargs, "labels"


def strain_layer(
    equivalent: np.ndarray, field, source, *, voxel_size=None, offset=None
) -> LayerDataTuple:
    """Equivalent strain ``εeq`` on the grid of ``field`` (dimensionless), an Image layer.

    Parameters
    ----------
    equivalent : ndarray, shape ``field.shape``
        Equivalent (octahedral) strain at each node.
    """
    equivalent = np.asarray(equivalent, dtype=np.float32)
    if equivalent.shape != field.shape:
        raise ValueError(f"strain must have the grid shape {field.shape}, got {equivalent.shape}")
    finite = equivalent[np.isfinite(equivalent)]
    high = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    kwargs = {
        "name": layer_name("εeq", source),
        "colormap": "inferno",
        "contrast_limits": [0.0, high if high > 0 else 1.0],
        "rendering": "mip",
        "blending": "additive",
        "opacity": 0.8,
        "metadata": _meta("equivalent strain", source, field),
        **grid_placement(field, voxel_size, offset),
    }
    return equivalent, kwargs, "image"


def residual_layer(
    residual: np.ndarray, source: str, *, voxel_size=None, offset=None
) -> LayerDataTuple:
    """Dense gray residual ``|F(X + u(X)) - G(X)|`` (gray levels), an Image layer."""
    residual = np.asarray(residual, dtype=np.float32)
    kwargs = {
        "name": layer_name("residual", source),
        "colormap": "gray",
        "contrast_limits": [0.0, max(1e-6, float(np.nanpercentile(residual, 99.5)))],
        "visible": False,
        "metadata": _meta("residual", source),
        **dense_placement(voxel_size, offset),
    }
    return residual, kwargs, "image"


def phase_layer(labels: np.ndarray, *, voxel_size=None, offset=None) -> LayerDataTuple:
    """Phase labels (0 = unassigned, 1..n = phases from dark to bright), a Labels layer."""
    kwargs = {
        "name": "phases",
        "opacity": 0.4,
        "metadata": _meta("phases", "thresholds"),
        **dense_placement(voxel_size, offset),
    }
    return np.asarray(labels), kwargs, "labels"


def field_layers(
    field: DisplacementField,
    source: str = "uncorrected",
    *,
    voxel_size=None,
    offset=None,
    equivalent_strain: np.ndarray | None = None,
    max_vectors: int = 4000,
    components: bool = True,
) -> list[LayerDataTuple]:
    """All the grid layers of a field: vectors, ``|u|``, components, ZNCC, status and ``εeq``.

    ``εeq`` is included when ``equivalent_strain`` (shape ``field.shape``) is given, the
    ``uz``/``uy``/``ux`` images unless ``components`` is False.
    """
    placement = {"voxel_size": voxel_size, "offset": offset}
    layers = [magnitude_layer(field, source, **placement)]
    if components:
        layers += component_layers(field, source, **placement)
    layers += [zncc_layer(field, source, **placement), status_layer(field, source, **placement)]
    if equivalent_strain is not None:
        layers.append(strain_layer(equivalent_strain, field, source, **placement))
    layers.append(vectors_layer(field, source, max_vectors=max_vectors, **placement))
    return layers


# -- reading back ------------------------------------------------------------------------------
def plugin_metadata(layer_or_metadata) -> dict | None:
    """The plugin's metadata entry of a layer (or of a layer's ``metadata`` dict), or None."""
    metadata = getattr(layer_or_metadata, "metadata", layer_or_metadata)
    if not isinstance(metadata, dict):
        return None
    entry = metadata.get(MARKER)
    return entry if isinstance(entry, dict) else None


def field_of(layer_or_metadata) -> DisplacementField | None:
    """The :class:`DisplacementField` a plugin layer was made from, or None."""
    entry = plugin_metadata(layer_or_metadata)
    if entry is None:
        return None
    field = entry.get("field")
    return field if isinstance(field, DisplacementField) else None


def fields_in(layers) -> dict[str, DisplacementField]:
    """Fields carried by ``layers``, by source name, in layer order (first layer of each wins)."""
    found: dict[str, DisplacementField] = {}
    for layer in layers:
        field = field_of(layer)
        if field is not None:
            found.setdefault(plugin_metadata(layer)["source"], field)
    return found


def find_layer(viewer, name: str):
    """The layer the plugin made under ``name`` (even if napari numbered it), or None."""
    return next((x for x in viewer.layers if (plugin_metadata(x) or {}).get("name") == name), None)


def show_layers(viewer, layer_tuples) -> list:
    """Add layer tuples to ``viewer``, replacing same-named layers the plugin made before.

    A replaced layer keeps its position in the layer list; layers of the same name that the user
    made (without the plugin's metadata) are left alone and the new one gets napari's usual
    numbered name.

    Returns
    -------
    list of napari layers, in the order of ``layer_tuples``.
    """
    from napari.layers import Layer

    added = []
    for data, kwargs, layer_type in layer_tuples:
        kwargs = dict(kwargs)
        name = kwargs.get("name")
        metadata = kwargs.get("metadata") or {}
        entry = metadata.get(MARKER)
        if isinstance(entry, dict):  # napari may rename the layer; we find it by this name
            kwargs["metadata"] = {**metadata, MARKER: {**entry, "name": name}}
        layer = Layer.create(data, kwargs, layer_type)
        old = find_layer(viewer, name)
        if old is not None:
            index = viewer.layers.index(old)
            viewer.layers.remove(old)
            viewer.layers.insert(index, layer)
        else:
            viewer.layers.append(layer)
        added.append(layer)
    return added
