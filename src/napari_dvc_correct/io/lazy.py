"""Lazy volumes: read a large volume region by region, never whole.

Every lazy volume follows one small protocol, :class:`LazyVolume`:

- ``shape``: ``(nz, ny, nx)`` voxels, axis order ``(z, y, x)``;
- ``dtype``: the stored dtype;
- ``read_region(slices) -> ndarray``: the region as a C-contiguous float32 array.

Implementations: :class:`ArrayVolume` (any array that slices like numpy: an ndarray, a
``numpy.memmap``, an h5py dataset, a Zarr or Dask array), :class:`TiffVolume` (a multi-page TIFF,
memory-mapped when its pages are contiguous and uncompressed, else read through
``TiffFile.aszarr`` tile by tile), :class:`NpyVolume` (a memory-mapped ``.npy``),
:class:`ZarrVolume` (a Zarr array, or the first multiscale level of an OME-Zarr image) and
:class:`SliceFolderVolume` (a folder of 2-D TIFF slices, read slice by slice).

File-backed volumes keep only their path when pickled, so they travel cheaply to
``dask.distributed`` workers, which reopen the file on first use.

:func:`open_volume` picks the implementation from the path; :func:`as_lazy` also accepts arrays.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from .volumes import natural_key as _natural_key  # one slice order for both folder readers
from .volumes import split_member

#: File suffixes of TIFF stacks and slices.
TIFF_SUFFIXES = (".tif", ".tiff")


@runtime_checkable
class LazyVolume(Protocol):
    """A 3-D volume ``(z, y, x)`` read region by region."""

    @property
    def shape(self) -> tuple[int, int, int]: ...

    @property
    def dtype(self) -> np.dtype: ...

    def read_region(self, slices) -> np.ndarray: ...


def normalize_slices(slices, shape) -> tuple[slice, slice, slice]:
    """Three ``slice`` objects with explicit, clipped bounds and unit step.

    Parameters
    ----------
    slices : tuple of 3 slices (or ``(start, stop)`` pairs)
        The region ``(z, y, x)``; ``None`` bounds mean the whole axis.
    shape : tuple of 3 ints
        Volume shape.

    Raises
    ------
    ValueError
        If there are not 3 slices, a step other than 1 is asked for, or the region is empty.
    """
    if len(slices) != 3:
        raise ValueError(f"a region needs 3 slices (z, y, x), got {len(slices)}")
    out = []
    for axis, (item, n) in enumerate(zip(slices, shape)):
        if not isinstance(item, slice):
            item = slice(*item)
        start, stop, step = item.indices(int(n))
        if step != 1:
            raise ValueError(f"regions are read with step 1, got step {step} on axis {axis}")
        if stop <= start:
            raise ValueError(f"empty region on axis {axis}: {start}:{stop} of {n}")
        out.append(slice(start, stop))
    return tuple(out)


def _as_float32(block) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(block), dtype=np.float32)


def _check_shape(shape, source) -> tuple[int, int, int]:
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3:
        raise ValueError(f"{source} is not a 3-D volume (z, y, x): shape {shape}")
    if min(shape) < 1:
        raise ValueError(f"{source} is empty (shape {shape})")
    return shape


def _check_dtype(dtype, source) -> np.dtype:
    dtype = np.dtype(dtype)
    if dtype.kind not in "uif" and dtype != np.bool_:
        raise ValueError(f"{source} must hold real numbers, got dtype {dtype}")
    return dtype


class VolumeBase:
    """Shared behaviour: ``__getitem__`` with slices, ``nbytes``, ``__array__`` for small volumes.

    A subclass sets ``shape`` and ``dtype`` and defines ``read_region`` (a lazy boolean mask
    may return ``bool`` blocks: readers of masks take ``!= 0``).
    """

    shape: tuple[int, int, int]
    dtype: np.dtype

    @property
    def ndim(self) -> int:
        return 3

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape)) * self.dtype.itemsize

    def __getitem__(self, key) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (3 - len(key))
        return self.read_region(key)

    def __array__(self, dtype=None, copy=None):
        data = self.read_region((slice(None),) * 3)
        return data if dtype is None else data.astype(dtype)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(shape={self.shape}, dtype={self.dtype})"


class ArrayVolume(VolumeBase):
    """A lazy view of any array that slices like numpy (ndarray, memmap, h5py, Zarr, Dask).

    Parameters
    ----------
    array : array-like, shape (nz, ny, nx)
        Real-valued. Pickling copies it (use a file-backed volume for large data on a cluster).
    """

    def __init__(self, array) -> None:
        if not hasattr(array, "shape") or not hasattr(array, "dtype"):
            array = np.asarray(array)
        self.array = array
        self.shape = _check_shape(array.shape, "array")
        self.dtype = _check_dtype(array.dtype, "array")

    def read_region(self, slices) -> np.ndarray:
        slices = normalize_slices(slices, self.shape)
        block = self.array[slices]
        if hasattr(block, "compute"):  # dask
            block = block.compute()
        return _as_float32(block)


class _FileVolume(VolumeBase):
    """A volume backed by a file: the open handle is dropped when pickled and reopened lazily."""

    path: Path
    _handle = None

    def _open(self):  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def handle(self):
        if self._handle is None:
            self._handle = self._open()
        return self._handle

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_handle"] = None
        return state

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, shape={self.shape}, dtype={self.dtype})"


class TiffVolume(_FileVolume):
    """A multi-page TIFF stack (or one 3-D TIFF series).

    Uncompressed, contiguous files are memory-mapped (``tifffile.memmap``): a region read touches
    only its bytes. Compressed or tiled files are read through ``TiffFile.aszarr``, which decodes
    only the pages (and tiles) a region overlaps.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        import tifffile

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"TIFF not found: {self.path}")
        try:
            with tifffile.TiffFile(self.path) as tif:
                series = tif.series[0]
                shape, dtype = series.shape, series.dtype
        except (tifffile.TiffFileError, ValueError, OSError, IndexError) as error:
            raise ValueError(f"{self.path} is not a readable TIFF file ({error})") from error
        shape = tuple(n for n in shape if n != 1) if len(shape) > 3 else tuple(shape)
        if len(shape) == 2:
            shape = (1, *shape)
        self.shape = _check_shape(shape, self.path)
        self.dtype = _check_dtype(dtype, self.path)
        self.memory_mapped = self._try_memmap() is not None

    def _try_memmap(self):
        import tifffile

        try:
            mapped = tifffile.memmap(self.path, mode="r")
        except (ValueError, OSError):
            return None
        layout = (int(mapped.offset), mapped.dtype, self.shape)
        del mapped
        return layout

    def _open(self):
        layout = self._try_memmap()
        if layout is not None:
            return _MappedFile(self.path, *layout)
        import tifffile
        import zarr

        store = tifffile.imread(self.path, aszarr=True)
        array = zarr.open(store, mode="r")
        if hasattr(array, "keys"):  # multiscale group: level 0
            array = array[sorted(array.keys())[0]]
        return _Reshaped(array, self.shape)

    def read_region(self, slices) -> np.ndarray:
        slices = normalize_slices(slices, self.shape)
        return _as_float32(self.handle[slices])


