"""Exporting fields and volumes: HDF5, VTK image data (ParaView), TIFF stacks, CSV, reports.

Every writer is atomic (see :func:`~napari_dvc_correct.io.atomic.atomic_path`): a failed or
interrupted export leaves an existing file untouched. No Qt, no napari, no vtk dependency: XML VTK
files (``.vti`` image data, ``.vtu`` points) are written by ``pyevtk``; the legacy ``.vtk`` (which
pyevtk does not write) by a small writer here.

Grid quantities beyond the field itself (equivalent strain, ...) are passed as ``extra``: a dict of
arrays of the grid shape ``(nz, ny, nx)``, written next to the field's own arrays.

A field at scattered points (:class:`..engine.fields.scattered.ScatteredField`, e.g. a Correlate run on a
Points layer) goes through :func:`export_points`: CSV here, ``.vtu`` points, and the other tools'
formats of :mod:`.formats` (the writers the command line's ``correlate --points`` uses); formats
that need a regular grid are refused.

Axis order: numpy arrays are ``(z, y, x)`` as everywhere in the package. VTK wants points with x
varying fastest (which is numpy's C order of a ``(z, y, x)`` array), dimensions/spacing/origin as
``(x, y, z)`` and vectors as ``(ux, uy, uz)``: the VTK writers reorder these, nothing else does.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np

from ..engine.fields.field import DisplacementField, Provenance, Status
from ..engine.fields.scattered import ScatteredField
from .atomic import atomic_path
from .formats._common import unusable_as_nan
from .npz import FIELD_SUFFIX, _json_default, save_field

#: File suffixes :func:`export_field` understands, and what they write.
FIELD_FORMATS = {
    FIELD_SUFFIX: "napari-dvc-correct field (numpy .npz contents; napari opens it with this plugin)",
    ".npz": "napari-dvc-correct field (numpy .npz)",
    ".h5": "HDF5",
    ".hdf5": "HDF5",
    ".vti": "VTK XML image data (ParaView)",
    ".vtk": "VTK legacy structured points (ParaView)",
    ".csv": "CSV, one row per POI",
    ".tif": "TIFF stacks, one file per component",
    ".tiff": "TIFF stacks, one file per component",
    ".vtu": "VTK XML points, one per node (ParaView)",
    ".tsv": "spam TSV",
    ".disp": "iDVC .disp",
    ".mat": "ALDVC MATLAB .mat",
}

#: Export format names (the command line's ``export --format``) -> the suffix that writes them.
EXPORT_FORMATS = {
    "dvcfield": FIELD_SUFFIX,
    "npz": ".npz",
    "hdf5": ".h5",
    "vti": ".vti",
    "vtk": ".vtk",
    "vtu": ".vtu",
    "csv": ".csv",
    "tiff": ".tif",
    "spam": ".tsv",
    "idvc": ".disp",
    "aldvc": ".mat",
}

#: File suffixes :func:`export_points` understands (a field at scattered points), and what they
#: write; the command line's ``correlate --points`` writes the same files (``.npz`` with
#: ``--out-format aldvc``).
POINT_FORMATS = {
    ".csv": "CSV, one row per point",
    ".npz": "pyALDVC .npz at the points (coordinates, U_1, zncc_1, status_1)",
    ".vtu": "VTK XML points (ParaView)",
    ".tsv": "spam TSV",
    ".disp": "iDVC .disp",
    ".mat": "ALDVC MATLAB .mat",
}

#: Writer of :mod:`.formats` for each suffix of :data:`POINT_FORMATS` it writes.
_POINT_WRITERS = {".npz": "aldvc", ".tsv": "spam", ".disp": "idvc", ".mat": "aldvc"}


def _json(value) -> str:
    return json.dumps(value, default=_json_default)


def _check_extra(
    field: DisplacementField | ScatteredField, extra: dict | None
) -> dict[str, np.ndarray]:
    checked = {}
    scattered = isinstance(field, ScatteredField)
    shape = (field.n_points,) if scattered else field.shape
    for name, values in (extra or {}).items():
        array = np.asarray(values)
        if array.shape != shape:
            where = "one value per point" if scattered else "the grid shape"
            raise ValueError(f"extra array {name!r} must have {where} {shape}, got {array.shape}")
        checked[str(name)] = array
    return checked


def _with_uncertainty(field: DisplacementField, extra: dict) -> dict:
    """``extra`` plus the per-node uncertainty ``uncertainty_uz/uy/ux`` and the evaluation's
    ``error_estimate`` and ``error_resolution`` (voxels), where the field has them."""
    own = {}
    if field.uncertainty is not None:
        sigma = np.asarray(field.uncertainty, np.float32)
        own = {f"uncertainty_{axis}": sigma[..., k] for k, axis in enumerate(("uz", "uy", "ux"))}
    return {**extra, **own, **_evaluation_arrays(field)}


def _evaluation_arrays(field: DisplacementField) -> dict:
    """The error estimate an accuracy evaluation left on ``field`` and the residual's resolution
    there (voxels, float32 on the grid; below the resolution the estimate is a bound)."""
    from ..engine.evaluation.error_estimate import estimate_of, resolution_of

    arrays = {"error_estimate": estimate_of(field), "error_resolution": resolution_of(field)}
    return {k: v.astype(np.float32) for k, v in arrays.items() if v is not None}


def _voxel_size(voxel_size) -> np.ndarray:
    vs = np.ones(3) if voxel_size is None else np.asarray(voxel_size, dtype=np.float64)
    vs = np.broadcast_to(vs, (3,)).astype(np.float64)
    if not np.all(np.isfinite(vs) & (vs > 0)):
        raise ValueError(f"voxel_size must be 3 positive numbers (z, y, x), got {voxel_size!r}")
    return vs


# -- HDF5 --------------------------------------------------------------------------------------
def export_hdf5(
    field: DisplacementField,
    path: str | os.PathLike,
    *,
    extra: dict | None = None,
    volumes: dict | None = None,
    voxel_size=None,
) -> Path:
    """Write the field (and optional grid or dense quantities) to an HDF5 file.

    Layout: group ``/field`` with datasets ``u`` (nz, ny, nx, 3), ``zncc``, ``status``,
    ``iterations``, ``provenance``, ``gradient`` and ``uncertainty`` (if any), ``points`` (N, 3)
    and ``displacement`` (N, 3); attributes ``origin``, ``step``, ``voxel_size`` (z, y, x), ``params`` and ``metadata``
    (JSON), ``status_names`` and ``provenance_names``. Group ``/grid`` holds the ``extra`` arrays
    and an evaluation's ``error_estimate``/``error_resolution`` (grid shape), group ``/volumes`` the ``volumes`` (dense, e.g. the gray residual).
    """
    import h5py

    field = unusable_as_nan(field)  # a failed node: NaN and its status, as in every export
    extra = {**_check_extra(field, extra), **_evaluation_arrays(field)}
    vs = _voxel_size(voxel_size)
    path = Path(path)
    with atomic_path(path) as temp:
        with h5py.File(temp, "w") as h5:
            group = h5.create_group("field")
            options = {"compression": "gzip", "compression_opts": 4}
            for name in ("u", "zncc", "status", "iterations", "provenance"):
                group.create_dataset(name, data=getattr(field, name), **options)
            if field.gradient is not None:
                group.create_dataset("gradient", data=field.gradient, **options)
            if field.uncertainty is not None:  # voxels, (z, y, x) components
                group.create_dataset("uncertainty", data=field.uncertainty, **options)
            group.create_dataset("points", data=field.points, **options)
            group.create_dataset("displacement", data=field.displacement, **options)
            group.attrs["origin"] = np.asarray(field.origin)
            group.attrs["step"] = np.asarray(field.step)
            group.attrs["voxel_size"] = vs
            group.attrs["axis_order"] = "z, y, x"
            group.attrs["units"] = "voxels"
            group.attrs["params"] = _json(field.params)
            group.attrs["metadata"] = _json(field.metadata)
            group.attrs["status_names"] = _json({int(s): s.label for s in Status})
            group.attrs["provenance_names"] = _json({int(p): p.label for p in Provenance})
            if extra:
                grid = h5.create_group("grid")
                for name, values in extra.items():
                    grid.create_dataset(name, data=values, **options)
            if volumes:
                dense = h5.create_group("volumes")
                for name, values in volumes.items():
                    dense.create_dataset(str(name), data=np.asarray(values), **options)
    return path


# -- VTK ---------------------------------------------------------------------------------------
_VTK_TYPES = {
    np.dtype(np.float32): ("Float32", "float"),
    np.dtype(np.float64): ("Float64", "double"),
    np.dtype(np.int32): ("Int32", "int"),
    np.dtype(np.uint8): ("UInt8", "unsigned_char"),
}


def _vtk_arrays(field: DisplacementField, extra: dict, vs: np.ndarray) -> list[tuple]:
    """``(name, array (N, components) in VTK point order, n_components)``."""
    n = field.n_points
    # displacement in physical units, components reordered to (x, y, z)
    u = (field.u * vs).reshape(n, 3)[:, ::-1].astype(np.float32)
    arrays = [
        ("displacement", np.ascontiguousarray(u), 3),
        ("magnitude", np.linalg.norm(u, axis=1).astype(np.float32).reshape(n, 1), 1),
        ("zncc", field.zncc.reshape(n, 1), 1),
        ("status", field.status.reshape(n, 1), 1),
        ("iterations", field.iterations.reshape(n, 1), 1),
        ("provenance", field.provenance.reshape(n, 1), 1),
    ]
    for name, values in extra.items():
        values = np.asarray(values)
        if values.dtype not in _VTK_TYPES:
            values = values.astype(np.float32)
        arrays.append((name.replace(" ", "_"), values.reshape(n, 1), 1))
    return arrays


def export_vtk(
    field: DisplacementField,
    path: str | os.PathLike,
    *,
    extra: dict | None = None,
    voxel_size=None,
) -> Path:
    """Write the field as VTK image data for ParaView: XML ``.vti`` or legacy ``.vtk``.

    The grid becomes the image (origin and spacing ``origin * voxel_size`` and
    ``step * voxel_size``, reordered to x, y, z); point data hold ``displacement`` (a 3-vector
    ``(ux, uy, uz)`` in physical units, ready for ParaView's *Warp By Vector* and *Glyph*),
    ``magnitude``, ``zncc``, ``status``, ``iterations``, ``provenance`` and the ``extra`` grid
    arrays. ``.vti`` is written by ``pyevtk`` (``imageToVTK``, binary appended data); pyevtk has
    no legacy writer, so ``.vtk`` (``STRUCTURED_POINTS``) keeps a small writer of its own.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".vti", ".vtk"):
        raise ValueError(f"{path}: a VTK export must end in .vti (XML) or .vtk (legacy)")
    field = unusable_as_nan(field)
    extra = _with_uncertainty(field, _check_extra(field, extra))
    vs = _voxel_size(voxel_size)
    arrays = _vtk_arrays(field, extra, vs)
    origin = (np.asarray(field.origin) * vs)[::-1]
    spacing = (np.asarray(field.step) * vs)[::-1]
    dims = field.shape[::-1]
    with atomic_path(path) as temp:
        if suffix == ".vti":
            _write_vti(temp, dims, origin, spacing, arrays)
        else:
            _write_legacy_vtk(temp, dims, origin, spacing, arrays)
    return path


