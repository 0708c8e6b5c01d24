"""Volumes written chunk by chunk to Zarr or TIFF, committed atomically.

:func:`create_output` makes an empty output next to its final path; every chunk task writes its
block through the returned :class:`OutputVolume` (which pickles as a path, so ``dask.distributed``
workers on a shared file system can write too); :meth:`OutputVolume.commit` renames it onto the
final path, and :meth:`OutputVolume.discard` removes it after a failure, so an earlier result is
never half overwritten.

- ``.zarr``: a Zarr array (chunked as asked; compressed by Zarr's default codec);
- ``.tif``/``.tiff``: an uncompressed (Big)TIFF stack, written through a memory map.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

import numpy as np

from .atomic import temp_name

OUTPUT_SUFFIXES = (".zarr", ".tif", ".tiff")


def _kind(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".zarr":
        return "zarr"
    if suffix in (".tif", ".tiff"):
        return "tiff"
    raise ValueError(f"output {path} must end with .zarr, .tif or .tiff")


class OutputVolume:
    """An output being written; ``write(slices, block)`` from any process that sees the file."""

    def __init__(self, final: Path, temp: Path, kind: str, shape, dtype, offset: int = 0):
        self.final, self.temp, self.kind = Path(final), Path(temp), kind
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        self.offset = int(offset)

    def write(self, slices, block: np.ndarray) -> None:
        """Write ``block`` at ``slices`` (a tuple of slices over the leading axes)."""
        block = np.asarray(block, dtype=self.dtype)
        if self.kind == "zarr":
            import zarr

            zarr.open_array(str(self.temp), mode="r+")[tuple(slices)] = block
            return
        mapped = np.memmap(self.temp, self.dtype, "r+", self.offset, self.shape)
        try:
            mapped[tuple(slices)] = block
            mapped.flush()
        finally:
            del mapped

    def commit(self) -> Path:
        """Move the finished output onto its final path (replacing an earlier one)."""
        if self.kind == "tiff":
            os.replace(self.temp, self.final)
            return self.final
        old = None
        if self.final.exists():
            old = self.final.with_name(f".{self.final.name}.old-{os.getpid()}")
            os.replace(self.final, old)
        os.replace(self.temp, self.final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink()
        return self.final

    def discard(self) -> None:
        """Remove the unfinished output."""
        if self.temp.is_dir():
            shutil.rmtree(self.temp, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                self.temp.unlink()


def create_output(path, shape, dtype=np.float32, chunks=None, metadata: dict | None = None):
    """Create an empty output volume of ``shape`` next to ``path`` (not visible there yet).

    Parameters
    ----------
    path : str or PathLike
        Final path, ``.zarr``, ``.tif`` or ``.tiff``; its folder must exist.
    shape : tuple of ints
        ``(nz, ny, nx)`` or ``(nz, ny, nx, C)`` (e.g. a dense displacement field, C = 3).
    dtype : numpy dtype
    chunks : tuple of ints, optional
        Zarr chunk shape (default ``(32, 256, 256[, C])`` clipped to the shape).
    metadata : dict, optional
        JSON-serialisable attributes (Zarr attributes; TIFF ImageDescription).

    Returns
    -------
    OutputVolume
    """
    final = Path(path)
    kind = _kind(final)
    folder = final.parent if str(final.parent) else Path(".")
    if not folder.exists():
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    shape = tuple(int(n) for n in shape)
    if len(shape) not in (3, 4) or min(shape) < 1:
        raise ValueError(f"an output volume needs shape (nz, ny, nx[, C]), got {shape}")
    if kind == "zarr":
        import zarr

        temp = temp_name(final)
        if chunks is None:
            chunks = tuple(min(n, c) for n, c in zip(shape, (32, 256, 256, shape[-1])))
        array = zarr.create_array(str(temp), shape=shape, chunks=tuple(chunks), dtype=dtype)
        if metadata:
            array.attrs.update(metadata)
        return OutputVolume(final, temp, kind, shape, dtype)
    import json

    import tifffile

    temp = temp_name(final)  # unique and recognisable; an earlier final file stays untouched
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    mapped = tifffile.memmap(
        temp,
        shape=shape,
        dtype=dtype,
        bigtiff=nbytes > 2**31,
        photometric="minisblack",
        description=json.dumps(metadata) if metadata else None,
    )
    offset = int(mapped.offset)
    del mapped
    return OutputVolume(final, temp, kind, shape, dtype, offset)


def output_chunks(output: OutputVolume, block_shape) -> tuple[int, int, int]:
    """A task block shape for ``output``: multiples of its Zarr chunks (no two tasks share one)."""
    block_shape = tuple(int(b) for b in block_shape)
    if output.kind != "zarr":
        return block_shape
    import zarr

    chunks = zarr.open_array(str(output.temp), mode="r").chunks[:3]
    return tuple(max(c, (b // c) * c) for b, c in zip(block_shape, chunks))
