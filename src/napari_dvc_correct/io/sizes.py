"""How much memory reading a file would take, known from its header before anything is allocated.

A file's header can claim any size: a TIFF whose pages promise 6·10¹⁰ voxels, an ``.npz`` member
whose ``.npy`` header promises 3·10¹⁵ elements, or a small zip whose members inflate to hundreds
of MB (a zip bomb). The readers ask these functions first and refuse with a ``ValueError`` that
names the file, instead of ending in a ``MemoryError`` (or swapping) half-way.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def available_memory() -> int:
    """Bytes this process can still allocate: ``MemAvailable`` (Linux), capped by a cgroup limit."""
    available = None
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            available = 1 << 34
    try:
        with open("/sys/fs/cgroup/memory.max") as handle:
            limit = handle.read().strip()
        with open("/sys/fs/cgroup/memory.current") as handle:
            used = int(handle.read().strip())
        if limit != "max":
            available = min(available, int(limit) - used)
    except (OSError, ValueError):
        pass
    return int(max(available, 0))


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def check_fits_in_memory(path, nbytes: int, what: str, available: int | None = None) -> None:
    """Raise ``ValueError`` (naming ``path``) if reading ``nbytes`` would not fit in memory."""
    available = available_memory() if available is None else int(available)
    if nbytes > available:
        raise ValueError(
            f"{path}: its header says {what} of {_gib(nbytes)}, more than the {_gib(available)} "
            "of memory available: the file is broken, or too large to read whole (use --tiled)"
        )


@dataclass(frozen=True)
class NpzMember:
    """One array of an ``.npz``, as its ``.npy`` header describes it (nothing decompressed)."""

    name: str  #: key, without ``.npy``
    shape: tuple
    dtype: np.dtype
    stored: int  #: bytes inflated, as the zip directory says

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=object)) * int(self.dtype.itemsize)


def npz_members(path: str | os.PathLike) -> dict[str, NpzMember]:
    """The arrays of an ``.npz`` from their headers only: name -> :class:`NpzMember`.

    Raises
    ------
    ValueError
        If the file is not a zip of ``.npy`` arrays, or a member's header is broken, holds
        Python objects, or promises more bytes than the member holds (a lying header).
    """
    path = Path(path)
    members = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with archive.open(info) as stream:
                    version = np.lib.format.read_magic(stream)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(stream)
                    else:
                        shape, _, dtype = np.lib.format.read_array_header_2_0(stream)
                    header = stream.tell()
                member = NpzMember(info.filename[:-4], tuple(shape), np.dtype(dtype),
                                   int(info.file_size))  # fmt: skip
                if member.dtype.hasobject:
                    raise ValueError(f"{path}: the array {member.name!r} holds Python objects")
                if member.nbytes > member.stored - header:
                    raise ValueError(
                        f"{path}: the array {member.name!r} claims shape {member.shape} "
                        f"({_gib(member.nbytes)}) but holds {member.stored - header} bytes: the "
                        "file is broken"
                    )
                members[member.name] = member
    except (zipfile.BadZipFile, OSError, EOFError, zipfile.LargeZipFile) as error:
        raise ValueError(f"{path} is not a readable .npz file ({error})") from None
    except ValueError as error:
        if str(path) in str(error):
            raise
        raise ValueError(f"{path} is not a readable .npz file ({error})") from None
    return members


def check_npz_sizes(path, names=None, available: int | None = None) -> dict[str, NpzMember]:
    """:func:`npz_members`, and refuse if the arrays ``names`` (default all) do not fit in memory."""
    members = npz_members(path)
    chosen = [m for n, m in members.items() if names is None or n in names]
    check_fits_in_memory(path, sum(m.nbytes for m in chosen), f"{len(chosen)} array(s)", available)
    return members


def tiff_size(path: str | os.PathLike) -> tuple[tuple, np.dtype]:
    """Shape and dtype of a TIFF's first series, from its header (no image data read).

    Raises
    ------
    ValueError
        If the file is not a readable TIFF, or is uncompressed and shorter than the image data
        its header promises (a truncated file).
    """
    import logging

    import tifffile

    quiet = logging.getLogger("tifffile")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)  # a truncated file's "invalid page offset": we say it once
    try:
        with tifffile.TiffFile(path) as tif:
            series = tif.series[0]
            shape, dtype = tuple(series.shape), np.dtype(series.dtype)
            compressed = int(tif.pages.first.compression) != 1
    except (tifffile.TiffFileError, ValueError, OSError, IndexError, KeyError) as error:
        raise ValueError(f"{path} is not a readable TIFF file ({error})") from error
    finally:
        quiet.setLevel(level)
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    size = os.path.getsize(path)
    if not compressed and nbytes > size:
        raise ValueError(
            f"{path} is a truncated TIFF file: its header promises {shape} {dtype} "
            f"({_gib(nbytes)}) but the file holds {size} bytes"
        )
    return shape, dtype