def _pyevtk_point_data(arrays, dims) -> dict:
    """``(name, (N, c) values in VTK point order, c)`` -> pyevtk's (nx, ny, nz) arrays."""
    data = {}
    for name, values, components in arrays:
        # VTK point order is x fastest: the (N,) column reshaped in Fortran order to (nx, ny, nz)
        columns = [
            np.asfortranarray(values[:, c].reshape(dims, order="F")) for c in range(components)
        ]
        data[name] = tuple(columns) if components == 3 else columns[0]
    return data


def _write_vti(path: Path, dims, origin, spacing, arrays) -> None:
    """XML ImageData through ``pyevtk.hl.imageToVTK`` (it appends ``.vti`` to the name)."""
    from pyevtk.hl import imageToVTK

    stem = str(path)[: -len(".vti")] if str(path).endswith(".vti") else str(path)
    written = imageToVTK(
        stem,
        origin=tuple(float(v) for v in origin),
        spacing=tuple(float(v) for v in spacing),
        pointData=_pyevtk_point_data(arrays, tuple(int(n) for n in dims)),
    )
    if Path(written) != Path(path):
        os.replace(written, path)


def export_vtk_points(field, path: str | os.PathLike, *, voxel_size=None) -> Path:
    """Write a field at scattered points (:class:`..engine.fields.scattered.ScatteredField`, or a grid
    field's nodes) as a VTK unstructured grid of vertices, ``.vtu``, via ``pyevtk.hl.pointsToVTK``.

    Point coordinates and the ``displacement`` vector ``(ux, uy, uz)`` are in physical units
    (``voxel_size`` per axis z, y, x; default voxels), x, y, z order; point data also hold
    ``magnitude``, ``zncc``, ``status``, ``iterations``, ``provenance`` and a grid field's
    ``error_estimate``/``error_resolution`` (voxels) where an evaluation left them.
    """
    from pyevtk.hl import pointsToVTK

    from ..engine.fields.scattered import ScatteredField, from_grid

    path = Path(path)
    if path.suffix.lower() != ".vtu":
        raise ValueError(f"{path}: VTK points are written as .vtu (XML unstructured grid)")
    points = unusable_as_nan(field if isinstance(field, ScatteredField) else from_grid(field))
    vs = _voxel_size(voxel_size)
    xyz = (points.points * vs)[:, ::-1]
    u = (points.u * vs)[:, ::-1].astype(np.float32)
    data = {
        "displacement": tuple(np.ascontiguousarray(u[:, c]) for c in range(3)),
        "magnitude": np.ascontiguousarray(np.linalg.norm(u, axis=1).astype(np.float32)),
        "zncc": np.ascontiguousarray(points.zncc),
        "status": np.ascontiguousarray(points.status),
        "iterations": np.ascontiguousarray(points.iterations),
        "provenance": np.ascontiguousarray(points.provenance),
    }
    if not isinstance(field, ScatteredField):  # a grid's nodes in C order, as ``from_grid``'s
        for name, values in _evaluation_arrays(field).items():
            data[name] = np.ascontiguousarray(values.reshape(-1))
    with atomic_path(path) as temp:
        stem = str(temp)[: -len(".vtu")]
        written = pointsToVTK(stem, *(np.ascontiguousarray(xyz[:, c]) for c in range(3)), data=data)
        if Path(written) != temp:
            os.replace(written, temp)
    return path


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def _write_legacy_vtk(path: Path, dims, origin, spacing, arrays) -> None:
    """Legacy ``DATASET STRUCTURED_POINTS``, binary (big-endian) point data."""
    n = int(np.prod(dims))
    header = (
        "# vtk DataFile Version 3.0\n"
        "napari-dvc-correct displacement field\n"
        "BINARY\n"
        "DATASET STRUCTURED_POINTS\n"
        f"DIMENSIONS {dims[0]} {dims[1]} {dims[2]}\n"
        f"ORIGIN {_fmt(origin)}\n"
        f"SPACING {_fmt(spacing)}\n"
        f"POINT_DATA {n}\n"
    )
    with open(path, "wb") as stream:
        stream.write(header.encode("ascii"))
        for name, values, components in arrays:
            legacy_type = _VTK_TYPES[np.dtype(values.dtype)][1]
            if components == 3:
                stream.write(f"VECTORS {name} {legacy_type}\n".encode("ascii"))
            else:
                stream.write(f"SCALARS {name} {legacy_type} 1\nLOOKUP_TABLE default\n".encode())
            stream.write(values.astype(values.dtype.newbyteorder(">")).tobytes())
            stream.write(b"\n")


