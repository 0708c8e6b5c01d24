"""pyALDVC (``.npz``) and ALDVC (MATLAB ``.mat``) result files.

Conventions, read from pyALDVC's sources: ``src/al_dvc/core/data_structures.py`` (layout
contracts and status codes), ``src/al_dvc/export/export_npz.py`` (the ``.npz`` writer),
``src/al_dvc/export/export_mat.py`` (pyALDVC's ``.mat`` writer) and
``src/al_dvc/io/matlab_results.py`` (pyALDVC's reader of the MATLAB ALDVC ``results_*.mat``):

* volumes are ``vol[z, y, x]``; node ``coordinates`` are ``(N, 3)`` with columns **x, y, z**
  (voxels, **0-based** in pyALDVC); nodes are in C order of ``grid_shape = (nz, ny, nx)``
  (``n = iz*ny*nx + iy*nx + ix``);
* displacement ``U_k`` ``(N, 3)`` = ``[u, v, w]`` = along x, y, z, voxels, for frame pair ``k``
  (1-based suffix, ``U_1`` for the first pair); ``F_k`` ``(N, 3, 3)`` is the *displacement*
  gradient ``F[n, i, j] = du_i/dx_j`` in x, y, z; ``zncc_k``, ``status_k`` per node;
* status codes: 0 converged, 1 max_iter, 2 out_of_bounds, 3 invalid_subset, 4 singular, 5 nan,
  6 skipped (masked out before the solver), 7 stalled;
* MATLAB ALDVC ``.mat``: ``DVCmesh.coordinatesFEM`` ``(N, 3)`` = ``[x, y, z]`` **1-based**;
  ``ResultDisp{k}.U`` interleaved ``(3N,)`` = ``[u1 v1 w1 u2 ...]``; ``ResultDefGrad{k}.F``
  interleaved ``(9N,)`` per node ``[F11 F21 F31 F12 F22 F32 F13 F23 F33]`` (column-major,
  ``Fij = du_i/dx_j``); ``DVCpara.winsize`` / ``winstepsize``;
* pyALDVC's own ``.mat`` export writes ``coordinatesFEM`` at the top level unshifted (0-based,
  only the element indices become 1-based) and ``ResultDisp`` as a cell of ``(N, 3)`` arrays.

Mapping of status: 0 → ``CONVERGED``, 1 → ``MAX_ITERATIONS``, 2 → ``OUT_OF_BOUNDS``, 3 and 6 →
``MASKED``, 4 → ``SINGULAR``, 5 and 7 → ``DIVERGED``. We write the pyALDVC ``.npz`` layout and the
MATLAB ALDVC ``.mat`` layout (the one pyALDVC's ``load_matlab_results`` reads); both also carry
our exact status and provenance codes (``ndc_status_k``, ``ndc_provenance_k``).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from ...engine.fields.field import Provenance, Status
from ...engine.fields.scattered import ScatteredField, regular_grid_of
from ..atomic import atomic_path
from ..sizes import check_npz_sizes
from ._common import as_scattered, flip_tensors, flip_vectors

_FROM_ALDVC = {
    0: Status.CONVERGED,
    1: Status.MAX_ITERATIONS,
    2: Status.OUT_OF_BOUNDS,
    3: Status.MASKED,
    4: Status.SINGULAR,
    5: Status.DIVERGED,
    6: Status.MASKED,
    7: Status.DIVERGED,
}
_TO_ALDVC = {
    Status.CONVERGED: 0,
    Status.MAX_ITERATIONS: 1,
    Status.OUT_OF_BOUNDS: 2,
    Status.SINGULAR: 4,
    Status.DIVERGED: 7,
    Status.MASKED: 6,
    Status.LOW_TEXTURE: 3,
    Status.NOT_COMPUTED: 6,
}


def is_result_mat(path) -> bool:
    """Whether a ``.mat`` file holds an ALDVC result (``DVCmesh`` or ``coordinatesFEM``)."""
    from scipy.io import whosmat
    from scipy.io.matlab import MatReadError

    try:
        names = {entry[0] for entry in whosmat(str(path))}
    except (OSError, ValueError, NotImplementedError, TypeError, MatReadError):
        return False  # an empty or truncated file too
    return "DVCmesh" in names or "coordinatesFEM" in names


def status_from_aldvc(codes) -> np.ndarray:
    codes = np.asarray(codes).astype(np.int64).reshape(-1)
    out = np.full(codes.shape, int(Status.NOT_COMPUTED), np.uint8)
    for theirs, ours in _FROM_ALDVC.items():
        out[codes == theirs] = int(ours)
    return out


def status_to_aldvc(status) -> np.ndarray:
    status = np.asarray(status)
    out = np.full(status.shape, 5, np.int8)  # anything else failed: "nan"
    for ours, theirs in _TO_ALDVC.items():
        out[status == int(ours)] = theirs
    return out


def _field(points_xyz, u_xyz, grad_xyz, zncc, status, provenance, params, source) -> ScatteredField:
    n = len(points_xyz)
    provenance_default = np.where(
        np.isin(status, [Status.CONVERGED, Status.MAX_ITERATIONS]),
        int(Provenance.MEASURED),
        int(Provenance.NOT_COMPUTED),
    )
    return ScatteredField(
        points=flip_vectors(points_xyz),
        u=flip_vectors(np.asarray(u_xyz, np.float64).reshape(n, 3)),
        zncc=np.full(n, np.nan) if zncc is None else np.asarray(zncc, np.float64).reshape(n),
        status=status,
        provenance=provenance_default if provenance is None else provenance,
        gradient=None if grad_xyz is None else flip_tensors(np.reshape(grad_xyz, (n, 3, 3))),
        params=params,
        metadata={"source": source},
    )


def _params(winsize, winstepsize) -> dict:
    params = {}
    if winsize is not None:
        size = int(np.max(np.asarray(winsize).reshape(-1)))
        params["subvolume"] = size + 1 if size % 2 == 0 else size  # ours are odd (2M + 1)
    if winstepsize is not None:
        params["step"] = int(np.max(np.asarray(winstepsize).reshape(-1)))
    return params


def read(path: str | os.PathLike, frame: int = 1, accumulated: bool = False) -> ScatteredField:
    """Read frame pair ``frame`` (1-based, as in ``U_1``) of a pyALDVC ``.npz`` or ALDVC ``.mat``.

    ``accumulated`` reads the displacement from frame 0 (``U_accum_k``) instead of the pair's.
    ``params`` get the subvolume (``winsize``, made odd) and step when the file has them.
    """
    path = Path(path)
    if path.suffix.lower() == ".mat":
        return _read_mat(path, frame)
    check_npz_sizes(path)  # headers first: nothing inflated that does not fit in memory
    with np.load(path, allow_pickle=False) as data:
        pairs = sorted(int(name[2:]) for name in data.files if re.fullmatch(r"U_[0-9]+", name))
        if "coordinates" in data and pairs:
            _check_frame(path, frame, len(pairs), pairs)
        if "coordinates" not in data or f"U_{frame}" not in data:
            raise ValueError(
                f"{path}: not a pyALDVC result (needs 'coordinates' and 'U_{frame}'; "
                f"has {', '.join(sorted(data.files)[:12])})"
            )
        key = f"U_accum_{frame}" if accumulated and f"U_accum_{frame}" in data else f"U_{frame}"
        n = len(data["coordinates"])
        status = (
            status_from_aldvc(data[f"status_{frame}"])
            if f"status_{frame}" in data
            else np.full(n, int(Status.CONVERGED), np.uint8)
        )
        provenance = None
        if f"ndc_status_{frame}" in data:
            status = data[f"ndc_status_{frame}"].astype(np.uint8)
            provenance = data[f"ndc_provenance_{frame}"].astype(np.uint8)
        params = {}
        if "para_json" in data:
            para = json.loads(str(data["para_json"]))
            params = _params(para.get("winsize"), para.get("winstepsize"))
        return _field(
            data["coordinates"],
            data[key],
            data[f"F_{frame}"] if f"F_{frame}" in data else None,
            data[f"zncc_{frame}"] if f"zncc_{frame}" in data else None,
            status,
            provenance,
            params,
            {
                "format": "aldvc",
                "path": str(path),
                "frame": frame,
                "frames": len(pairs),
                "displacement": key,
            },
        )


def _check_frame(path, frame: int, count: int, labels=None) -> None:
    """Refuse a frame pair the file does not hold (0 or a negative number read the last one
    of a .mat, a number past the end gave 'IndexError')."""
    labels = list(range(1, count + 1)) if labels is None else list(labels)
    if frame not in labels:
        raise ValueError(
            f"{path}: frame pair {frame} asked, but the file holds {count} frame pair(s) "
            f"({', '.join(map(str, labels[:8]))}{'...' if count > 8 else ''}): choose "
            "--frame-pair among them (1 = the first)"
        )


def _items(value) -> list:
    if isinstance(value, np.ndarray) and value.dtype == object:
        return list(value.ravel())
    return [value]


def _read_mat(path: Path, frame: int) -> ScatteredField:
    from scipy.io import loadmat

    m = loadmat(str(path), squeeze_me=True, struct_as_record=False)
    k = frame - 1
    source = {"format": "aldvc", "path": str(path), "frame": frame}
    if "DVCmesh" in m:  # MATLAB ALDVC: 1-based coordinates, interleaved vectors
        coords = np.asarray(m["DVCmesh"].coordinatesFEM, np.float64).reshape(-1, 3) - 1.0
        disp = _items(m["ResultDisp"])
        _check_frame(path, frame, len(disp))
        source["frames"] = len(disp)
        u = np.asarray(disp[k].U, np.float64).reshape(-1, 3)
        grad = None
        if "ResultDefGrad" in m and k < len(_items(m["ResultDefGrad"])):
            entry = _items(m["ResultDefGrad"])[k]
            if hasattr(entry, "F"):
                grad = np.transpose(np.asarray(entry.F, np.float64).reshape(-1, 3, 3), (0, 2, 1))
        para = m.get("DVCpara")
        params = _params(getattr(para, "winsize", None), getattr(para, "winstepsize", None))
        zncc = None
        n = len(coords)
        status = np.full(n, int(Status.CONVERGED), np.uint8)
        provenance = None
        extras = m.get("ndcQuality")
        if extras is not None:
            entry = _items(extras)[k]
            zncc = np.asarray(entry.zncc, np.float64).reshape(-1)
            status = np.asarray(entry.status).astype(np.uint8).reshape(-1)
            provenance = np.asarray(entry.provenance).astype(np.uint8).reshape(-1)
        source["layout"] = "ALDVC (MATLAB)"
        return _field(coords, u, grad, zncc, status, provenance, params, source)
    if "coordinatesFEM" in m:  # pyALDVC's .mat export: 0-based, (N, 3) per frame
        coords = np.asarray(m["coordinatesFEM"], np.float64).reshape(-1, 3)
        disp = _items(m["ResultDisp"])
        _check_frame(path, frame, len(disp))
        source["frames"] = len(disp)
        u = np.asarray(disp[k], np.float64).reshape(-1, 3)
        grad = None
        if "ResultDefGrad" in m:
            grad = np.asarray(_items(m["ResultDefGrad"])[k], np.float64).reshape(-1, 3, 3)
        zncc = None
        if "ResultZNCC" in m:
            zncc = np.asarray(_items(m["ResultZNCC"])[k], np.float64).reshape(-1)
            zncc = zncc if zncc.size == len(coords) else None
        params = _params(m.get("winsize"), m.get("winstepsize"))
        status = np.full(len(coords), int(Status.CONVERGED), np.uint8)
        source["layout"] = "pyALDVC .mat export"
        return _field(coords, u, grad, zncc, status, None, params, source)
    raise ValueError(f"{path}: not an ALDVC result (no DVCmesh or coordinatesFEM variable)")


def write(field, path: str | os.PathLike, subvolume: int | None = None) -> None:
    """Write a field as a pyALDVC ``.npz`` (suffix ``.npz``) or MATLAB ALDVC ``.mat`` (``.mat``).

    ``subvolume`` (voxels) is stored as ``winsize`` (default: the field's ``params``).
    """
    path = Path(path)
    field = as_scattered(field)
    n = field.n_points
    coords = flip_vectors(field.points)
    u = flip_vectors(field.u)
    grad = None if field.gradient is None else flip_tensors(field.gradient)
    winsize = subvolume or field.params.get("subvolume")
    winstep = field.params.get("step")
    grid = regular_grid_of(field.points)
    if path.suffix.lower() == ".mat":
        _write_mat(field, path, coords, u, grad, winsize, winstep)
        return
    arrays = {
        "coordinates": coords,
        "U_1": u,
        "F_1": np.zeros((n, 3, 3)) if grad is None else grad,
        "zncc_1": field.zncc.astype(np.float64),
        "status_1": status_to_aldvc(field.status),
        "ndc_status_1": field.status,
        "ndc_provenance_1": field.provenance,
        "para_json": np.array(
            json.dumps(
                {
                    "winsize": None if winsize is None else [int(winsize)] * 3,
                    "winstepsize": None if winstep is None else [int(winstep)] * 3,
                }
            )
        ),
    }
    if grid is not None and np.array_equal(np.sort(grid[3]), grid[3]):
        origin, step, shape, _ = grid
        arrays["grid_shape"] = np.asarray(shape, np.int64)
        axes = [origin[a] + step[a] * np.arange(shape[a]) for a in range(3)]
        arrays["z0"], arrays["y0"], arrays["x0"] = axes
        arrays["spacing"] = np.asarray(step[::-1], np.float64)
    with atomic_path(path) as temp:
        np.savez_compressed(temp, **arrays)


def _write_mat(field, path, coords, u, grad, winsize, winstep) -> None:
    from scipy.io import savemat

    n = field.n_points
    grad = np.zeros((n, 3, 3)) if grad is None else grad
    disp = np.empty((1,), dtype=object)
    disp[0] = {"U": u.reshape(-1, 1)}
    defgrad = np.empty((1,), dtype=object)
    defgrad[0] = {"F": np.transpose(grad, (0, 2, 1)).reshape(-1, 1)}
    quality = np.empty((1,), dtype=object)
    quality[0] = {
        "zncc": field.zncc.astype(np.float64),
        "status": field.status.astype(np.float64),
        "provenance": field.provenance.astype(np.float64),
    }
    para = {}
    if winsize is not None:
        para["winsize"] = np.full(3, float(winsize))
    if winstep is not None:
        para["winstepsize"] = np.full(3, float(winstep))
    data = {
        "DVCpara": para,
        "DVCmesh": {"coordinatesFEM": coords + 1.0, "elementsFEM": np.zeros((0, 8))},
        "ResultDisp": disp,
        "ResultDefGrad": defgrad,
        "ndcQuality": quality,
    }
    with atomic_path(path) as temp:
        savemat(str(temp), data, do_compression=True)
