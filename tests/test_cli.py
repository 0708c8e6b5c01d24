"""Start-up of the command line: what ``--help`` and a plain ``correlate`` import and load.

Each check runs in a fresh interpreter (``sys.modules`` and numba's dispatchers start empty), so it
sees what a user's process would.
"""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import napari_dvc_correct
from napari_dvc_correct.commands import _common

#: Top-level packages a plain correlate has no use for (GUI, out-of-core, exports, plotting).
NOT_FOR_A_PLAIN_CORRELATE = (
    "napari",
    "qtpy",
    "PyQt5",
    "PyQt6",
    "PySide6",
    "magicgui",
    "vispy",
    "dask",
    "distributed",
    "zarr",
    "h5py",
    "pyevtk",
    "skimage",
    "matplotlib",
)


def _environment() -> dict:
    """This process's environment, with this checkout's package first on the path (absolute, as
    the child runs in another folder)."""
    source = os.path.dirname(os.path.dirname(os.path.abspath(napari_dvc_correct.__file__)))
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (source, path) if p)}


def _run_python(code: str, cwd) -> dict:
    """Run ``code`` in a new interpreter; it prints one JSON line last, returned decoded."""
    result = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=_environment(),
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_help_imports_neither_numba_nor_scipy(tmp_path):
    report = _run_python(
        """
        import json, sys
        from napari_dvc_correct import cli
        for argv in (["--help"], ["correlate", "--help"], ["correct", "--help"]):
            try:
                cli.main(argv)
            except SystemExit:
                pass
        print(json.dumps(sorted({m.split(".")[0] for m in sys.modules})))
        """,
        tmp_path,
    )
    heavy = {"numba", "scipy", "tifffile", *NOT_FOR_A_PLAIN_CORRELATE} & set(report)
    assert not heavy, f"--help imported {sorted(heavy)}"


@pytest.mark.parametrize("given", [None, "3"])
def test_the_command_line_runs_blas_on_one_thread_unless_told(tmp_path, given):
    # numba's kernels use the cores; OpenBLAS's threads beside them only wait (docs/performance.md)
    code = """
        import json, os, sys
        import napari_dvc_correct.cli
        assert "numpy" not in sys.modules  # numpy (and OpenBLAS) load later and read it
        print(json.dumps(os.environ.get("OPENBLAS_NUM_THREADS")))
    """
    env = {k: v for k, v in _environment().items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    result = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout.strip().splitlines()[-1]) == (given or "1")


def test_plain_correlate_imports_only_what_it_uses_and_loads_each_kernel_once(tmp_path):
    from napari_dvc_correct.engine import synthetic

    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=3),
        (40, 40, 40),
        synthetic.translation((0.3, -2.6, 4.2)),  # far enough for a coarse pyramid level
    )
    # .npy volumes are memory-mapped read-only; the coarse level is computed (writable)
    np.save(tmp_path / "ref.npy", reference.astype(np.float32))
    np.save(tmp_path / "def.npy", deformed.astype(np.float32))
    report = _run_python(
        """
        import json, sys
        from napari_dvc_correct import cli
        code = cli.main(["correlate", "ref.npy", "def.npy", "--subvolume", "19", "--step", "7",
                         "--search", "8", "--out", "f.npz", "--quiet"])
        from napari_dvc_correct.engine.correlation import icgn
        from napari_dvc_correct.io.npz import load_field
        field = load_field("f.npz")
        print(json.dumps({
            "code": code,
            "modules": sorted(sys.modules),
            "signatures": len(icgn.match_many.signatures),
            "levels": field.metadata["pyramid_levels"],
            "good": float(field.valid.mean()),
        }))
        """,
        tmp_path,
    )
    assert report["code"] == 0 and report["good"] > 0.9
    assert report["levels"] >= 1  # so both a read-only and a computed level were matched
    top = {m.split(".")[0] for m in report["modules"]}
    unused = top & set(NOT_FOR_A_PLAIN_CORRELATE)
    assert not unused, f"a plain correlate imported {sorted(unused)}"
    for module in (
        "scipy.sparse",
        "scipy.spatial",
        "napari_dvc_correct.engine.correction.self_correction",
    ):
        assert module not in report["modules"], f"a plain correlate imported {module}"
    # one IC-GN signature for all levels: one cache load (and one cold compile), not two
    assert report["signatures"] == 1


def test_correction_defaults_are_those_the_engine_uses():
    import inspect

    from napari_dvc_correct.engine.correction.cleaning import CleaningOptions, clean
    from napari_dvc_correct.engine.correction.self_correction import correct_iter

    defaults = _common.correction_defaults()
    signature = inspect.signature(correct_iter).parameters
    for name in ("frame", "update", "max_passes", "min_improvement"):
        assert defaults[name] == signature[name].default
    assert defaults["threshold"] == CleaningOptions().threshold
    assert clean.__module__ == "napari_dvc_correct.engine.correction.cleaning"


@pytest.mark.parametrize("argv", [["correlate", "--help"], ["--help"]])
def test_help_still_lists_what_it_did(argv, capsys):
    from napari_dvc_correct import cli

    with pytest.raises(SystemExit):
        cli.main(argv)
    text = capsys.readouterr().out
    if argv == ["--help"]:
        assert all(name in text for name in cli.SUBCOMMANDS)
    else:
        assert "--self-correct" in text and "--max-passes" in text and "default 3" in text