# -- TIFF --------------------------------------------------------------------------------------
def export_volume_tiff(
    volume: np.ndarray,
    path: str | os.PathLike,
    *,
    scale=None,
    translate=None,
    description: dict | None = None,
) -> Path:
    """Write one 3-D volume ``(z, y, x)`` to a TIFF stack (float32 unless integer).

    ``scale`` and ``translate`` (z, y, x, world units per voxel and world position of voxel 0)
    go into the ImageJ ``spacing``/resolution tags and into a JSON image description, so the
    stack can be placed back over the volume.
    """
    import tifffile

    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise ValueError(f"a TIFF volume must be 3-D (z, y, x), got shape {volume.shape}")
    if volume.dtype.kind == "f" or volume.dtype == np.float64:
        volume = volume.astype(np.float32)
    elif volume.dtype.kind == "b":
        volume = volume.astype(np.uint8)
    scale = _voxel_size(scale)
    info = {
        "axes": "ZYX",
        "scale": [float(s) for s in scale],
        "translate": [float(t) for t in (np.zeros(3) if translate is None else translate)],
        **(description or {}),
    }
    path = Path(path)
    with atomic_path(path) as temp:
        tifffile.imwrite(
            temp,
            volume,
            imagej=volume.dtype in (np.uint8, np.uint16, np.float32),
            resolution=(1.0 / scale[2], 1.0 / scale[1]),
            metadata={"spacing": float(scale[0]), "axes": "ZYX", "Info": _json(info)},
        )
    return path


