"""Layers put into a napari viewer: added or updated in place, framed by the camera, with the
axes labelled, the units matched and the canvas overlays (the quantity's caption and colorbar title).

:mod:`.layers` makes the layer data (no viewer); this module is the part that touches the viewer."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from .layers import (
    MARKER,
    colorbar_title,
    find_layer,
    plugin_metadata,
    quantity_layers,
    show_quantity,
)
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


def label_axes(viewer) -> None:
    """Name the viewer's axes z, y, x (and ``state`` before them for a 4-D series)."""
    ndim = viewer.dims.ndim
    names = ("state", "z", "y", "x")[-ndim:] if ndim <= 4 else None
    if names is not None and ndim >= 3 and tuple(viewer.dims.axis_labels) != names:
        viewer.dims.axis_labels = names


class KeepSliceAndFrame:
    """Context manager for a change of the layers' placement (a voxel size typed, a session's
    scans placed): the same slice (by index) stays on view, and the camera frames the layers
    afterwards, keeping its 3-D angles.

    Without it napari keeps the camera and the world position of the slice: after a voxel size
    of 0.05 mm the scan is a thumbnail in a corner and the slider jumps to the last slice.
    """

    def __init__(self, viewer) -> None:
        self.viewer = viewer
        self.step = None

    def __enter__(self):
        self.step = tuple(self.viewer.dims.current_step)
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is not None:
            return
        frame(self.viewer)
        dims = self.viewer.dims
        if len(self.step) == dims.ndim:
            for axis, (index, steps) in enumerate(zip(self.step, dims.nsteps)):
                dims.set_current_step(axis, min(int(index), max(0, int(steps) - 1)))


def frame(viewer, layers=None) -> None:
    """Fit the camera to ``layers`` (default: all), keeping its 3-D angles."""
    if len(viewer.layers):
        viewer.fit_to_view(layers=layers)


def match_units(viewer, layer) -> None:
    """Give ``layer``, if its units are pixels, the length unit the other layers have (napari
    ignores units that disagree and warns "Inconsistent units across layers" on every draw)."""
    _same_units(viewer, layer)


def _same_units(viewer, layer) -> None:
    """Give ``layer`` the length unit of the scans (napari ignores units that disagree)."""
    if "units" in dir(layer) and all(str(u) == "pixel" for u in layer.units):
        for other in viewer.layers:
            units = [str(u) for u in getattr(other, "units", ())]
            if units and units[-1] != "pixel":
                layer.units = (units[-1],) * layer.ndim
                return


def show_layers(viewer, layer_tuples) -> list:
    """Add layer tuples to ``viewer``, replacing same-named layers the plugin made before.

    A replaced layer keeps its position in the layer list; layers of the same name that the user
    made (without the plugin's metadata) are left alone and the new one gets napari's usual
    numbered name.

    Returns
    -------
    list of napari layers, in the order of ``layer_tuples``.
    """
    return finish(show_layers_steps(viewer, layer_tuples))


