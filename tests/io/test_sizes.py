"""Sizes are checked against the headers and the memory before anything is allocated (issue 27
item 5): a TIFF or ``.npz`` header that promises 10^10-10^15 elements, and a small zip that
inflates to hundreds of MB, are refused (or left unread) with the file's name, never a
MemoryError."""

from __future__ import annotations

import io
import os
import tracemalloc
import zipfile

import numpy as np
import pytest
import tifffile

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.io.npz import load_field, save_field
from napari_dvc_correct.io.sizes import check_npz_sizes, npz_members
from napari_dvc_correct.io.volumes import read_volume


def npy_header(shape, dtype="<f4") -> bytes:
    stream = io.BytesIO()
    np.lib.format.write_array_header_2_0(
        stream, {"descr": dtype, "fortran_order": False, "shape": tuple(shape)}
    )
    return stream.getvalue()


def test_a_tiff_header_promising_6e10_voxels_is_refused_before_reading(tmp_path):
    path = tmp_path / "claims.tif"
    tifffile.imwrite(path, shape=(60000, 1000, 1000), dtype="uint8")  # sparse: header + hole
    os.truncate(path, 200_000)  # the header is intact, the data is not there
    with pytest.raises(ValueError, match=r"claims.tif is a truncated TIFF file: .*60000, 1000"):
        read_volume(path)


def test_an_npz_header_promising_3e15_elements_is_refused(tmp_path):
    path = tmp_path / "claims.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("volume.npy", npy_header((300_000, 100_000, 100_000)) + b"\0" * 64)
    with pytest.raises(ValueError, match=r"claims.npz: the array 'volume' claims shape"):
        read_volume(path)
    with pytest.raises(ValueError, match="claims.npz"):
        load_field(path)


def _field() -> DisplacementField:
    field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (3, 3, 3))
    field.u[...] = (0.1, 0.2, 0.3)
    return field


def _add_member(path, name: str, header: bytes, zeros: int) -> None:
    """Append a member of ``zeros`` zero bytes (deflated: a few hundred kB for 100 MB)."""
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open(name, "w", force_zip64=True) as stream:
            stream.write(header)
            chunk = bytes(2**20)
            for _ in range(zeros // len(chunk)):
                stream.write(chunk)


def test_load_field_never_inflates_what_it_does_not_read(tmp_path):
    """A 'zip bomb' member is not unpacked: the peak stays far below its 128 MB."""
    path = tmp_path / "bomb.npz"
    save_field(_field(), path)
    _add_member(path, "junk.npy", npy_header((2**25,)), 2**27)
    assert path.stat().st_size < 2**20 and npz_members(path)["junk"].nbytes == 2**27
    tracemalloc.start()
    try:
        field = load_field(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert field.shape == (3, 3, 3) and peak < 2**24, peak  # measured ~0.1 MB (was > 128 MB)
    with pytest.raises(ValueError, match="more than the"):
        check_npz_sizes(path, available=2**26)


def test_field_arrays_of_another_grid_are_refused_from_their_headers(tmp_path):
    path = tmp_path / "mixed.npz"
    save_field(_field(), path)
    with zipfile.ZipFile(path) as archive:
        kept = {n: archive.read(n) for n in archive.namelist() if n != "zncc.npy"}
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in kept.items():
            archive.writestr(name, data)
        archive.writestr("zncc.npy", npy_header((4000, 4000, 4000)) + bytes(64))
    with pytest.raises(ValueError, match="zncc"):
        load_field(path)