def export_tiff(
    field: DisplacementField,
    path: str | os.PathLike,
    *,
    extra: dict | None = None,
    voxel_size=None,
) -> list[Path]:
    """Write each grid quantity of the field as its own TIFF stack.

    ``path`` names the set: ``result.tif`` writes ``result_uz.tif``, ``result_uy.tif``,
    ``result_ux.tif``, ``result_magnitude.tif``, ``result_zncc.tif``, ``result_status.tif`` and one
    file per ``extra`` array. Each stack's scale is ``step * voxel_size`` and its translate
    ``origin * voxel_size``.

    Returns
    -------
    list of Path
        The files written.
    """
    path = Path(path)
    field = unusable_as_nan(field)
    extra = _with_uncertainty(field, _check_extra(field, extra))
    vs = _voxel_size(voxel_size)
    suffix = path.suffix if path.suffix.lower() in (".tif", ".tiff") else ".tif"
    stem = path.with_suffix("") if path.suffix.lower() in (".tif", ".tiff") else path
    quantities = {
        "uz": field.u[..., 0].astype(np.float32),
        "uy": field.u[..., 1].astype(np.float32),
        "ux": field.u[..., 2].astype(np.float32),
        "magnitude": field.magnitude.astype(np.float32),
        "zncc": field.zncc,
        "status": field.status,
        **extra,
    }
    placement = {
        "scale": np.asarray(field.step) * vs,
        "translate": np.asarray(field.origin) * vs,
    }
    written = []
    for name, values in quantities.items():
        target = stem.parent / f"{stem.name}_{name.replace(' ', '_')}{suffix}"
        export_volume_tiff(
            values, target, description={"quantity": name, "units": "voxels"}, **placement
        )
        written.append(target)
    return written


