"""Sessions without Qt: what a session file holds, written and read back.

A session is a JSON file (``*.dvc-session.json``) with the scans' paths and placement, the
panels' parameters and thresholds, and the fields, each saved as the plugin's field file in a
folder next to it (``STEM_fields/SOURCE.dvcfield``, so a field reopens under its own name; sessions
written before hold ``SOURCE.npz``, read the same way).
Reopening opens the scans, restores the panels and opens the fields.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..engine.field import DisplacementField

FORMAT = "napari-dvc-correct session"
VERSION = 1
SUFFIX = ".dvc-session.json"


def session_path(path) -> Path:
    """``path`` with the session suffix (``run`` -> ``run.dvc-session.json``)."""
    path = Path(str(path).strip()).expanduser()
    if not path.name.endswith(SUFFIX):
        path = path.with_name(path.name.removesuffix(".json") + SUFFIX)
    return path


def fields_folder(path) -> Path:
    path = session_path(path)
    return path.with_name(path.name.removesuffix(SUFFIX) + "_fields")


def write_session(
    path,
    scans: list,
    panels: dict,
    fields: dict[str, DisplacementField],
    view: dict | None = None,
) -> Path:
    """Write the session file and its field files; returns the session file's path.

    Parameters
    ----------
    scans : list of dict
        ``{"name", "path", "scale", "translate"}`` per scan, in the order opened.
    panels : dict
        Panel name -> its settings (JSON-friendly).
    fields : dict of source -> DisplacementField
        Saved as ``STEM_fields/SOURCE.dvcfield``.
    view : dict, optional
        What the canvas showed (:func:`..session.view_state`): the field and quantity on view,
        the slice, the camera. JSON-friendly.
    """
    from ..io.atomic import atomic_path
    from ..io.npz import FIELD_SUFFIX, save_field

    path = session_path(path)
    if not path.parent.is_dir():
        raise ValueError(f"the folder {path.parent} does not exist")
    missing = [scan["name"] for scan in scans if not scan.get("path")]
    if missing:
        raise ValueError(
            f"{', '.join(missing)} was not opened from a file: a session can only reopen scans "
            "that are files (save them as TIFF first)"
        )
    folder = fields_folder(path)
    files = {}
    if fields:
        folder.mkdir(exist_ok=True)
    for source, field in fields.items():
        target = folder / f"{source}{FIELD_SUFFIX}"
        save_field(field, target)
        files[source] = str(target.relative_to(path.parent))
    content = {
        "format": FORMAT,
        "version": VERSION,
        "scans": scans,
        "panels": panels,
        "fields": files,
        "view": view or {},
    }
    with atomic_path(path) as temp:
        temp.write_text(json.dumps(content, indent=2) + "\n", encoding="utf-8")
    return path


def read_session(path) -> dict:
    """The session's content, with field paths made absolute; ValueError if not a session."""
    path = Path(path)
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise ValueError(f"{path} is not a readable session file: {error}") from error
    if not isinstance(content, dict) or content.get("format") != FORMAT:
        raise ValueError(f"{path} is not a napari-dvc-correct session file")
    content["fields"] = {
        source: str((path.parent / name).resolve()) for source, name in content["fields"].items()
    }
    for scan in content["scans"]:
        if not Path(scan["path"]).exists():
            raise ValueError(f"the scan '{scan['name']}' is not at {scan['path']} any more")
    return content
