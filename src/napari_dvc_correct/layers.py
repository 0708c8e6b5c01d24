"""napari layer data tuples built from a :class:`DisplacementField` and the evaluation volumes.

A field shows as two layers (:func:`field_layers`): one Image layer with one quantity at a time
(``|u|``, a component, a strain component, principal/volumetric/shear/equivalent strain, ZNCC,
status, uncertainty, residual; :data:`QUANTITIES`, switched in place by :func:`show_quantity`)
and the displacement arrows. Every builder returns ``(data, kwargs, layer_type)`` tuples (what
npe2 readers and sample data return), placed over the volume they come from:

* grid quantities are Image layers with ``scale = step * voxel_size`` and
  ``translate = offset + origin * voxel_size``, drawn translucent so the scan shows through;
* the Vectors layer holds node positions in grid units (node indices) and vectors in grid units
  (``u / step``) with the same ``scale``/``translate``, so the drawn arrows have their true length
  in world units;
* dense quantities (gray residual, phase labels) have ``scale = voxel_size`` and
  ``translate = offset``;
* a series (a list of fields, state 0 first) gives 4-D layers ``(state, z, y, x)`` that follow
  the state slider of the scan series.

``voxel_size`` is the physical size of a voxel (z, y, x) and ``offset`` the world position of the
volume's first voxel: the ``scale`` and ``translate`` of the reference Image layer.

Layer names say what they show and which field they come from, e.g. ``"εeq (corrected)"``, and
every layer carries ``metadata["dvc_correct"]`` with its ``kind``, its ``source``
(``"uncorrected"``, ``"corrected"``...) and, for field layers, the :class:`DisplacementField`
itself (``"field"``), which the writer and the panels read back. :func:`show_layers` replaces the
layers the plugin made before under the same key instead of piling up new ones.

No Qt here; napari is imported only by :func:`show_layers` and the status colormap.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .engine.fields.field import DisplacementField
from .quantities import (  # noqa: F401 (the quantities are part of what layers offers)
    DEFAULT_QUANTITY,
    QUANTITIES,
    STATUS_COLORS,
    as_triple,
    available_quantities,
    field_uncertainty,
    physical_strain,
    quantity_style,
    quantity_values,
    status_colormap,
    unit_of,
)

#: Key of the plugin's entry in a layer's ``metadata``.
MARKER = "dvc_correct"

LayerDataTuple = tuple[Any, dict, str]


def layer_name(quantity: str, source: str) -> str:
    """Layer name for ``quantity`` of the field ``source``, e.g. ``"εeq (corrected)"``."""
    return f"{quantity} ({source})"


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
    vs, off = as_triple(voxel_size, 1.0), as_triple(offset, 0.0)
    return {
        "scale": tuple(float(v) for v in np.asarray(field.step) * vs),
        "translate": tuple(float(v) for v in off + np.asarray(field.origin) * vs),
    }


def dense_placement(voxel_size=None, offset=None) -> dict:
    """``scale`` and ``translate`` of a quantity on the voxels of the volume."""
    vs, off = as_triple(voxel_size, 1.0), as_triple(offset, 0.0)
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


def _vector_data(field: DisplacementField, stride: int, state: int | None = None):
    index = np.stack(
        np.meshgrid(*[np.arange(0, n, stride) for n in field.shape], indexing="ij"), axis=-1
    ).reshape(-1, 3)
    u = field.u[index[:, 0], index[:, 1], index[:, 2]]
    keep = field.valid[index[:, 0], index[:, 1], index[:, 2]]
    index, u = index[keep], u[keep]
    data = np.stack([index.astype(np.float64), u / np.asarray(field.step)], axis=1)
    if state is not None:  # a leading state coordinate; arrows do not move along it
        data = np.concatenate([np.zeros((len(data), 2, 1)), data], axis=2)
        data[:, 0, 0] = state
    return data, np.linalg.norm(u, axis=1)


def vectors_layer(
    field,
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
    layer controls show the factor). ``field`` may be a list of fields (a series, state 0
    first): the arrows are then 4-D, one set per state.

    Returns
    -------
    tuple
        ``(data, kwargs, "vectors")`` with data of shape (N, 2, 3): node index positions and
        ``u / step``, both in grid units (z, y, x); (N, 2, 4) with the state first for a series.
    """
    series = not isinstance(field, DisplacementField)
    fields = list(field) if series else [field]
    last = fields[-1]
    stride = vector_stride(last.shape, max_vectors)
    parts = [_vector_data(f, stride, t if series else None) for t, f in enumerate(fields)]
    data = np.concatenate([p[0] for p in parts])
    magnitude = np.concatenate([p[1] for p in parts])
    length = 1.0
    if exaggerate and magnitude.size and 0 < magnitude.max() < 0.5 * min(last.step):
        length = float(min(last.step) / magnitude.max())
    kwargs = {
        "name": layer_name("displacement", source),
        "features": {"magnitude": magnitude},
        "edge_color": "magnitude",
        "edge_colormap": "viridis",
        "edge_width": 0.12,
        "vector_style": "arrow",
        "length": length,
        "metadata": _meta("vectors", source, last, stride=stride),
        **_placement(field, voxel_size, offset),
    }
    if series:
        kwargs["metadata"][MARKER]["fields"] = fields
    return data, kwargs, "vectors"