# -- CSV ---------------------------------------------------------------------------------------
def export_csv(
    field: DisplacementField | ScatteredField,
    path: str | os.PathLike,
    *,
    extra: dict | None = None,
    voxel_size=None,
) -> Path:
    """Write one row per POI: position, displacement, quality and any ``extra`` arrays.

    Columns: ``z, y, x`` (voxels), ``uz, uy, ux, magnitude`` (voxels), ``zncc``, ``status``
    (code), ``status_name``, ``provenance``, ``provenance_name``, ``iterations``, then the
    ``extra`` names; with a ``voxel_size`` also the physical position and displacement
    (``z_phys``..., ``uz_phys``...). A grid field's rows follow the grid's C order and its
    ``extra`` arrays have the grid shape ``(nz, ny, nx)``; a field at scattered points
    (:class:`..engine.fields.scattered.ScatteredField`) has one row per point in its order and
    ``extra`` arrays of shape ``(N,)``.
    """
    field = unusable_as_nan(field)
    extra = _check_extra(field, extra)
    if isinstance(field, ScatteredField):
        u = field.u
    else:
        extra = _with_uncertainty(field, extra)
        u = field.displacement
    vs = None if voxel_size is None else _voxel_size(voxel_size)
    points = field.points
    columns = ["z", "y", "x", "uz", "uy", "ux", "magnitude", "zncc", "status", "status_name"]
    columns += ["provenance", "provenance_name", "iterations", *extra]
    if vs is not None:
        columns += ["z_phys", "y_phys", "x_phys", "uz_phys", "uy_phys", "ux_phys"]
    status_names = {int(s): s.label for s in Status}
    provenance_names = {int(p): p.label for p in Provenance}
    status, provenance = field.status.ravel(), field.provenance.ravel()
    zncc, iterations = field.zncc.ravel(), field.iterations.ravel()
    magnitude = np.sqrt(np.sum(u**2, axis=-1))
    flat_extra = [np.asarray(v).ravel() for v in extra.values()]
    path = Path(path)
    with atomic_path(path) as temp:
        with open(temp, "w", newline="", encoding="utf-8") as stream:
            writer = csv.writer(stream)
            writer.writerow(columns)
            for i in range(field.n_points):
                row = [*points[i], *u[i], magnitude[i], zncc[i], int(status[i])]
                row += [status_names.get(int(status[i]), str(status[i]))]
                row += [int(provenance[i]), provenance_names.get(int(provenance[i]), "")]
                row += [int(iterations[i]), *(values[i] for values in flat_extra)]
                if vs is not None:
                    row += [*(points[i] * vs), *(u[i] * vs)]
                writer.writerow(
                    [f"{v:.9g}" if isinstance(v, (float, np.floating)) else v for v in row]
                )
    return path


