"""npe2 reader: TIFF volumes, folders of TIFF slices, the plugin's field files and other
tools' field files (:mod:`.io.formats`).

A field file opens as the layers of :func:`napari_dvc_correct.layers.field_layers` (one quantity
layer, ``|u|`` first, and the arrows), named after the file.

Which reader napari uses is decided by file name alone (npe2 ``filename_patterns``): where two
plugins claim a name and the user has no preference, File ▸ Open asks. This reader never writes
the user's reader preferences. Our field files are written as ``*.dvcfield``
(:data:`.io.npz.FIELD_SUFFIX`), a name only this plugin claims, so File ▸ Open, drag-and-drop and
``viewer.open(path, plugin=None)`` open them as field layers without a dialog, with fresh
settings. A field file named ``*.npz`` is still read (its contents are checked), but napari's own
reader claims every ``*.npz`` too, so napari asks which reader to use. An ``.npz`` of several
volumes opens as one Image layer each (:func:`read_npz_volumes`); any other ``.npz`` that is
neither our field file nor another tool's is handed to napari's built-in reader.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .io.npz import FIELD_SUFFIX

TIFF_SUFFIXES = (".tif", ".tiff")
PLUGIN = "napari-dvc-correct"


def _builtin_reader(path):
    """napari's own reader for a file that is not ours (an ``.npz`` that is not a field)."""
    from napari_builtins.io import napari_get_reader as builtin

    return builtin(str(path))


#: Field files of other DVC tools (io.formats): spam .tsv, iDVC .disp, ALDVC .mat/.npz, tables.
FOREIGN_SUFFIXES = (".tsv", ".disp", ".mat", ".csv")


def _tiff_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in TIFF_SUFFIXES)


def is_field_file(path: str | os.PathLike) -> bool:
    """True if ``path`` is a readable field file, ``.dvcfield`` or ``.npz`` (see
    :mod:`napari_dvc_correct.io.npz`)."""
    from .io.npz import FIELD_KEYS, FORMAT_NAME, check_member_shapes
    from .io.sizes import check_npz_sizes

    try:
        with zipfile.ZipFile(path) as archive:
            if "format.npy" not in archive.namelist():
                return False
        members = check_npz_sizes(path, FIELD_KEYS)  # headers: sizes and shapes, nothing inflated
        check_member_shapes(path, members)
        with np.load(path, allow_pickle=False) as data:
            return str(data["format"]) == FORMAT_NAME
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return False


def _has_format_marker(path) -> bool:
    """Whether an ``.npz`` says it is our field file (its small ``format`` array, read alone)."""
    from .io.npz import FORMAT_NAME

    try:
        with zipfile.ZipFile(path) as archive:
            if "format.npy" not in archive.namelist():
                return False
            if archive.getinfo("format.npy").file_size > 4096:  # a marker is a short string
                return False
            with archive.open("format.npy") as stream:
                return str(np.lib.format.read_array(stream, allow_pickle=False)) == FORMAT_NAME
    except (OSError, zipfile.BadZipFile, ValueError, EOFError):
        return False


def napari_get_reader(path):
    """Return a reader function for ``path``, or None if this plugin cannot read it.

    Parameters
    ----------
    path : str or list of str
        A file, a folder of TIFF slices, or a list of TIFF slice files (read as one stack).
    """
    if isinstance(path, (list, tuple)):
        paths = [Path(p) for p in path]
        if len(paths) == 1:
            return napari_get_reader(str(paths[0]))
        if paths and all(p.suffix.lower() in TIFF_SUFFIXES and p.is_file() for p in paths):
            return read_tiff_slices
        return None
    path = Path(path)
    if path.is_dir():
        return read_tiff_folder if _tiff_files(path) else None
    suffix = path.suffix.lower()
    if suffix == FIELD_SUFFIX:
        return read_field_file if is_field_file(path) else None
    if suffix == ".npz" and is_field_file(path):
        return read_field_file
    if suffix == ".npz" and _has_format_marker(path):
        return None  # our field file, broken: nothing can read it (napari's reader would raise)
    if suffix == ".roi" and _is_roi(path):
        return read_roi_points
    if suffix in (*FOREIGN_SUFFIXES, ".npz") and foreign_field_format(path):
        return read_foreign_field
    if suffix == ".npz" and len(_npz_volumes(path)) > 1:
        return read_npz_volumes
    if suffix == ".npz":  # not a field: napari's own reader, as if ours were not there
        return _builtin_reader(path)
    if suffix in TIFF_SUFFIXES and path.is_file():
        return read_tiff if is_readable_tiff(path) else None
    return None


def is_readable_tiff(path: str | os.PathLike) -> bool:
    """True if tifffile can open ``path``, it holds at least one page, and (uncompressed) the
    file holds all the image data its header promises (header check only)."""
    from .io.sizes import tiff_size

    try:
        shape, _ = tiff_size(path)  # refuses a truncated file whose header is intact
        return len(shape) > 0
    except Exception:  # any failure to parse means: not ours to claim
        return False