def field_key(source: str) -> str:
    """The stable name under which the plugin finds the quantity layer of ``source``."""
    return f"field ({source})"


def _placement(fields, voxel_size, offset) -> dict:
    first = fields if isinstance(fields, DisplacementField) else fields[-1]
    placement = grid_placement(first, voxel_size, offset)
    if not isinstance(fields, DisplacementField):  # series: state axis first
        placement = {
            "scale": (1.0, *placement["scale"]),
            "translate": (0.0, *placement["translate"]),
        }
    return placement


def quantity_layer(
    fields,
    source: str,
    quantity: str = DEFAULT_QUANTITY,
    *,
    voxel_size=None,
    offset=None,
    residual: np.ndarray | None = None,
    limits=None,
    caches: dict | None = None,
) -> LayerDataTuple:
    """One Image layer showing ``quantity`` of a field (or of a series of fields), over the scan.

    Parameters
    ----------
    fields : DisplacementField or list of DisplacementField
        One field, or one per state of a series (state 0 first; the layer is then 4-D,
        ``(state, nz, ny, nx)``, and follows the state slider of the scan series).
    source : str
        ``"uncorrected"``, ``"corrected"``, ``"series (total)"``...
    quantity : str
        A key of :data:`QUANTITIES`.
    residual : ndarray (NZ, NY, NX), optional
        The dense gray residual, for ``quantity="residual"`` (placed on the voxels).
    caches : dict, optional
        Kept by the caller between calls (one dict per state), so switching between strain
        quantities computes the strain tensor once.

    The layer is drawn translucent (the scan shows through); its metadata carries the field
    (``"field"``; ``"fields"`` for a series), the quantity and its units.
    """
    field = fields if isinstance(fields, DisplacementField) else fields[-1]
    if quantity == "residual":
        if residual is None:
            raise ValueError(f"no gray residual for the '{source}' field yet: run Evaluate first")
        values = np.asarray(residual, dtype=np.float32)
        placement = dense_placement(voxel_size, offset)
    else:
        caches = {} if caches is None else caches  # one per state: the strain tensor kept
        series = [fields] if isinstance(fields, DisplacementField) else list(fields)
        values = np.stack(
            [quantity_values(f, quantity, caches.setdefault(t, {})) for t, f in enumerate(series)]
        )
        values = values[0] if isinstance(fields, DisplacementField) else values

        placement = _placement(fields, voxel_size, offset)
    style = quantity_style(quantity, values, limits)
    if quantity == "status":
        style["colormap"] = status_colormap()
    extra = {"quantity": quantity, "unit": unit_of(quantity, field), "key": field_key(source)}
    if not isinstance(fields, DisplacementField):
        extra["fields"] = list(fields)
    kwargs = {
        "name": layer_name(quantity, source),
        **style,
        "blending": "translucent",
        "opacity": 0.7,
        "metadata": _meta("quantity", source, field, **extra),
        **placement,
    }
    unit = field.metadata.get("unit")
    if unit:
        kwargs["units"] = (unit,) * len(placement["scale"])
    return values, kwargs, "image"