class _MappedFile:
    """A contiguous array in a file, memory-mapped afresh for each read.

    Mapping per read (cheap) unmaps the pages afterwards, so the process's resident memory counts
    only the regions being converted, not every page it ever touched.
    """

    def __init__(self, path, offset: int, dtype, shape) -> None:
        self.path, self.offset, self.dtype, self.shape = path, offset, np.dtype(dtype), shape

    def __getitem__(self, slices):
        mapped = np.memmap(self.path, self.dtype, "r", self.offset, self.shape)
        try:
            return np.array(mapped[slices], copy=True)
        finally:
            del mapped


class _Reshaped:
    """Index a stored array with singleton axes as a 3-D one."""

    def __init__(self, array, shape) -> None:
        self.array = array
        self.shape = shape
        self.keep = [i for i, n in enumerate(array.shape) if n != 1]
        if len(array.shape) == 3 or len(self.keep) != 3:
            self.keep = None

    def __getitem__(self, slices):
        if self.keep is None:
            if len(self.array.shape) == 2:
                return np.asarray(self.array[slices[1:]])[None]
            return self.array[slices]
        key = [0] * len(self.array.shape)
        for axis, item in zip(self.keep, slices):
            key[axis] = item
        return self.array[tuple(key)]


class NpyVolume(_FileVolume):
    """A ``.npy`` file, memory-mapped."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"volume not found: {self.path}")
        array = self._open()
        self.shape = _check_shape(array.shape, self.path)
        self.dtype = _check_dtype(array.dtype, self.path)
        self._handle = array

    def _open(self):
        try:
            mapped = np.load(self.path, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError) as error:
            raise ValueError(f"{self.path} is not a readable .npy file ({error})") from error
        order_c = mapped.flags.c_contiguous or mapped.ndim < 2
        layout = (int(mapped.offset), mapped.dtype, mapped.shape)
        del mapped
        if not order_c:  # Fortran order: keep numpy's own map (strided reads)
            return np.load(self.path, mmap_mode="r", allow_pickle=False)
        return _MappedFile(self.path, *layout)

    def read_region(self, slices) -> np.ndarray:
        return _as_float32(self.handle[normalize_slices(slices, self.shape)])


def _ome_multiscales(attrs) -> list | None:
    """The ``multiscales`` list of OME-Zarr metadata (v0.4 top level, v0.5 under ``ome``)."""
    attrs = dict(attrs)
    if "multiscales" in attrs:
        return attrs["multiscales"]
    ome = attrs.get("ome")
    if isinstance(ome, dict) and "multiscales" in ome:
        return ome["multiscales"]
    return None


class ZarrVolume(_FileVolume):
    """A Zarr array, or one level of an OME-Zarr multiscale image.

    Parameters
    ----------
    path : str or PathLike
        The Zarr store (a folder).
    component : str, optional
        Path of the array inside a group. Default: the group's OME multiscale level ``level``,
        else its only array.
    level : int
        OME-Zarr multiscale level (0 = full resolution).

    Leading singleton axes (OME's ``t`` and ``c``) are dropped; more than 3 non-singleton axes is
    an error.
    """

    def __init__(self, path: str | os.PathLike, component: str | None = None, level: int = 0):
        import zarr

        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"Zarr store not found: {self.path}")
        try:
            node = zarr.open(str(self.path), mode="r")
        except Exception as error:  # zarr raises many kinds of errors for a bad store
            raise ValueError(f"{self.path} is not a readable Zarr store ({error})") from error
        self.level = int(level)
        self.component = component
        if hasattr(node, "keys") and component is None:
            self.component = self._default_component(node)
        array = node if self.component is None else node[self.component]
        if hasattr(array, "keys"):
            raise ValueError(f"{self.path}/{self.component} is a Zarr group, not an array")
        squeezed = tuple(n for n in array.shape if n != 1) if array.ndim > 3 else array.shape
        if len(squeezed) != 3:
            raise ValueError(
                f"{self.path}: the array has shape {array.shape}; a volume needs exactly 3 axes "
                "(z, y, x) besides singleton ones"
            )
        self.shape = _check_shape(squeezed, self.path)
        self.dtype = _check_dtype(array.dtype, self.path)
        self.chunks = tuple(getattr(array, "chunks", self.shape))

    def _default_component(self, group) -> str:
        multiscales = _ome_multiscales(group.attrs)
        if multiscales:
            datasets = multiscales[0].get("datasets", [])
            if not datasets:
                raise ValueError(f"{self.path}: OME-Zarr multiscales lists no datasets")
            if not 0 <= self.level < len(datasets):
                raise ValueError(
                    f"{self.path}: level {self.level} does not exist (the image has "
                    f"{len(datasets)} levels)"
                )
            return str(datasets[self.level]["path"])
        arrays = sorted(name for name, _ in group.arrays())
        if len(arrays) != 1:
            raise ValueError(
                f"{self.path} is a Zarr group with {len(arrays)} arrays and no OME multiscales: "
                "name the array (component)"
            )
        return arrays[0]

    def _open(self):
        import zarr

        node = zarr.open(str(self.path), mode="r")
        array = node if self.component is None else node[self.component]
        return _Reshaped(array, self.shape)

    def read_region(self, slices) -> np.ndarray:
        return _as_float32(self.handle[normalize_slices(slices, self.shape)])


class SliceFolderVolume(_FileVolume):
    """A folder of 2-D TIFF slices, one file per z, in natural order (``img2`` before ``img10``).

    A region read opens only the slices it spans (memory-mapped when possible).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        import tifffile

        self.path = Path(path)
        if not self.path.is_dir():
            raise FileNotFoundError(f"slice folder not found: {self.path}")
        self.files = sorted(
            (p for p in self.path.iterdir() if p.suffix.lower() in TIFF_SUFFIXES), key=_natural_key
        )
        if not self.files:
            raise ValueError(f"{self.path} is a folder with no .tif slices")
        try:
            with tifffile.TiffFile(self.files[0]) as tif:
                page = tif.series[0]
                plane, dtype = tuple(n for n in page.shape if n != 1), page.dtype
        except (tifffile.TiffFileError, ValueError, OSError, IndexError) as error:
            raise ValueError(f"{self.files[0]} is not a readable TIFF slice ({error})") from error
        if len(plane) != 2:
            raise ValueError(f"{self.files[0]} is not a 2-D slice (shape {plane})")
        self.shape = _check_shape((len(self.files), *plane), self.path)
        self.dtype = _check_dtype(dtype, self.path)

    def _open(self):
        return {}

    def _slice(self, index: int) -> np.ndarray:
        import tifffile

        path = self.files[index]
        try:
            try:
                plane = tifffile.memmap(path, mode="r")
            except (ValueError, OSError):
                plane = tifffile.imread(path)
        except (tifffile.TiffFileError, ValueError, OSError) as error:
            raise ValueError(f"slice {path} could not be read ({error})") from error
        plane = plane.reshape(tuple(n for n in plane.shape if n != 1) or (1, 1))
        if plane.shape != self.shape[1:]:
            raise ValueError(
                f"slice {path} has shape {plane.shape}, the first slice {self.shape[1:]}: all "
                "slices of a volume must have the same shape"
            )
        return plane

    def read_region(self, slices) -> np.ndarray:
        z, y, x = normalize_slices(slices, self.shape)
        out = np.empty((z.stop - z.start, y.stop - y.start, x.stop - x.start), np.float32)
        for row, index in enumerate(range(z.start, z.stop)):
            out[row] = self._slice(index)[y, x]
        return out


def _is_zarr(path: Path) -> bool:
    if path.suffix.lower() == ".zarr":
        return True
    return path.is_dir() and any(
        (path / name).exists() for name in ("zarr.json", ".zarray", ".zgroup")
    )


def open_volume(
    path: str | os.PathLike, *, component: str | None = None, level: int = 0
) -> LazyVolume:
    """Open a volume lazily, choosing the reader from the path.

    Parameters
    ----------
    path : str or PathLike
        ``.tif``/``.tiff`` stack, ``.npy``, a Zarr store (``.zarr`` or a folder with Zarr
        metadata, OME-Zarr included) or a folder of TIFF slices. An ``.npz`` is read whole
        (its arrays are compressed) and wrapped; ``FILE.npz:NAME`` reads its array ``NAME``.
    component, level : optional
        For Zarr: the array inside a group, or the OME-Zarr multiscale level.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        For an unsupported format or a file that does not hold a 3-D real volume.
    """
    if split_member(path)[1] is not None:  # FILE.npz:NAME, one array of several
        from .volumes import read_volume

        return ArrayVolume(read_volume(path))
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"volume not found: {path}")
    if _is_zarr(path):
        return ZarrVolume(path, component=component, level=level)
    if path.is_dir():
        return SliceFolderVolume(path)
    suffix = path.suffix.lower()
    if suffix in TIFF_SUFFIXES:
        return TiffVolume(path)
    if suffix == ".npy":
        return NpyVolume(path)
    if suffix == ".npz":
        from .volumes import read_volume

        return ArrayVolume(read_volume(path))
    raise ValueError(
        f"{path}: unsupported volume format {suffix!r} (use .tif, .tiff, .npy, .npz, .zarr, "
        "OME-Zarr, or a folder of .tif slices)"
    )


def as_lazy(volume) -> LazyVolume:
    """A :class:`LazyVolume` for a lazy volume (returned as is), a path, or an array."""
    if isinstance(volume, (str, os.PathLike)):
        return open_volume(volume)
    if isinstance(volume, LazyVolume) and not isinstance(volume, np.ndarray):
        return volume
    return ArrayVolume(volume)


def iter_blocks(shape, block_voxels: int = 1 << 24, align: int = 1):
    """Yield ``(z, y)`` slice pairs covering a volume in z-slabs split along y.

    Slab edges fall on multiples of ``align`` (for binning), each block holds about
    ``block_voxels`` voxels (at least ``align`` planes/rows) and spans the whole x axis.
    """
    nz, ny, nx = (int(n) for n in shape)
    align = max(1, int(align))
    rows = max(align, (max(1, block_voxels // max(1, nx)) // align) * align)
    rows = min(rows, ny)
    depth = max(align, (max(1, block_voxels // max(1, nx * rows)) // align) * align)
    for z0 in range(0, nz, depth):
        for y0 in range(0, ny, rows):
            yield slice(z0, min(nz, z0 + depth)), slice(y0, min(ny, y0 + rows))