def _placement_from_tiff(tif) -> dict:
    """``scale``/``translate`` stored by :func:`..io.export.export_volume_tiff`, if any."""
    metadata = tif.imagej_metadata or {}
    try:
        info = json.loads(metadata.get("Info", "{}"))
    except (TypeError, ValueError):
        return {}
    placement = {}
    for key in ("scale", "translate"):
        value = info.get(key) if isinstance(info, dict) else None
        if isinstance(value, list) and len(value) == 3:
            placement[key] = [float(v) for v in value]
    return placement


def read_tiff(path) -> list[tuple]:
    """Read one TIFF (memory-mapped when its layout allows) as an Image layer."""
    import tifffile

    path = Path(path[0] if isinstance(path, (list, tuple)) else path)
    with tifffile.TiffFile(path) as tif:
        placement = _placement_from_tiff(tif)
    try:
        data = tifffile.memmap(path, mode="r")
    except (ValueError, OSError):
        data = tifffile.imread(path)
    if len(placement.get("scale", [])) != min(data.ndim, 3) or data.ndim != 3:
        placement = {}
    return [(data, {"name": path.stem, **placement}, "image")]


def read_tiff_folder(path) -> list[tuple]:
    """Read a folder of 2-D TIFF slices (sorted by name) as one 3-D Image layer."""
    from .io.volumes import read_volume

    path = Path(path[0] if isinstance(path, (list, tuple)) else path)
    return [(read_volume(path), {"name": path.name}, "image")]


def read_tiff_slices(paths) -> list[tuple]:
    """Read a list of 2-D TIFF slice files (in the given order) as one 3-D Image layer."""
    import tifffile

    paths = [Path(p) for p in paths]
    return [(tifffile.imread(paths), {"name": paths[0].parent.name or paths[0].stem}, "image")]


def _npz_volumes(path) -> list[str]:
    """Names of the 3-D real arrays of an ``.npz`` (headers only; [] if it cannot tell)."""
    from .io.sizes import npz_members

    try:
        members = npz_members(path)
    except ValueError:
        return []
    return [
        name
        for name, member in members.items()
        if len(member.shape) == 3 and np.dtype(member.dtype).kind in "uif"
    ]


def read_npz_volumes(path) -> list[tuple]:
    """An ``.npz`` holding several volumes (the real-rock crops: ``reference``, ``deformed``):
    one Image layer each, named ``FILE:NAME`` as the command line names them. napari's own
    reader gave one layer under the file's name holding one of them (the deformed scan)."""
    from .io.volumes import read_volume

    path = Path(path[0] if isinstance(path, (list, tuple)) else path)
    return [
        (read_volume(f"{path}:{name}"), {"name": f"{path.stem}:{name}"}, "image")
        for name in _npz_volumes(path)
    ]


def read_field_file(path) -> list[tuple]:
    """Read a field file as the plugin's layers (the ``|u|`` quantity layer and the arrows)."""
    from .io.npz import load_field
    from .layers import field_layers

    path = Path(path[0] if isinstance(path, (list, tuple)) else path)
    field = load_field(path)
    voxel_size = field.metadata.get("voxel_size")
    offset = field.metadata.get("offset")
    return field_layers(field, path.stem, voxel_size=voxel_size, offset=offset)


def foreign_field_format(path) -> str | None:
    """The other tool's format of a field file (:mod:`.io.formats`), or None if it is not one."""
    from .io.formats import sniff_format, table

    try:
        fmt = sniff_format(path)
        if fmt in ("table", "spam", "idvc") and not _has_data_row(path):
            return None  # a header and no rows: nothing to show
        if fmt == "table":
            from .io.formats._common import first_line

            return fmt if table.looks_like(first_line(path)) else None
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return None if fmt == "npz" else fmt


def _has_data_row(path) -> bool:
    """Whether a text table has a line after its header (comments and blank lines aside)."""
    with open(path, encoding="utf-8", errors="replace") as handle:
        lines = (line for line in handle if line.strip() and not line.lstrip().startswith("#"))
        return next(lines, None) is not None and next(lines, None) is not None


def read_foreign_field(path) -> list[tuple]:
    """Read another tool's field file as the plugin's field layers (scattered points are put on
    a grid, with provenance; see :func:`.engine.fields.scattered.to_grid`)."""
    from .io.formats import read_field
    from .layers import field_layers

    path = Path(path[0] if isinstance(path, (list, tuple)) else path)
    field = read_field(path, foreign_field_format(path))
    return field_layers(field, path.stem)


def _is_roi(path: Path) -> bool:
    from .io.formats.idvc import read_roi

    try:
        read_roi(path)
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return True


def read_roi_points(path) -> list[tuple]:
    """A CCPi ``dvc`` point cloud (``.roi``) as a Points layer in z, y, x voxels: the points of
    interest the Correlate panel can measure at (*POIs: the points of a Points layer*)."""
    from .io.formats.idvc import read_roi

    path = Path(path[0] if isinstance(path, (list, tuple)) else path)
    points = read_roi(path)
    return [(points, {"name": path.stem, "size": 2.0, "face_color": "yellow"}, "points")]