def residual_layer(
    residual: np.ndarray, source: str, *, voxel_size=None, offset=None
) -> LayerDataTuple:
    """Dense gray residual ``|F(X + u(X)) - G(X)|`` (gray levels), a hidden Image layer.

    Kept as its own (hidden) layer so Export and the View panel find the residual of each field.
    A lazy array (the Zarr residual of an out-of-core evaluation) stays lazy.
    """
    if isinstance(residual, np.ndarray):
        residual = sample = np.asarray(residual, dtype=np.float32)
    else:  # a lazy (Zarr) residual of an out-of-core run: shown lazily, ranged on a sample
        stride = max(1, int(np.ceil((float(np.prod(residual.shape)) / (1 << 21)) ** (1 / 3))))
        sample = np.asarray(residual[::stride, ::stride, ::stride], dtype=np.float32)
    kwargs = {
        "name": layer_name("residual volume", source),
        "colormap": "gray",
        "contrast_limits": [0.0, max(1e-6, float(np.nanpercentile(sample, 99.5)))],
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
    field,
    source: str = "uncorrected",
    *,
    voxel_size=None,
    offset=None,
    quantity: str = DEFAULT_QUANTITY,
    max_vectors: int = 4000,
) -> list[LayerDataTuple]:
    """The two layers of a field: the chosen quantity (an Image) and the displacement arrows.

    ``field`` may be a list of fields (a series, state 0 first): both layers are then 4-D.
    """
    placement = {"voxel_size": voxel_size, "offset": offset}
    return [
        quantity_layer(field, source, quantity, **placement),
        vectors_layer(field, source, max_vectors=max_vectors, **placement),
    ]


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


def series_of(layer_or_metadata) -> list | None:
    """The fields of a series layer (state 0 first), or None for a single field."""
    entry = plugin_metadata(layer_or_metadata)
    fields = entry.get("fields") if entry is not None else None
    return list(fields) if isinstance(fields, list) else None


def state_source(source: str, state: int) -> str:
    """Name of state ``state`` of the series ``source``, e.g. ``"state 2 (total)"``."""
    return f"state {state} {source.split(' ', 1)[1]}" if " " in source else f"{source} {state}"


def fields_in(layers) -> dict[str, DisplacementField]:
    """Fields carried by ``layers``, by source name, in layer order (first layer of each wins).

    A series layer gives one entry per state after the first (:func:`state_source`).
    """
    found: dict[str, DisplacementField] = {}
    for layer in layers:
        field = field_of(layer)
        if field is None:
            continue
        source = plugin_metadata(layer)["source"]
        series = series_of(layer)
        if series is None:
            found.setdefault(source, field)
        else:
            for state, item in enumerate(series[1:], start=1):
                found.setdefault(state_source(source, state), item)
    return found


def find_layer(viewer, name: str):
    """The layer the plugin made under ``name`` (even if napari numbered or renamed it), or None."""
    return next((x for x in viewer.layers if (plugin_metadata(x) or {}).get("name") == name), None)


def quantity_layers(viewer) -> list:
    """The plugin's quantity layers (one per field or series), in layer order."""
    return [x for x in viewer.layers if (plugin_metadata(x) or {}).get("kind") == "quantity"]


def quantity_update(layer_or_entry, quantity: str, *, residual=None, limits=None) -> tuple:
    """What :func:`apply_quantity` needs to switch a quantity layer to ``quantity``.

    The expensive half of :func:`show_quantity` (strain tensors, eigenvalues, percentiles):
    pure numpy on the layer's field(s), no layer touched, so a thread worker may run it. Takes
    the layer or its plugin metadata entry (read it on the main thread and hand the entry to a
    worker). Returns ``(data, kwargs)``; raises ValueError when the field cannot show
    ``quantity``.
    """
    entry = plugin_metadata(layer_or_entry)
    entry = layer_or_entry if entry is None else entry
    fields = series_of({MARKER: entry}) or entry["field"]
    data, kwargs, _ = quantity_layer(
        fields,
        entry["source"],
        quantity,
        voxel_size=entry["field"].metadata.get("voxel_size"),
        offset=entry["field"].metadata.get("offset"),
        residual=residual,
        limits=limits,
        caches=entry.setdefault("cache", {}),
    )
    return data, kwargs


