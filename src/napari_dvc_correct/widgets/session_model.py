"""Sessions without Qt: what a session file holds, written and read back.

A session is a JSON file (``*.dvc-session.json``) with the scans' paths and placement, the
panels' parameters and thresholds, and the fields, each saved as the plugin's field file in a
folder next to it (``STEM_fields/SOURCE.dvcfield``, so a field reopens under its own name; sessions
written before hold ``SOURCE.npz``, read the same way).
Reopening opens the scans, restores the panels and opens the fields.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from ..engine.fields.field import DisplacementField

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
        # always inside the fields folder
        target = folder / f"{_file_stem(source, files)}{FIELD_SUFFIX}"
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


def _file_stem(source: str, taken: dict) -> str:
    """A file name for a field's source: no folder parts, no leading dot, unique in ``taken``."""
    stem = re.sub(r"[^\w.()+=-]+", "_", str(source)).strip("._") or "field"
    used = {Path(name).stem for name in taken.values()}
    unique, number = stem, 2
    while unique in used:
        unique, number = f"{stem}_{number}", number + 1
    return unique


def read_session(path) -> dict:
    """The session's content, checked, with field paths made absolute.

    Raises
    ------
    ValueError
        For anything but a session this version wrote or could have written: not JSON (or
        nested too deeply), another format, a newer or non-integer version, entries of the wrong
        type, a field file outside the session's folder (``../``), a scan that is gone.
    """
    path = Path(path)
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as error:
        raise ValueError(f"{path} is not a readable session file: {error}") from None
    if not isinstance(content, dict) or content.get("format") != FORMAT:
        raise ValueError(f"{path} is not a napari-dvc-correct session file")
    version = content.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise ValueError(f"{path} has an invalid session version {str(version)[:20]!r}")
    if version > VERSION:
        raise ValueError(
            f"{path} is a session of version {version}, newer than this napari-dvc-correct "
            f"reads ({VERSION}): upgrade the package"
        )
    scans, panels, fields = (content.get(k) for k in ("scans", "panels", "fields"))
    if not isinstance(scans, list) or not all(isinstance(s, dict) for s in scans):
        raise ValueError(f"{path}: 'scans' must be a list of scans")
    if not isinstance(panels, dict) or not all(isinstance(v, dict) for v in panels.values()):
        raise ValueError(f"{path}: 'panels' must map panel names to their settings")
    if not isinstance(fields, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in fields.items()
    ):
        raise ValueError(f"{path}: 'fields' must map field names to file names")
    content["scans"] = [_checked_scan(path, scan) for scan in scans]
    folder = path.parent.resolve()
    resolved = {}
    for source, name in fields.items():
        file = (folder / name).resolve()
        if not file.is_relative_to(folder):
            raise ValueError(
                f"{path}: the field '{source}' points outside the session's folder ({name}): "
                "a session only opens field files next to it"
            )
        resolved[source] = str(file)
    content["fields"] = resolved
    for scan in content["scans"]:
        if not Path(scan["path"]).exists():
            raise ValueError(f"the scan '{scan['name']}' is not at {scan['path']} any more")
    return content


def _checked_scan(path: Path, scan: dict) -> dict:
    """One scan entry with the types :func:`..session.open_session` uses, else ValueError."""
    name, file = scan.get("name"), scan.get("path")
    if not isinstance(name, str) or not isinstance(file, str) or not file:
        raise ValueError(f"{path}: every scan needs a 'name' and a 'path' (text)")
    for key in ("scale", "translate"):
        value = scan.get(key)
        if not (
            isinstance(value, list)
            and 2 <= len(value) <= 5
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            and all(math.isfinite(v) for v in value)
        ):
            raise ValueError(f"{path}: the scan '{name}' needs a '{key}' of finite numbers")
    if any(v <= 0 for v in scan["scale"]):
        raise ValueError(f"{path}: the scan '{name}' has a scale that is not > 0")
    units = scan.get("units")
    if units is not None and not (
        isinstance(units, list) and all(isinstance(u, str) for u in units)
    ):
        raise ValueError(f"{path}: the scan '{name}' has units that are not a list of names")
    return scan
