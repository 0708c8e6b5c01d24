"""Save and reopen a session: the scans, the panels' settings and thresholds, the fields.

Thin Qt glue over :mod:`.session_model`: each panel gives its ``settings()`` and takes them back
with ``restore(settings)``; the Export panel has the two buttons.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import layers as L
from .. import viewer_layers as V
from . import session_model as model


def scan_entries(viewer) -> list[dict]:
    """The input scans (Image layers not made by the plugin), in the order opened."""
    from ._layer_kinds import is_scan

    scans = []
    for layer in viewer.layers:
        if not is_scan(layer):
            continue
        path = getattr(getattr(layer, "source", None), "path", None)
        scans.append(
            {
                "name": layer.name,
                "path": str(Path(path).resolve()) if path else None,
                "scale": [float(v) for v in np.asarray(layer.scale)],
                "translate": [float(v) for v in np.asarray(layer.translate)],
                "units": [str(u) for u in layer.units] if getattr(layer, "units", None) else None,
            }
        )
    return scans


def session_fields(viewer) -> dict:
    """Fields to save, by source: single fields (a series is saved state by state)."""
    return dict(L.fields_in(viewer.layers))


def view_state(viewer) -> dict:
    """What the canvas shows, JSON-friendly: the field and quantity on view, the slice (as
    indices), 2-D or 3-D, and the camera."""
    shown = next((x for x in L.quantity_layers(viewer) if x.visible), None)
    entry = (L.plugin_metadata(shown) or {}) if shown is not None else {}
    camera = viewer.scene.camera if hasattr(viewer, "scene") else viewer.camera
    return {
        "source": entry.get("source"),
        "quantity": entry.get("quantity"),
        "current_step": [int(i) for i in viewer.dims.current_step],
        "ndisplay": int(viewer.dims.ndisplay),
        "camera": {
            "center": [float(v) for v in camera.center],
            "zoom": float(camera.zoom),
            "angles": [float(v) for v in camera.angles],
        },
        "canvas": [int(v) for v in viewer.canvas.size],
    }


def restore_view(viewer, view: dict) -> None:
    """Take back :func:`view_state`: the field on view (its layers shown, the others hidden),
    2-D or 3-D, the slice, the camera. Missing entries leave things as they are."""
    source = view.get("source")
    if source:
        for layer in viewer.layers:
            entry = L.plugin_metadata(layer) or {}
            if entry.get("kind") in ("quantity", "vectors"):
                layer.visible = entry.get("source") == source
                if entry.get("kind") == "quantity":
                    layer.colorbar.visible = layer.visible
                    if layer.visible:
                        V.text_overlay(viewer).text = L.colorbar_title(layer)
    if view.get("ndisplay") in (2, 3):
        viewer.dims.ndisplay = view["ndisplay"]
    step = view.get("current_step") or []
    if len(step) == viewer.dims.ndim:
        for axis, (index, steps) in enumerate(zip(step, viewer.dims.nsteps)):
            viewer.dims.set_current_step(axis, min(int(index), max(0, int(steps) - 1)))
    saved = view.get("camera") or {}
    camera = viewer.scene.camera if hasattr(viewer, "scene") else viewer.camera
    if saved.get("angles") and len(saved["angles"]) == 3:
        camera.angles = tuple(saved["angles"])
    if saved.get("center") and len(saved["center"]) == len(camera.center):
        camera.center = tuple(saved["center"])
    if saved.get("zoom"):  # the same part of the scene on a canvas of another size
        canvas = view.get("canvas") or []
        now = [int(v) for v in viewer.canvas.size]
        ratio = min(n / c for n, c in zip(now, canvas)) if len(canvas) == 2 and all(canvas) else 1
        camera.zoom = float(saved["zoom"]) * ratio


def save_session(viewer, path, panels: dict) -> Path:
    """Write the session of ``viewer`` (``panels``: name -> panel with ``settings()``)."""
    settings = {name: panel.settings() for name, panel in panels.items()}
    return model.write_session(
        path, scan_entries(viewer), settings, session_fields(viewer), view_state(viewer)
    )


def open_session(viewer, path, panels: dict) -> dict:
    """Open the scans and fields of a session in ``viewer``, restore the ``panels`` and the
    view, and evaluate again the fields that were evaluated (Evaluate runs in its worker; the
    residual layers and the summary come back when it is done).

    The scans are created with their scale, position and units (no moment with units that
    disagree); the Correlate panel's grid preview stays hidden, as after a run, until one of its
    settings changes.
    """
    from .._reader import read_field_file

    content = model.read_session(path)
    view = content.get("view") or {}
    with V.KeepSliceAndFrame(viewer):  # the scans fill the canvas, whatever was shown before
        for scan in content["scans"]:
            placement = {"scale": scan["scale"], "translate": scan["translate"]}
            if scan.get("units"):
                placement["units"] = scan["units"]
            (layer,) = viewer.open(scan["path"], plugin="napari-dvc-correct", **placement)
            if layer.name != scan["name"]:
                layer.name = scan["name"]
        for file in content["fields"].values():
            V.show_field(viewer, read_field_file(file), quantity=view.get("quantity"))
        for name, panel in panels.items():
            if name in content["panels"]:
                panel.restore(content["panels"][name])
    if content["fields"] and "Correlate" in panels:
        panels["Correlate"].hold_preview()
    restore_view(viewer, view)
    evaluated = content["panels"].get("Evaluate", {}).get("evaluated")
    if evaluated and "Evaluate" in panels:
        panels["Evaluate"].evaluate_again(evaluated)
    return content