def apply_quantity(layer, data, kwargs: dict) -> None:
    """Put a :func:`quantity_update` result into ``layer`` (main thread: touches the layer)."""
    entry = plugin_metadata(layer)
    layer.data = data
    layer.scale, layer.translate = kwargs["scale"], kwargs["translate"]
    layer.colormap = kwargs["colormap"]
    layer.contrast_limits = kwargs["contrast_limits"]
    layer.rendering = kwargs["rendering"]
    new = kwargs["metadata"][MARKER]
    entry.update(quantity=new["quantity"], unit=new["unit"])
    layer.name = kwargs["name"]


def remember_quantity(layer) -> None:
    """Keep what a quantity layer shows now in its field's cache (:func:`apply_quantity` input),
    so switching back to it needs no computing. The residual is not kept (it changes with each
    evaluation)."""
    entry = plugin_metadata(layer)
    quantity = entry.get("quantity")
    if quantity is None or quantity == "residual":
        return
    kwargs = {
        "name": layer_name(quantity, entry["source"]),
        "scale": tuple(layer.scale),
        "translate": tuple(layer.translate),
        "colormap": layer.colormap,
        "contrast_limits": list(layer.contrast_limits),
        "rendering": layer.rendering,
        "metadata": {MARKER: {"quantity": quantity, "unit": entry.get("unit", "")}},
    }
    entry.setdefault("shown", {}).setdefault((quantity, None), (layer.data, kwargs))


def show_quantity(layer, quantity: str, *, residual=None, limits=None) -> None:
    """Switch a quantity layer to ``quantity`` in place (data, placement, colours, name).

    ``residual`` is the dense gray residual for ``quantity="residual"``; ``limits`` a shared
    contrast range. Raises ValueError when the field cannot show ``quantity``. Computes on the
    calling thread; the View panel runs :func:`quantity_update` in a worker instead.
    """
    data, kwargs = quantity_update(layer, quantity, residual=residual, limits=limits)
    apply_quantity(layer, data, kwargs)


def shared_limits(layers, quantity: str) -> list[float] | None:
    """One contrast range for ``quantity`` over several layers already showing it (or None)."""
    limits = [list(x.contrast_limits) for x in layers]
    if not limits or quantity == "status":
        return None
    low, high = min(v[0] for v in limits), max(v[1] for v in limits)
    if QUANTITIES[quantity][1] in ("displacement", "strain"):
        high = max(abs(low), abs(high))
        low = -high
    return [low, high]


def series_fields(fields: list[DisplacementField]) -> list[DisplacementField]:
    """A series' fields with state 0 first (zero displacement), so state ``k`` is index ``k``."""
    first = fields[0]
    zero = first.replace(
        u=np.zeros_like(first.u),
        zncc=np.ones_like(first.zncc),
        status=np.zeros_like(first.status),
        gradient=None,
        metadata=dict(first.metadata),
    )
    return [zero, *fields]


def caption(layer) -> str:
    """What the colorbar of a quantity layer shows, with units, e.g. ``"εeq (corrected) · –"``."""
    entry = plugin_metadata(layer) or {}
    quantity = entry.get("quantity", "")
    what = QUANTITIES.get(quantity, ("", ""))[0]
    text = f"{quantity} [{entry.get('unit', '')}]: {what} — {entry.get('source', '')} field"
    if quantity in ("error estimate", "error resolution"):
        text += error_caption(entry.get("field"))
    return text


def error_caption(field) -> str:
    """What a caption of the error estimate adds: the resolution's median, the share of nodes
    whose estimate is a bound and the share likely above 0.5 voxel ("" without an estimate)."""
    from .engine.evaluation.error_estimate import (
        error_summary,
        estimate_of,
        likely_text,
        resolution_of,
    )

    estimate = None if field is None else estimate_of(field)
    resolution = None if field is None else resolution_of(field)
    if estimate is None or resolution is None:
        return ""
    summary = error_summary(estimate, resolution=resolution)
    return (
        f". Resolution {summary['resolution']:.3f} voxel (median); "
        f"{100 * summary['below_resolution']:.0f} % of nodes below it (there the estimate is a "
        f"bound); {likely_text(summary)}"
    )


def colorbar_title(layer) -> str:
    """The short title of a quantity layer's colorbar, shown on the canvas: what, in which
    units, of which field (``"|u| [mm] · corrected"``); it fits a narrow canvas where the
    :func:`caption` would be cut off (napari's colorbar has no title of its own)."""
    entry = plugin_metadata(layer) or {}
    return f"{entry.get('quantity', '')} [{entry.get('unit', '')}] · {entry.get('source', '')}"
