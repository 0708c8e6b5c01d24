"""Reading volumes for the engine: TIFF (memory-mapped where possible), ``.npy`` and ``.npz``."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..engine.validation import validate_volume
from .sizes import check_fits_in_memory, npz_members, tiff_size

VOLUME_SUFFIXES = (".tif", ".tiff", ".npy", ".npz")


def read_volume(path: str | os.PathLike, mmap: bool = True) -> np.ndarray:
    """Read a 3-D volume ``(z, y, x)`` from a TIFF stack, a folder of TIFF slices, ``.npy`` or ``.npz``.

    The slices of a folder are stacked along z in natural order (``img2`` before ``img10``), as
    :class:`.lazy.SliceFolderVolume` reads them.

    TIFF and ``.npy`` files are memory-mapped when their layout allows it, so only the regions
    the engine touches are read. An ``.npz`` must hold exactly one array (or one named ``volume``),
    or the array is named after a colon: ``rock_lower.npz:reference`` (:func:`split_member`).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file is not what its name claims, or does not hold a 3-D real-valued volume.
    """
    path, member = split_member(path)
    if not path.exists():
        raise FileNotFoundError(f"volume not found: {path}")
    if member is not None:
        return validate_volume(_read_npz(path, member), f"{path}:{member}")
    if path.is_dir():
        volume = _read_tiff_folder(path)
    else:
        suffix = path.suffix.lower()
        if suffix in (".tif", ".tiff"):
            volume = _read_tiff(path, mmap)
        elif suffix == ".npy":
            try:
                volume = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
            except (ValueError, OSError) as error:
                raise ValueError(f"{path} is not a readable .npy file ({error})") from error
        elif suffix == ".npz":
            volume = _read_npz(path)
        else:
            raise ValueError(
                f"{path}: unsupported volume format {suffix!r} (use .tif, .tiff, .npy, .npz "
                "or a folder of .tif slices)"
            )
    return validate_volume(volume, str(path))


def natural_key(path: Path) -> list:
    """Sort key of a slice file: numbers compare as numbers (``img2`` before ``img10``)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def _read_tiff(path: Path, mmap: bool) -> np.ndarray:
    import tifffile

    shape, dtype = tiff_size(path)  # the header's claim, checked before anything is allocated
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    try:
        if mmap:
            try:
                return tifffile.memmap(path, mode="r")
            except (ValueError, OSError, IndexError):
                pass  # compressed or tiled (or broken: reading says so): fall back to reading
        check_fits_in_memory(path, nbytes, f"a volume {shape} {dtype}")
        volume = tifffile.imread(path)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError) as error:
        raise ValueError(f"{path} is not a readable TIFF file ({error})") from error
    if volume.size == 0:  # a broken header reads as no pages
        raise ValueError(f"{path} is not a readable TIFF file (no image data)")
    return volume


def _read_tiff_folder(path: Path) -> np.ndarray:
    import tifffile

    files = sorted(
        (p for p in path.iterdir() if p.suffix.lower() in (".tif", ".tiff")), key=natural_key
    )
    if not files:
        raise ValueError(f"{path} is a folder with no .tif slices")
    try:
        return tifffile.imread(files)
    except (tifffile.TiffFileError, ValueError, OSError) as error:
        raise ValueError(
            f"{path}: the TIFF slices could not be read as one stack ({error})"
        ) from error


def split_member(path: str | os.PathLike) -> tuple[Path, str | None]:
    """``FILE.npz:NAME`` -> ``(FILE.npz, NAME)``: one array of an ``.npz`` that holds several
    (the real-rock crops hold ``reference``, ``deformed`` and ``box_zyx``). Any other path, or
    a file whose own name has such a colon, is returned whole with ``None``."""
    text = os.fspath(path)
    head, colon, name = text.rpartition(":")
    if colon and name and head.lower().endswith(".npz") and not Path(text).exists():
        return Path(head), name
    return Path(text), None


def _read_npz(path: Path, member: str | None = None) -> np.ndarray:
    import zipfile

    members = npz_members(path)  # headers only: sizes checked before anything is inflated
    names = list(members)
    if member is not None:
        if member not in names:
            raise ValueError(f"{path} holds no array {member!r}; it holds {', '.join(names[:8])}")
        names = [member]
    if "volume" in names:
        names = ["volume"]
    if len(names) != 1:
        raise ValueError(
            f"{path} holds {len(names)} arrays ({', '.join(names[:5])}); "
            f"store one array, name it 'volume', or name the one to read: {path}:{names[0]}"
        )
    member = members[names[0]]
    check_fits_in_memory(path, member.nbytes, f"a volume {member.shape} {member.dtype}")
    try:
        with np.load(path, allow_pickle=False) as data:
            return data[names[0]]
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise ValueError(f"{path} is not a readable .npz file ({error})") from error
