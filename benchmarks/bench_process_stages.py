"""The whole ``correlate`` / ``correlate --self-correct`` process stage by stage: wall, process CPU
and the main thread's CPU of each stage, the numba kernels it loads from the cache (each one's
load timed), the modules it imports.

Each run is a new process as a user starts it (``python -m napari_dvc_correct.cli correlate``
on ``bench_pipeline.py``'s 100³ ``.npy`` pairs, subvolume 21, step 8), wrapped by this file's
``--child`` mode, which times the command line's own steps: start-up (the CLI module, numba,
the subcommand's imports), reading the pair, the correlation job, the correction job (its lazy
imports and kernel loads included), the pass table, writing the field. ``OPENBLAS_NUM_THREADS``
is left as the caller has it (the CLI's own default applies).

With numba's threads, the main thread runs its share of every parallel loop and all the serial
work, so on a machine with a free core per thread the main thread's CPU is about the wall time;
on a loaded machine it is the figure that still means something (wall does not). ``2 × main −
process`` estimates the serial part of a stage run on two threads.

``--checkout DIR`` (repeatable) runs the same commands against other source trees (their
``src`` first on ``PYTHONPATH``), alternating run by run, for A/B comparisons on a shared
machine; ``--save-fields DIR`` keeps every checkout's field files (compare them bit for bit).

    python benchmarks/bench_process_stages.py [--cases "shear band" ...] [--threads 2 1]
        [--repeat 3] [--checkout /path/a --checkout /path/b] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODES = {"plain": [], "corrected": ["--self-correct"]}


def _child(argv: list[str]) -> None:
    """Run the CLI on ``argv`` in this process; print one JSON line of stage timings last."""
    clock = time.perf_counter, time.process_time, time.thread_time
    marks: list[tuple] = []

    def mark(name: str) -> None:
        marks.append((name, *(c() for c in clock)))

    mark("start")
    import napari_dvc_correct.cli as cli  # first, as the command line (it sets the BLAS threads)

    mark("start-up: the CLI module")
    import numba  # noqa: F401
    from numba.core import dispatcher

    mark("start-up: numba, numpy")
    loads = []
    compile_overload = dispatcher.Dispatcher.compile

    def timed_compile(self, sig):
        start = [c() for c in clock]
        result = compile_overload(self, sig)
        name = f"{self.py_func.__module__.rsplit('.', 1)[-1]}.{self.py_func.__name__}"
        loads.append((name, *(c() - s for c, s in zip(clock, start, strict=True))))
        return result

    dispatcher.Dispatcher.compile = timed_compile
    from napari_dvc_correct.commands import _field_formats, correct, correlate
    from napari_dvc_correct.jobs import volumes

    mark("start-up: the subcommand's modules")

    def wrap(module, name: str, label: str) -> None:
        function = getattr(module, name)

        def timed(*args, **kwargs):
            mark(f"before {label}")
            result = function(*args, **kwargs)
            mark(label)
            return result

        setattr(module, name, timed)

    wrap(volumes, "load_volume", "reading the pair")
    wrap(correlate, "drive", "correlation job")
    wrap(correct, "_correct", "correction job")
    wrap(correct, "pass_table", "pass table")
    wrap(_field_formats, "write_output_field", "writing the field")
    with open(os.devnull, "w") as quiet:
        stdout, sys.stdout = sys.stdout, quiet
        try:
            cli.main(argv)
        finally:
            sys.stdout = stdout
    mark("end")
    stages: dict[str, list[float]] = {}
    for previous, current in zip(marks, marks[1:]):
        label = current[0]
        if label.startswith("before "):  # what ran between two timed steps
            label = "checks, imports and set-up before " + label[len("before ") :]
        total = stages.setdefault(label, [0.0, 0.0, 0.0])
        for k in range(3):
            total[k] += current[k + 1] - previous[k + 1]
    print(
        json.dumps(
            {
                "stages": stages,
                "total": [marks[-1][k] - marks[0][k] for k in (1, 2, 3)],
                "kernels": loads,
                "modules": len(sys.modules),
            }
        )
    )


def _pair(folder: Path, case: str, size: int) -> tuple[Path, Path]:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import numpy as np
    from bench_pipeline import make_case

    reference, deformed, _ = make_case(case, size)
    paths = (
        folder / f"{case.replace(' ', '_')}_ref.npy",
        folder / f"{case.replace(' ', '_')}_def.npy",
    )
    np.save(paths[0], reference)
    np.save(paths[1], deformed)
    return paths


def _run(checkout: Path | None, threads: int, pair, mode: str, out: Path) -> dict:
    env = dict(os.environ, NUMBA_NUM_THREADS=str(threads))
    if checkout is not None:
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (str(checkout / "src"), env.get("PYTHONPATH", "")) if p
        )
    argv = ["correlate", str(pair[0]), str(pair[1]), "--subvolume", "21", "--step", "8"]
    argv += ["--quiet", *MODES[mode], "--out", str(out)]
    done = subprocess.run(
        [sys.executable, __file__, "--child", *argv], env=env, capture_output=True, text=True
    )
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def _best(runs: list[dict]) -> dict:
    """Per stage the smallest wall, process CPU and main-thread CPU over the runs."""
    stages = {}
    for run in runs:
        for label, values in run["stages"].items():
            best = stages.setdefault(label, list(values))
            stages[label] = [min(a, b) for a, b in zip(best, values, strict=True)]
    kernels: dict[str, list[float]] = {}
    for run in runs:
        for name, *values in run["kernels"]:
            best = kernels.setdefault(name, list(values))
            kernels[name] = [min(a, b) for a, b in zip(best, values, strict=True)]
    return {
        "stages": stages,
        "kernels": kernels,
        "wall": [r["total"][0] for r in runs],
        "cpu": [r["total"][1] for r in runs],
        "main": [r["total"][2] for r in runs],
        "modules": runs[0]["modules"],
    }


def _print(label: str, best: dict) -> None:
    print(
        f"{label}: wall {min(best['wall']):.2f} s, CPU {min(best['cpu']):.2f} s, main thread "
        f"{min(best['main']):.2f} s (best of {len(best['wall'])}); {best['modules']} modules, "
        f"{len(best['kernels'])} kernels loaded ({sum(v[1] for v in best['kernels'].values()):.3f}"
        " s CPU)",
        flush=True,
    )
    for stage, (wall, cpu, main) in best["stages"].items():
        if max(wall, cpu) >= 0.0005:
            print(f"    {stage:55s} wall {wall:6.3f}  CPU {cpu:6.3f}  main thread {main:6.3f}")


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        _child(sys.argv[2:])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=["shear band"])
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--threads", nargs="*", type=int, default=[2, 1])
    parser.add_argument("--modes", nargs="*", default=list(MODES), choices=list(MODES))
    parser.add_argument("--repeat", type=int, default=3, help="timed runs after a warm-up run")
    parser.add_argument("--checkout", type=Path, action="append", default=None)
    parser.add_argument("--kernels", action="store_true", help="print every kernel's load")
    parser.add_argument("--save-fields", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    checkouts = args.checkout or [None]
    results = []
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        for case in args.cases:
            pair = _pair(folder, case, args.size)
            runs: dict[tuple, list] = {}
            for repeat in range(args.repeat + 1):  # the first round warms numba's cache
                for threads in args.threads:
                    for mode in args.modes:
                        for k, checkout in enumerate(checkouts):
                            out = folder / f"{k}_{threads}_{mode}.npz"
                            run = _run(checkout, threads, pair, mode, out)
                            if repeat:
                                runs.setdefault((threads, mode, k), []).append(run)
                            if args.save_fields is not None:
                                args.save_fields.mkdir(parents=True, exist_ok=True)
                                target = args.save_fields / f"{case}_{k}_{threads}_{mode}.npz"
                                target.write_bytes(out.read_bytes())
            print(f"== {case}, load {os.getloadavg()[0]:.1f} at the end", flush=True)
            for (threads, mode, k), case_runs in runs.items():
                best = _best(case_runs)
                name = "this checkout" if checkouts[k] is None else str(checkouts[k])
                _print(f"{case}, {mode}, {threads} thread(s), {name}", best)
                if args.kernels:
                    for kernel, (wall, cpu, _) in best["kernels"].items():
                        print(
                            f"        {kernel:50s} {1e3 * cpu:6.1f} ms CPU {1e3 * wall:6.1f} ms wall"
                        )
                results.append(
                    {"case": case, "mode": mode, "threads": threads, "checkout": name, **best}
                )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
