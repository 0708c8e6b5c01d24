"""The ``.npz`` field file: the native, versioned format of :class:`DisplacementField`.

Besides the grid arrays the file holds flat ``points`` (N, 3) and ``displacement`` (N, 3) in
(z, y, x) reference voxels, so any tool can read it with ``numpy.load`` alone. The flat
``displacement`` is NaN wherever the node's status is not good (failed, low ZNCC, masked,
replaced: :attr:`DisplacementField.measured_displacement`); the grid ``u`` keeps the values that
cleaning filled in, with their ``provenance``. ``uncertainty`` (grid, voxels) is optional: files
without it load with ``uncertainty=None``.
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np

from ..engine.fields.field import DisplacementField, Provenance, Status
from .atomic import atomic_path
from .sizes import check_npz_sizes

FORMAT_NAME = "napari-dvc-correct field"
FORMAT_VERSION = 1
#: Suffix of a field file that only this plugin claims in napari (the same contents as ``.npz``;
#: napari's own reader claims every ``*.npz``, so a ``.npz`` field file needs a reader choice).
FIELD_SUFFIX = ".dvcfield"


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (set, tuple)):
        return list(value)
    return str(value)


def save_field(field: DisplacementField, path: str | os.PathLike) -> None:
    """Write ``field`` to ``path`` (``.dvcfield`` or ``.npz``, the same contents) atomically: a failed write leaves ``path`` as it was."""
    arrays = {
        "format": np.array(FORMAT_NAME),
        "format_version": np.array(FORMAT_VERSION),
        "origin": np.asarray(field.origin, np.float64),
        "step": np.asarray(field.step, np.float64),
        "u": field.u,
        "zncc": field.zncc,
        "status": field.status,
        "iterations": field.iterations,
        "provenance": field.provenance,
        "points": field.points,
        "displacement": field.measured_displacement,
        "status_names": np.array([s.name for s in Status]),
        "provenance_names": np.array([p.name for p in Provenance]),
        "params_json": np.array(json.dumps(field.params, default=_json_default)),
        "metadata_json": np.array(json.dumps(field.metadata, default=_json_default)),
    }
    if field.gradient is not None:
        arrays["gradient"] = field.gradient
    if field.uncertainty is not None:
        arrays["uncertainty"] = field.uncertainty
    with atomic_path(path) as temp:
        with open(temp, "wb") as stream:
            np.savez_compressed(stream, **arrays)


#: The arrays :func:`load_field` reads (any other member of the file is never inflated).
FIELD_KEYS = (
    "format", "format_version", "origin", "step", "u", "zncc", "status", "iterations",
    "provenance", "gradient", "uncertainty", "params_json", "metadata_json",
)  # fmt: skip


def check_member_shapes(path, members) -> None:
    """Refuse, from the headers alone, arrays whose shapes do not fit one grid of ``u``."""
    u = members.get("u")
    if u is None:
        raise ValueError(f"{path} is a broken field file: missing u")
    if len(u.shape) != 4 or u.shape[3] != 3:
        raise ValueError(
            f"{path} is a broken field file: u has shape {u.shape}, not (nz, ny, nx, 3)"
        )
    grid = u.shape[:3]
    expected = {"zncc": grid, "status": grid, "iterations": grid, "provenance": grid,
                "gradient": (*grid, 3, 3), "uncertainty": (*grid, 3), "origin": (3,),
                "step": (3,), "format_version": (), "params_json": (), "metadata_json": ()}  # fmt: skip
    for name, shape in expected.items():
        if name in members and members[name].shape != shape:
            raise ValueError(
                f"{path} is a broken field file: {name} has shape {members[name].shape}, "
                f"not {shape} (the grid of u is {grid})"
            )


def load_field(path: str | os.PathLike) -> DisplacementField:
    """Read a field file written by :func:`save_field`.

    Raises
    ------
    ValueError
        If the file is not a field file, is broken, or was written by a newer format version.
    FileNotFoundError
        If ``path`` does not exist.
    """
    if not os.path.exists(path):
        raise FileNotFoundError(f"field file not found: {path}")
    try:  # headers first: the arrays read are sized before anything is inflated
        members = check_npz_sizes(path, FIELD_KEYS)
    except ValueError as error:
        raise ValueError(f"{path} is not a readable .npz field file ({error})") from error
    marker = members.get("format")
    if marker is None or marker.shape != () or marker.nbytes > 1024:
        raise ValueError(f"{path} is not a napari-dvc-correct field file (no format marker)")
    check_member_shapes(path, members)
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["format"]) != FORMAT_NAME:
                raise ValueError(
                    f"{path} is not a napari-dvc-correct field file (no format marker)"
                )
            contents = {key: data[key] for key in FIELD_KEYS if key in members}
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise ValueError(f"{path} is not a readable .npz field file ({error})") from error
    try:
        version = int(contents.get("format_version", -1))
    except (TypeError, ValueError):
        raise ValueError(
            f"{path} has a non-numeric field format version "
            f"{str(contents['format_version'])[:20]!r}: the file is broken"
        ) from None
    if version > FORMAT_VERSION:
        raise ValueError(
            f"{path} has field format version {version}, newer than this version of "
            f"napari-dvc-correct understands ({FORMAT_VERSION}): upgrade the package"
        )
    if version < 1:
        raise ValueError(f"{path} has an invalid field format version {version}")
    missing = [k for k in ("origin", "step", "u") if k not in contents]
    if missing:
        raise ValueError(f"{path} is a broken field file: missing {', '.join(missing)}")
    try:
        return DisplacementField(
            origin=contents["origin"],
            step=contents["step"],
            u=contents["u"],
            zncc=contents.get("zncc"),
            status=contents.get("status"),
            iterations=contents.get("iterations"),
            provenance=contents.get("provenance"),
            gradient=contents.get("gradient"),
            uncertainty=contents.get("uncertainty"),
            params=json.loads(str(contents.get("params_json", "{}"))),
            metadata=json.loads(str(contents.get("metadata_json", "{}"))),
        )
    except (ValueError, TypeError) as error:
        raise ValueError(f"{path} is a broken field file: {error}") from error
