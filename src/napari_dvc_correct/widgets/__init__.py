"""The plugin's dock widgets (Qt). Each is thin: it checks choices and runs the engine in a worker.

The Qt-free parts (checks, previews, estimates, read-outs) live in ``*_model.py`` modules.
"""

from __future__ import annotations

__all__ = ["CorrectWidget", "CorrelateWidget", "EvaluateWidget", "ExportWidget", "ViewWidget"]

_MODULES = {
    "CorrelateWidget": "correlate",
    "CorrectWidget": "correct",
    "EvaluateWidget": "evaluate",
    "ExportWidget": "export",
    "ViewWidget": "view",
}


def __getattr__(name: str):
    """Import a panel only when napari asks for it (keeps ``import napari_dvc_correct`` light)."""
    if name in _MODULES:
        import importlib

        module = importlib.import_module(f".{_MODULES[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