# -- dispatch ----------------------------------------------------------------------------------
def export_field(
    field: DisplacementField | ScatteredField,
    path: str | os.PathLike,
    *,
    extra: dict | None = None,
    voxel_size=None,
) -> list[Path]:
    """Export ``field`` in the format named by the suffix of ``path`` (see :data:`FIELD_FORMATS`;
    a field at scattered points: :func:`export_points`). ``.vtu``, ``.tsv``, ``.disp`` and
    ``.mat`` write a grid's nodes as points (:func:`export_points`; no ``extra`` arrays).

    Returns
    -------
    list of Path
        The files written (several for TIFF).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if isinstance(field, ScatteredField):
        return export_points(field, path, extra=extra, voxel_size=voxel_size)
    if suffix in (FIELD_SUFFIX, ".npz"):
        save_field(field, path)  # the native format holds the field only (no extra arrays)
        return [path]
    if suffix in (".h5", ".hdf5"):
        return [export_hdf5(field, path, extra=extra, voxel_size=voxel_size)]
    if suffix in (".vti", ".vtk"):
        return [export_vtk(field, path, extra=extra, voxel_size=voxel_size)]
    if suffix == ".csv":
        return [export_csv(field, path, extra=extra, voxel_size=voxel_size)]
    if suffix in (".tif", ".tiff"):
        return export_tiff(field, path, extra=extra, voxel_size=voxel_size)
    if suffix in _POINT_WRITERS or suffix == ".vtu":  # the grid's nodes, in another tool's format
        return export_points(field, path, voxel_size=voxel_size)
    known = ", ".join(sorted(FIELD_FORMATS))
    raise ValueError(f"{path}: unknown export format {suffix!r}; use one of {known}")


def export_points(
    field: ScatteredField | DisplacementField,
    path: str | os.PathLike,
    *,
    extra: dict | None = None,
    voxel_size=None,
) -> list[Path]:
    """Export a field at scattered points in the format named by the suffix of ``path``.

    Parameters
    ----------
    field : ScatteredField or DisplacementField
        Positions and displacements ``(z, y, x)`` in reference voxels, one entry per point (a
        grid field: one per node, as :func:`export_field` writes it for these suffixes).
    path : path
        ``.csv`` (:func:`export_csv`), ``.vtu`` (:func:`export_vtk_points`), or ``.npz``
        (pyALDVC layout), ``.tsv`` (spam), ``.disp`` (iDVC), ``.mat`` (ALDVC): the writers of
        :mod:`.formats` that ``correlate --points`` uses; see :data:`POINT_FORMATS`.
    extra : dict of ndarray (N,), optional
        Per-point arrays written as more columns; CSV only.
    voxel_size : 3 floats (z, y, x), optional
        Physical size of a voxel: physical columns in the CSV, physical coordinates in the
        ``.vtu``; the other formats stay in voxels.

    Returns
    -------
    list of Path
        The file written.

    Raises
    ------
    ValueError
        For a format that needs a regular grid (``.vti``, ``.vtk``, ``.h5``, ``.tif``), an
        unknown suffix, or ``extra`` arrays with a format other than CSV.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_FORMATS:
        known = ", ".join(POINT_FORMATS)
        if suffix in FIELD_FORMATS:
            raise ValueError(
                f"{path.name}: {FIELD_FORMATS[suffix]} needs a field on a regular grid; a "
                f"field at scattered points is written as {known}"
            )
        raise ValueError(f"{path}: unknown export format {suffix!r} for points; use one of {known}")
    if suffix == ".csv":
        return [export_csv(field, path, extra=extra, voxel_size=voxel_size)]
    if extra:
        raise ValueError(
            f"{path.name}: {POINT_FORMATS[suffix]} holds the field only; extra arrays "
            f"({', '.join(extra)}) are written to .csv"
        )
    if suffix == ".vtu":
        return [export_vtk_points(field, path, voxel_size=voxel_size)]
    from .formats import write_field

    return [write_field(field, path, _POINT_WRITERS[suffix])]
