"""Save and reopen a session: the scans, the panels' settings and thresholds, the fields.

Thin Qt glue over :mod:`.session_model`: each panel gives its ``settings()`` and takes them back
with ``restore(settings)``; the Export panel has the two buttons.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import layers as L
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


def save_session(viewer, path, panels: dict) -> Path:
    """Write the session of ``viewer`` (``panels``: name -> panel with ``settings()``)."""
    settings = {name: panel.settings() for name, panel in panels.items()}
    return model.write_session(path, scan_entries(viewer), settings, session_fields(viewer))


def open_session(viewer, path, panels: dict) -> dict:
    """Open the scans and fields of a session in ``viewer`` and restore the ``panels``."""
    from .._reader import read_field_file

    content = model.read_session(path)
    with L.KeepSliceAndFrame(viewer):  # the scans fill the canvas, whatever was shown before
        for scan in content["scans"]:
            (layer,) = viewer.open(scan["path"], plugin="napari-dvc-correct")
            if layer.name != scan["name"]:
                layer.name = scan["name"]
            layer.scale, layer.translate = scan["scale"], scan["translate"]
            if scan.get("units"):
                layer.units = scan["units"]
        for name, panel in panels.items():
            if name in content["panels"]:
                panel.restore(content["panels"][name])
        for file in content["fields"].values():
            L.show_field(viewer, read_field_file(file))
    return content
