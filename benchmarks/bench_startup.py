"""Start-up of the command line, measured as a user sees it: new processes, wall-clock time.

* ``--help``: ``python -m napari_dvc_correct.cli --help`` (argparse only: no numba, no scipy);
* ``import engine``: ``python -c "import napari_dvc_correct.engine.correlation.correlate"`` (numpy, numba,
  scipy.fft/ndimage and the engine's modules; no kernel loaded yet);
* ``correlate``: ``napari-dvc-correct correlate`` on a small pair on disk (``--size``³ float32
  ``.npy``, subvolume 15, step 8), with numba's cache **cold** (a fresh ``NUMBA_CACHE_DIR``: every
  kernel the run uses is compiled) and **warm** (the same folder again: loaded from the cache);
  ``--no-cold`` uses each checkout's own cache instead (warm when it has run before).
  The engine's own stage times come from the field file (``prefilter_s`` includes loading, or
  compiling, the first kernel and numba's one-off set-up).

``--self-correct`` adds that option to ``correlate``. Two counts that do not depend on the machine's
load are given for the warm ``correlate``: the modules it imports (``python -X importtime``) and the
numba kernels it loads from the cache (``NUMBA_DEBUG_CACHE=1``: one load per kernel and signature).

Each figure is the best of ``--repeat`` runs (the cold run once). ``--checkout`` runs the same
commands against other source trees (their ``src`` folders first on ``PYTHONPATH``), alternating
between them, for A/B comparisons on a shared machine.

    python benchmarks/bench_startup.py [--size 48] [--repeat 5] [--no-cold] [--self-correct]
                                       [--checkout /path/a --checkout /path/b] [--json out.json]
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _pair(folder: Path, size: int) -> tuple[Path, Path]:
    sys.path.insert(0, str(ROOT / "src"))
    from napari_dvc_correct.engine import synthetic

    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=5),
        (size,) * 3,
        synthetic.translation((0.4, -1.3, 2.2)),
    )
    paths = folder / "ref.npy", folder / "def.npy"
    np.save(paths[0], reference.astype(np.float32))
    np.save(paths[1], deformed.astype(np.float32))
    return paths


def _wall(command: list[str], env: dict, cwd: Path) -> float:
    start = time.perf_counter()
    result = subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")
    return seconds


def _environment(checkout: Path, cache: Path | None) -> dict:
    """``checkout``'s package first on the path; numba's cache in ``cache`` (None: numba's own,
    next to the sources, as a user's warm install has it)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(checkout / "src"), env.get("PYTHONPATH", "")) if p
    )
    env.pop("NUMBA_CACHE_DIR", None)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def _stage_times(field_path: Path, env: dict) -> dict:
    code = (
        "import json, sys; from napari_dvc_correct.io.npz import load_field; "
        "print(json.dumps(load_field(sys.argv[1]).metadata['timings']))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(field_path)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout)


def _counts(command: list[str], env: dict, cwd: Path) -> dict:
    """Modules imported and numba kernels loaded from the cache by one run of ``command``."""
    imports = subprocess.run(
        [command[0], "-X", "importtime", *command[1:]],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        check=True,
    )
    modules = sum(
        1
        for line in imports.stderr.splitlines()
        if line.startswith("import time:") and "self [us]" not in line
    )
    loads = subprocess.run(
        command, env={**env, "NUMBA_DEBUG_CACHE": "1"}, cwd=cwd, capture_output=True, text=True
    )
    lines = (loads.stdout + loads.stderr).splitlines()
    return {
        "modules_imported": modules,
        "kernels_loaded": sum("[cache] data loaded" in line for line in lines),
        "kernels_compiled": sum("[cache] data saved" in line for line in lines),
    }


def measure(
    checkouts: list[Path], size: int, repeat: int, cold: bool, self_correct: bool = False
) -> dict:
    py = sys.executable
    results = {
        str(c): {"warm_correlate_s": [], "help_s": [], "import_engine_s": []} for c in checkouts
    }
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        ref, dfm = _pair(folder, size)
        caches = {c: folder / f"cache{i}" if cold else None for i, c in enumerate(checkouts)}
        out = folder / "field.npz"
        correlate = [py, "-m", "napari_dvc_correct.cli", "correlate", str(ref), str(dfm)]
        correlate += ["--subvolume", "15", "--step", "8", "--quiet", "--out", str(out)]
        correlate += ["--self-correct"] if self_correct else []
        for checkout in checkouts:  # the first run fills the cache: cold (else a warm-up)
            env = _environment(checkout, caches[checkout])
            seconds = _wall(correlate, env, folder)
            if cold:
                results[str(checkout)]["cold_correlate_s"] = seconds
                results[str(checkout)]["cold_stages"] = _stage_times(out, env)
        for _ in range(repeat):
            for checkout in checkouts:
                env = _environment(checkout, caches[checkout])
                entry = results[str(checkout)]
                entry["help_s"].append(
                    _wall([py, "-m", "napari_dvc_correct.cli", "--help"], env, folder)
                )
                entry["import_engine_s"].append(
                    _wall(
                        [py, "-c", "import napari_dvc_correct.engine.correlation.correlate"],
                        env,
                        folder,
                    )
                )
                entry["warm_correlate_s"].append(_wall(correlate, env, folder))
                entry["warm_stages"] = _stage_times(out, env)
        for checkout in checkouts:
            env = _environment(checkout, caches[checkout])
            results[str(checkout)].update(_counts(correlate, env, folder))
    for entry in results.values():
        for key in ("help_s", "import_engine_s", "warm_correlate_s"):
            entry[key] = min(entry[key])
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=48, help="edge of the test pair (voxels)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument(
        "--no-cold",
        action="store_true",
        help="no cold run: use each checkout's own (warm) numba cache",
    )
    parser.add_argument(
        "--checkout",
        action="append",
        type=Path,
        help="source tree to measure (repeatable; default: this one)",
    )
    parser.add_argument(
        "--self-correct", action="store_true", help="time `correlate --self-correct`"
    )
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    checkouts = [c.resolve() for c in (args.checkout or [ROOT])]
    load = os.getloadavg()
    results = measure(checkouts, args.size, args.repeat, not args.no_cold, args.self_correct)
    print(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs")
    for checkout, entry in results.items():
        print(f"{checkout}:")
        print(f"  --help                {entry['help_s']:.3f} s")
        print(f"  import engine         {entry['import_engine_s']:.3f} s")
        if "cold_correlate_s" in entry:
            print(f"  correlate, cold cache {entry['cold_correlate_s']:.2f} s")
        stages = entry["warm_stages"]
        print(
            f"  correlate, warm cache {entry['warm_correlate_s']:.3f} s (engine total "
            f"{stages['total_s']:.3f} s, prefilter + first kernel {stages['prefilter_s']:.3f} s, "
            f"IC-GN {stages['icgn_s']:.3f} s)"
        )
        print(
            f"  warm correlate: {entry['modules_imported']} modules imported, "
            f"{entry['kernels_loaded']} kernels loaded from the cache "
            f"({entry['kernels_compiled']} compiled)"
        )
    if args.json:
        args.json.write_text(json.dumps({"load": load, "results": results}, indent=2))


if __name__ == "__main__":
    main()