def finish(steps: Generator):
    """Run ``steps`` (a generator of showing steps) to its end; its return value."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


def show_layers_steps(viewer, layer_tuples, each=None) -> Generator[None, None, list]:
    """:func:`show_layers` one layer at a time: yields between two layers (napari builds a new
    layer's visual, controls and colorbar on the main thread, 0.1-0.7 s each), so a caller can
    let the event loop turn between them; returns the layers. ``each(layer)``, if given, is
    called after each layer is in; it may return more steps (a generator), run next."""
    from napari.layers import Layer

    added = []
    for data, kwargs, layer_type in layer_tuples:
        if added:
            yield
        key, kwargs = _keyed(kwargs)
        old = find_layer(viewer, key)
        if old is not None and _update_in_place(old, data, kwargs, layer_type):
            layer = old
        else:
            layer = Layer.create(data, kwargs, layer_type)
            _same_units(viewer, layer)
            if old is not None:
                index = viewer.layers.index(old)
                viewer.layers.remove(old)
                viewer.layers.insert(index, layer)
            else:
                viewer.layers.append(layer)
        added.append(layer)
        more = each(layer) if each is not None else None
        if more is not None:
            yield from more
    label_axes(viewer)
    return added


def _keyed(kwargs: dict) -> tuple[str, dict]:
    """The name the plugin finds a layer by (napari may rename it) and the layer's keyword
    arguments with that name in its metadata."""
    kwargs = dict(kwargs)
    name = kwargs.get("name")
    metadata = kwargs.get("metadata") or {}
    entry = metadata.get(MARKER)
    if not isinstance(entry, dict):
        return name, kwargs
    key = entry.get("key", name)
    kwargs["metadata"] = {**metadata, MARKER: {**entry, "name": key}}
    return key, kwargs


#: Layer types whose plugin layers a new result updates in place (:func:`_update_in_place`).
_IN_PLACE = ("image", "vectors")


#: Keyword arguments set before the others (the data's companions first).
_FIRST = ("features", "metadata", "scale", "translate")


def _update_in_place(layer, data, kwargs: dict, layer_type: str) -> bool:
    """Give ``layer`` the new ``data`` and ``kwargs`` if it is of the same type and dimension;
    True if done.

    Replacing a layer (remove, insert) makes napari build a new canvas visual and run a full
    garbage collection on the main thread (a quarter of a second each); updating keeps the
    visual and its colorbar. Where a property cannot be set, the layer is replaced instead.
    """
    if layer_type not in _IN_PLACE or type(layer).__name__.lower() != layer_type:
        return False
    ndim = np.ndim(data) if layer_type == "image" else np.shape(data)[-1]
    if ndim != layer.ndim or (layer_type == "image" and kwargs.get("rgb")):
        return False
    settable = {k: v for k, v in kwargs.items() if k not in ("name", "rgb")}
    try:
        if layer_type == "vectors":  # the features follow the new data's length
            layer.data = data
        for key in [k for k in _FIRST if k in settable]:
            setattr(layer, key, settable.pop(key))
        if layer_type == "image":
            layer.data = data
        for key, value in settable.items():
            setattr(layer, key, value)
        if layer_type == "image" and "contrast_limits" not in kwargs:
            layer.reset_contrast_limits()
    except (AttributeError, TypeError, ValueError):
        return False
    return True


def canvas_overlay(viewer, name: str):
    """A canvas overlay (``"text"``, ``"scale_bar"``): ``viewer.canvas.overlays`` in napari 0.9."""
    canvas = getattr(viewer, "canvas", None)
    overlays = getattr(canvas, "overlays", None)
    if overlays is not None and name in overlays:
        return overlays[name]
    return getattr(viewer, f"{name}_overlay" if name == "text" else name)


def text_overlay(viewer):
    """The canvas text overlay (the caption of the quantity on view)."""
    return canvas_overlay(viewer, "text")


def hide_other_fields(viewer, keep) -> None:
    """Hide the quantity layers and arrows of every field but the layers ``keep`` (and their
    colorbars): one field on view at a time, not stacked."""
    for layer in viewer.layers:
        kind = (plugin_metadata(layer) or {}).get("kind")
        if kind in ("quantity", "vectors") and layer not in keep:
            layer.visible = False
            if kind == "quantity":
                layer.colorbar.visible = False


def show_field(viewer, layer_tuples, quantity: str | None = None) -> list:
    """Show a new field's layers and make them the ones on view (toggled, not stacked).

    The quantity layers and arrows of the other fields are hidden (the View panel switches
    back), the new quantity layer shows ``quantity`` (default: what the visible field showed)
    with its colorbar, the scale bar is on and the axes are named.
    """
    return finish(show_field_steps(viewer, layer_tuples, quantity))


def show_field_steps(
    viewer, layer_tuples, quantity: str | None = None
) -> Generator[None, None, list]:
    """:func:`show_field` in steps, one layer per step (:func:`show_layers_steps`), with the
    same end state; returns the layers.

    Steps: the other fields hidden (no draw of them between the steps); the quantity layer
    added (a series' state slider then goes to its last state, so the next layers are sliced
    once, at that state); its colorbar (napari builds the colorbar's visual, axis and text the
    first time it is shown: 0.2-0.4 s); each further layer."""
    current = next((x for x in quantity_layers(viewer) if x.visible), None)
    if quantity is None and current is not None:
        quantity = plugin_metadata(current).get("quantity")
    kept = [find_layer(viewer, _keyed(kwargs)[0]) for _, kwargs, _ in layer_tuples]
    hide_other_fields(viewer, [x for x in kept if x is not None])
    yield
    new = []

    def on_view(layer):
        if (plugin_metadata(layer) or {}).get("kind") != "quantity":
            return None
        new.append(layer)
        if quantity and quantity != plugin_metadata(layer).get("quantity"):
            try:
                show_quantity(layer, quantity)
            except ValueError:  # e.g. no residual yet for a new field: it keeps its default
                pass
        layer.visible = True
        if len(new) == 1:
            _last_state_on_view(viewer, layer)
        return _colorbar_on(viewer, layer)

    added = yield from show_layers_steps(viewer, layer_tuples, each=on_view)
    hide_other_fields(viewer, added)
    canvas_overlay(viewer, "scale_bar").visible = True
    return added


def _colorbar_on(viewer, layer) -> Generator[None, None, None]:
    """Step: show ``layer``'s colorbar and its caption."""
    if not layer.colorbar.visible:
        yield
    layer.colorbar.visible = True
    text_overlay(viewer).text = colorbar_title(layer)
    text_overlay(viewer).visible = True


def _last_state_on_view(viewer, layer) -> None:
    """A series' 4-D field (state, z, y, x) brought on view at state 0, which does not move,
    showed nothing: the slider goes to its last state (a state chosen before stays)."""
    if layer.ndim != 4 or layer.data.shape[0] < 2 or viewer.dims.ndim < 4:
        return
    axis = viewer.dims.ndim - 4
    first = float(layer.translate[0])
    if float(viewer.dims.point[axis]) <= first:
        viewer.dims.set_point(axis, first + float(layer.scale[0]) * (layer.data.shape[0] - 1))
