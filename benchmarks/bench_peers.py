"""Side by side with pyALDVC (``al-dvc`` on PyPI): its plain field against our plain and corrected ones.

The same 100³ cases as ``bench_pipeline.py`` (subvolume 21, step 8) and the real 200³ crops of
``bench_real.py`` (``../shared/data/real-rock``, the user's specimen mask), one table:

* **pyALDVC**: ``run_aldvc`` in this process, warm (a first run compiles or loads its kernels and
  is not counted; the best of ``--repeat`` after it), with its defaults (pyramid initial guess,
  local IC-GN, ADMM global step on, L-curve beta), strain off (``compute_strain=False``): its plain
  field. Its subsets are ``winsize + 1`` voxels wide (``winsize`` must be even, half-width
  ``winsize // 2``), so ``winsize=20`` is our 21³ subvolume; node spacing 8. On the real crops it
  gets the same specimen mask as ours.
* **ours, synthetic cases**: ``napari-dvc-correct correlate`` and ``correlate --self-correct`` as a
  user runs them (a new process each, start-up and file reading included, numba cache warm; best
  of ``--repeat`` after a first run), exactly as ``bench_pipeline.py`` does.
* **ours, real crops**: ``correlate`` and ``correct`` in this process, as ``bench_real.py`` runs
  them (the corrected time is plain + correction), warm (an untimed run on a 100³ corner first).
* **accuracy**: the RMSE against the true field at every node that has a value (synthetic cases);
  on the real crops bench_real's independent judge: the mean gray residual of the field as a user
  gets it, over the zero field's.

pyALDVC is an optional benchmark dependency (``pip install -e ".[bench]"``): without it only our
columns are printed, with a message saying so.

    python benchmarks/bench_peers.py [--repeat 2] [--cases translation "shear band" ...]
                                     [--crops lower upper] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_pipeline  # noqa: E402
import bench_real  # noqa: E402

from napari_dvc_correct.engine import synthetic  # noqa: E402
from napari_dvc_correct.engine.correction.self_correction import correct  # noqa: E402
from napari_dvc_correct.engine.correlation.correlate import correlate  # noqa: E402
from napari_dvc_correct.engine.correlation.params import CorrelationParams  # noqa: E402
from napari_dvc_correct.engine.fields.field import DisplacementField, Status  # noqa: E402

SUBVOLUME = 21
STEP = 8


def _aldvc():
    """The ``al_dvc`` module, or None with the reason printed."""
    try:
        import al_dvc
    except ImportError:
        print(
            "pyALDVC (al-dvc) is not installed: its columns are skipped "
            '(pip install -e ".[bench]" to compare)',
            flush=True,
        )
        return None
    return al_dvc


_WARMED: set = set()


def aldvc_field(al_dvc, reference, deformed, mask=None, repeat: int = 2):
    """pyALDVC's plain field as a :class:`DisplacementField` on its own node grid, and its best
    warm time in seconds (the first call with or without a mask runs once more, untimed, on a
    100³ corner of the pair: it compiles or loads its kernels)."""
    para = al_dvc.dvcpara_default(winsize=SUBVOLUME - 1, winstepsize=STEP, verbose=False)

    def run(reference, deformed, mask):
        masks = None if mask is None else [mask, mask]
        return al_dvc.run_aldvc(para, [reference, deformed], masks=masks, compute_strain=False)

    if (mask is None) not in _WARMED:
        corner = tuple(slice(0, min(100, n)) for n in reference.shape)
        run(reference[corner], deformed[corner], None if mask is None else mask[corner])
        _WARMED.add(mask is None)
    seconds = []
    for _ in range(repeat):
        started = time.perf_counter()
        result = run(reference, deformed, mask)
        seconds.append(time.perf_counter() - started)
    mesh = result.dvc_mesh
    frame = result.result_disp[0]
    axes_zyx = (mesh.z0, mesh.y0, mesh.x0)
    origin = tuple(float(a[0]) for a in axes_zyx)
    step = tuple(float(a[1] - a[0]) for a in axes_zyx)
    shape = tuple(len(a) for a in axes_zyx)
    xyz = np.asarray(mesh.coordinates, np.float64)
    index = np.rint((xyz[:, ::-1] - np.asarray(origin)) / np.asarray(step)).astype(int)
    u = np.full((*shape, 3), np.nan)
    u[tuple(index.T)] = np.asarray(frame.U, np.float64)[:, ::-1]  # (x, y, z) -> (z, y, x)
    status = np.where(np.all(np.isfinite(u), axis=-1), int(Status.CONVERGED), int(Status.DIVERGED))
    if mesh.node_valid.size:
        valid = np.zeros(shape, bool)
        valid[tuple(index.T)] = mesh.node_valid
        status[~valid] = int(Status.MASKED)
    field = DisplacementField(origin=origin, step=step, u=u, status=status.astype(np.uint8))
    return field, min(seconds)


def _rmse(field: DisplacementField, truth) -> float:
    expected = synthetic.sample_displacement(truth, field.points.reshape(*field.shape, 3))
    error = np.linalg.norm(field.u - expected, axis=-1)
    return float(np.sqrt(np.mean(error[np.isfinite(error)] ** 2)))


def synthetic_row(al_dvc, name: str, size: int, repeat: int) -> dict:
    ours = bench_pipeline.run_case(name, size, repeat + 1)
    row = {
        "case": name,
        "ours_plain_s": ours["plain"]["warm_s"],
        "ours_corrected_s": ours["self-corrected"]["warm_s"],
        "ours_plain_accuracy": ours["plain"]["rmse_voxel"],
        "ours_corrected_accuracy": ours["self-corrected"]["rmse_voxel"],
        "accuracy": "RMSE (voxel)",
    }
    if al_dvc is not None:
        reference, deformed, truth = bench_pipeline.make_case(name, size)
        field, seconds = aldvc_field(al_dvc, reference, deformed, repeat=repeat)
        row["aldvc_s"] = seconds
        row["aldvc_accuracy"] = _rmse(field, truth)
    return row


def real_row(al_dvc, name: str, repeat: int) -> dict | None:
    crop = bench_real.load_crop(name)
    if crop is None:
        return None
    reference, deformed = crop
    mask = bench_real.specimen_of(reference)
    params = CorrelationParams(subvolume=SUBVOLUME, step=STEP)
    # warm: our kernels (with a mask) loaded or compiled on a 100³ corner, untimed
    corner = tuple(slice(0, min(100, n)) for n in reference.shape)
    warm = correlate(reference[corner], deformed[corner], params, mask=mask[corner])
    correct(reference[corner], deformed[corner], warm, params, mask=mask[corner])
    plain_s, correction_s = [], []
    for _ in range(repeat):
        started = time.perf_counter()
        plain = correlate(reference, deformed, params, mask=mask)
        plain_s.append(time.perf_counter() - started)
        started = time.perf_counter()
        corrected = correct(reference, deformed, plain, params, mask=mask)
        correction_s.append(time.perf_counter() - started)
    zero = plain.copy()
    zero.u[:] = 0.0
    zero.status[:] = int(Status.CONVERGED)
    zero_residual = bench_real.judge_residual(reference, deformed, zero)[0]
    judged = lambda field: bench_real.judge_residual(reference, deformed, field)[0] / zero_residual  # noqa: E731
    row = {
        "case": f"real rock, {name} crop",
        "ours_plain_s": min(plain_s),
        "ours_corrected_s": min(plain_s) + min(correction_s),
        "ours_plain_accuracy": judged(plain),
        "ours_corrected_accuracy": judged(corrected),
        "accuracy": "residual / zero field's",
    }
    if al_dvc is not None:
        field, seconds = aldvc_field(al_dvc, reference, deformed, mask=mask, repeat=repeat)
        row["aldvc_s"] = seconds
        row["aldvc_accuracy"] = judged(field)
    return row


def print_table(rows: list[dict]) -> None:
    print(
        "\n| case | pyALDVC plain | our `correlate` | our `correlate --self-correct` | "
        "corrected / plain | accuracy: pyALDVC / ours plain / ours corrected |"
    )
    print("|---|---|---|---|---|---|")
    for row in rows:
        peer = row.get("aldvc_s")
        versus = lambda s, peer=peer: f" ({s / peer:.2f}× pyALDVC)" if peer else ""  # noqa: E731
        peer_s = f"{peer:.2f} s" if peer else "—"
        peer_accuracy = f"{row['aldvc_accuracy']:.4f}" if peer else "—"
        print(
            f"| {row['case']} | {peer_s} | {row['ours_plain_s']:.2f} s{versus(row['ours_plain_s'])} | "
            f"{row['ours_corrected_s']:.2f} s{versus(row['ours_corrected_s'])} | "
            f"{row['ours_corrected_s'] / row['ours_plain_s']:.2f}× | {row['accuracy']}: "
            f"{peer_accuracy} / {row['ours_plain_accuracy']:.4f} / "
            f"{row['ours_corrected_accuracy']:.4f} |",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=2, help="timed runs after a warm-up run")
    parser.add_argument("--cases", nargs="*", default=["translation", "shear band", "noisy band"])
    parser.add_argument("--crops", nargs="*", default=["lower", "upper"])
    parser.add_argument("--real-repeat", type=int, default=1, help="timed runs on the real crops")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    al_dvc = _aldvc()
    rows = []
    for name in args.cases:
        rows.append(synthetic_row(al_dvc, name, args.size, args.repeat))
        print_table(rows[-1:])
    for name in args.crops:
        row = real_row(al_dvc, name, args.real_repeat)
        if row is not None:
            rows.append(row)
            print_table(rows[-1:])
    print_table(rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
