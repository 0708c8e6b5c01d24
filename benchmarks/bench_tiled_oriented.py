"""The self-correction's oriented step in memory and out of core: RMSE, record, peak memory, CPU.

The pair is tests/tiled/test_correction.py's case made long along y (the band's plane holds y, so
each z-x section is that test's): a noisy two-phase volume (noise σ ``--noise``) under a broad
shear band (width 8, slip 6) on a rigid shift, subvolume 17, step ``--step``. Its first-order
passes stay on cubes although the field bends them, so the correction ends with the oriented step
(re-matches of the original pair under windows along the band's plane).

The first call writes the pair (``g.npy``, ``f.npy``) and the plain DVC field into ``--data``
and stops; each later call self-corrects it once (``--mode memory``: ``correct_iter`` on the
arrays; ``--mode tiled``: ``correct_tiled_iter`` on the .npy files read lazily, batches of
``--batch`` nodes, 2 workers, default warp blocks) with a thread sampling the resident memory
every 2 ms, and prints the peak RSS (and above the RSS before the call), the process's CPU
seconds (``time.process_time``: every thread) and wall seconds, the RMSE against the true field,
the oriented step's record and the largest RSS per progress report (stage and message). The field is saved as
``u_<mode>.npy`` in ``--data``; ``--compare`` prints the largest node difference of the two
modes' fields. Run each mode twice: numba compiles on a first call (its memory and seconds).

    python benchmarks/bench_tiled_oriented.py --data /tmp/oriented [--shape 48x768x48]
        [--step 6] [--noise 4] [--mode memory|tiled] [--batch 5x16x5] [--compare]
"""

from __future__ import annotations

import argparse
import os
import pickle
import threading
import time
from pathlib import Path

import numpy as np

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.correlate import correlate
from napari_dvc_correct.engine.correlation.params import CorrelationParams

PAGE = os.sysconf("SC_PAGE_SIZE")
GIB = 2**30


def rss_bytes() -> int:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * PAGE


def triple(text: str) -> tuple[int, int, int]:
    """``"ZxYxX"`` as three ints >= 1."""
    values = tuple(int(n) for n in text.lower().split("x"))
    if len(values) != 3 or min(values) < 1:
        raise argparse.ArgumentTypeError(f"give ZxYxX with whole numbers >= 1, got {text!r}")
    return values


def band(shape):
    return synthetic.shear_band(np.array(shape) / 2, width=8.0, slip=6.0, shift=(3.0, -2.0, 4.0))


def prepare(data: Path, shape, step: int, noise: float) -> None:
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.two_phase_volume(s, seed=4), shape, band(shape), margin=16
    )
    reference = synthetic.add_noise(reference, noise, seed=1).astype(np.float32)
    deformed = synthetic.add_noise(deformed, noise, seed=2).astype(np.float32)
    np.save(data / "g.npy", reference)
    np.save(data / "f.npy", deformed)
    field = correlate(reference, deformed, CorrelationParams(subvolume=17, step=step))
    with open(data / "field.pkl", "wb") as handle:
        pickle.dump(field, handle)


def run(data: Path, mode: str, batch) -> None:
    with open(data / "field.pkl", "rb") as handle:
        field = pickle.load(handle)
    shape = np.load(data / "g.npy", mmap_mode="r").shape
    peaks, stage, running = {}, ["start"], [True]

    def sample():
        while running[0]:
            value = rss_bytes()
            peaks[stage[0]] = max(peaks.get(stage[0], 0), value)
            time.sleep(0.002)

    before = rss_bytes()
    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    cpu, wall = time.process_time(), time.perf_counter()
    if mode == "tiled":
        from napari_dvc_correct.tiled.correction import correct_tiled_iter

        generator = correct_tiled_iter(
            data / "g.npy", data / "f.npy", field, max_passes=2, workers=2, batch_shape=batch
        )
    else:
        from napari_dvc_correct.engine.correction.self_correction import correct_iter

        generator = correct_iter(
            np.load(data / "g.npy"), np.load(data / "f.npy"), field, max_passes=2
        )
    try:
        while True:
            report = next(generator)
            stage[0] = f"{report.stage}: {report.message[:40]}"
    except StopIteration as stop:
        result = stop.value
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    running[0] = False
    thread.join()
    truth = band(shape)

    def rmse(f):
        error = f.displacement - truth(f.points)
        return float(np.sqrt(np.nanmean(np.sum(error**2, axis=1))))

    peak = max(peaks.values())
    print(
        f"{mode}: volume {shape}, grid {field.shape}: peak RSS {peak / GIB:.3f} GiB "
        f"({(peak - before) / GIB:.3f} above the start), CPU {cpu:.1f} s, wall {wall:.1f} s"
    )
    print(f"RMSE plain {rmse(field):.5f}, corrected {rmse(result):.5f}")
    print("oriented step:", result.metadata["correction"]["oriented"])
    largest = sorted(peaks.items(), key=lambda item: -item[1])[:6]
    print("largest RSS by stage:", [(k, round(v / GIB, 3)) for k, v in largest])
    np.save(data / f"u_{mode}.npy", result.u)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="folder for the pair")
    parser.add_argument("--shape", type=triple, default=(48, 768, 48))
    parser.add_argument("--step", type=int, default=6)
    parser.add_argument("--noise", type=float, default=4.0)
    parser.add_argument("--mode", choices=("memory", "tiled"), default="tiled")
    parser.add_argument("--batch", type=triple, default=(5, 16, 5), help="nodes per batch")
    parser.add_argument("--compare", action="store_true")
    args = parser.parse_args(argv)
    args.data.mkdir(parents=True, exist_ok=True)
    if args.compare:
        a, b = (np.load(args.data / f"u_{mode}.npy") for mode in ("memory", "tiled"))
        difference = np.abs(a - b).max(axis=-1)
        print(
            f"largest node difference {np.nanmax(difference):.3g} voxel; "
            f"{int(np.sum(difference > 1e-6))} of {difference.size} nodes above 1e-6"
        )
        return 0
    if not (args.data / "field.pkl").exists():
        prepare(args.data, args.shape, args.step, args.noise)
        print(f"pair and plain field written to {args.data}; run again for a correction")
        return 0
    run(args.data, args.mode, args.batch)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
