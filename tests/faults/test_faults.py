"""The fault suite: the command line run as a user runs it, with bad inputs and signals.

Every case asserts the exit status, the one-line message, that no input or earlier output
changed and that nothing was left behind (no partial file or set, no temporary file). Signals
land at chosen moments through ``pause_runner.py`` (the unchanged CLI with one pause); each
process is bounded by a timeout. What the tool promises: docs/faults.md.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import stat
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import napari_dvc_correct
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.io.atomic import SET_MARKER, TEMP_MARK

SHAPE = (24, 24, 24)
RUNNER = Path(__file__).with_name("pause_runner.py")
SOURCE = str(Path(napari_dvc_correct.__file__).resolve().parents[1])
TIMEOUT = 90  # seconds any one process may take (numba loads its cache in each)
DVC = ["--subvolume", "9", "--step", "6", "--quiet"]


def environment(**extra) -> dict:
    env = dict(os.environ, **extra)
    env["PYTHONPATH"] = os.pathsep.join([SOURCE, env.get("PYTHONPATH", "")])
    env.pop("NDC_PAUSE_AT", None) if "NDC_PAUSE_AT" not in extra else None
    return env


def cli(*arguments, cwd, umask=None) -> subprocess.CompletedProcess:
    """``python -m napari_dvc_correct.cli ARGS`` in ``cwd``, as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "napari_dvc_correct.cli", *map(str, arguments)],
        cwd=cwd, env=environment(), capture_output=True, text=True, timeout=TIMEOUT,
        preexec_fn=(lambda: os.umask(umask)) if umask is not None else None,
    )  # fmt: skip


def signalled(moment: str, sig: int, *arguments, cwd) -> tuple[int, str]:
    """Run the CLI paused at ``moment``, send ``sig`` there; return (exit status, stderr)."""
    process = subprocess.Popen(
        [sys.executable, str(RUNNER), *map(str, arguments)],
        cwd=cwd, env=environment(NDC_PAUSE_AT=moment), stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    watchdog = threading.Timer(TIMEOUT, process.kill)
    watchdog.start()
    try:
        lines = []
        for line in process.stderr:
            lines.append(line)
            if line.startswith(f"PAUSED {moment}"):
                process.send_signal(sig)
                break
        else:
            pytest.fail(f"never reached {moment!r}: {''.join(lines)[-2000:]}")
        rest = process.stderr.read()
        return process.wait(timeout=TIMEOUT), "".join(lines) + rest
    finally:
        watchdog.cancel()
        if process.poll() is None:
            process.kill()


def tree(folder: Path) -> dict:
    """Every file under ``folder`` (relative path -> bytes), to compare before and after."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.rglob("*") if TEMP_MARK in p.name]


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("scans")
    clean = synthetic.two_phase_volume(SHAPE, seed=11)
    states = [synthetic.translation((0.0, 0.3 * k, 0.0)) for k in range(3)]
    for k, truth in enumerate(states):
        volume = synthetic.add_noise(synthetic.deform_volume(clean, truth), 2.0, seed=12 + k)
        np.save(folder / f"v{k}.npy", volume.astype(np.float32))
    np.savez(folder / "in.npz", volume=np.load(folder / "v0.npy"))
    np.save(folder / "v0_small.npy", np.load(folder / "v0.npy")[:20])
    nan = np.load(folder / "v1.npy")
    nan[5, 5, 5] = np.nan
    np.save(folder / "nan.npy", nan)
    np.save(folder / "flat.npy", np.full(SHAPE, 100.0, np.float32))
    done = cli("correlate", "v0.npy", "v1.npy", *DVC, "--out", "field.npz", cwd=folder)
    assert done.returncode == 0, done.stderr
    return folder


@pytest.fixture
def work(scans, tmp_path) -> Path:
    """A fresh copy of the scans (each test may write into it)."""
    for path in scans.iterdir():
        if path.is_file():
            (tmp_path / path.name).write_bytes(path.read_bytes())
    return tmp_path


# --- bad input: one line, exit 2, nothing written or changed -----------------------------------
BAD_INPUT = [
    (["correlate", "in.npz", "v1.npy", *DVC, "--out", "in.npz"], "is also an input"),
    (["correlate", "v0.npy", "v1.npy", *DVC, "--out", "/proc/field2.npz"], "cannot write into"),
    (["evaluate", "v0_small.npy", "v1.npy", "--field", "field.npz", "--quiet", "--out-dir", "r"],
     "must have the same shape"),
    (["evaluate", "v0.npy", "nan.npy", "--field", "field.npz", "--quiet", "--out-dir", "r"],
     "contains NaN"),
    (["evaluate", "v0.npy", "v1.npy", "--field", "field.npz", "--quiet", "--out-dir", "sub"],
     "files this tool did not write"),
    (["series", "v0.npy", "v1.npy", *DVC, "--out-dir", "."], "holds the input"),
    (["series", "v0.npy", "v1.npy", "v2.npy", *DVC, "--out-dir", "s", "--max-memory", "1MB"],
     "--max-memory"),
]  # fmt: skip
# (more refusals run in-process in tests/commands/test_command_checks.py: cheaper than a process)


def test_bad_input_is_refused_in_one_line_and_changes_nothing(work):
    (work / "sub").mkdir()
    (work / "sub" / "notes.txt").write_text("not ours")
    before = tree(work)
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda arguments: cli(*arguments, cwd=work),
                                [arguments for arguments, _ in BAD_INPUT]))  # fmt: skip
    for (arguments, message), done in zip(BAD_INPUT, results):
        assert done.returncode == 2, (arguments, done.stderr)
        assert message in done.stderr and done.stderr.count("\n") == 1, (arguments, done.stderr)
        assert "device:" not in done.stdout, arguments  # refused before any work
        assert tree(work) == before, arguments


def test_textureless_volumes_give_no_runtime_warnings(work):
    done = cli("correlate", "flat.npy", "flat.npy", *DVC, "--out", "flat.npz", cwd=work)
    assert done.returncode == 0 and "low texture" in done.stdout, done.stderr
    assert "Warning" not in done.stderr, done.stderr


# --- signals: exit status, nothing written, earlier outputs and no temporary file left -----------
@pytest.mark.parametrize(
    ("moment", "sig", "status"),
    [
        ("compute", signal.SIGINT, 130),
        ("compute", signal.SIGTERM, 143),
        ("write", signal.SIGTERM, 143),
    ],
)
def test_correlate_stopped_by_a_signal_keeps_the_earlier_field(work, moment, sig, status):
    before = tree(work)
    code, err = signalled(moment, sig, "correlate", "v0.npy", "v2.npy", *DVC, "--out",
                          "field.npz", cwd=work)  # fmt: skip
    name = "SIGTERM" if sig == signal.SIGTERM else "SIGINT"
    assert code == status, err
    assert f"interrupted ({name}), nothing written, earlier outputs unchanged" in err
    assert "Traceback" not in err
    assert tree(work) == before and leftovers(work) == []


def test_tiled_series_stopped_by_a_signal_leaves_no_temporary_array(work):
    (work / "temporary").mkdir()
    before = tree(work)
    code, err = signalled("compute", signal.SIGINT, "series", "v0.npy", "v1.npy", "v2.npy", *DVC,
                          "--tiled", "--temp-dir", "temporary", "--out-dir", "out", cwd=work)  # fmt: skip
    assert code == 130 and "nothing written, earlier outputs unchanged" in err, err
    assert "Traceback" not in err
    assert tree(work) == before and leftovers(work) == []
    assert not any((work / "temporary").iterdir()) and not (work / "out").exists()


@pytest.mark.parametrize(
    ("command", "sig", "status"),
    [("series", signal.SIGTERM, 143), ("evaluate", signal.SIGINT, 130)],
)
def test_output_set_stopped_midway_keeps_the_earlier_set(work, command, sig, status):
    if command == "series":
        arguments = ["series", "v0.npy", "v1.npy", "v2.npy", *DVC, "--out-dir", "out"]
    else:
        arguments = ["evaluate", "v0.npy", "v1.npy", "--field", "field.npz", "--no-volumes",
                     "--quiet", "--out-dir", "out"]  # fmt: skip
    first = cli(*arguments, cwd=work)
    assert first.returncode == 0, first.stderr
    before = tree(work)
    code, err = signalled("set", sig, *arguments, cwd=work)
    assert code == status and "earlier outputs unchanged" in err, err
    assert tree(work) == before and leftovers(work) == []


def test_sigterm_before_any_work_leaves_nothing(work):
    before = tree(work)
    process = subprocess.Popen(
        [sys.executable, "-m", "napari_dvc_correct.cli", "series", "v0.npy", "v1.npy", *DVC,
         "--out-dir", "early"],
        cwd=work, env=environment(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    process.send_signal(signal.SIGTERM)  # during start-up: the default action or our handler
    assert process.wait(timeout=TIMEOUT) in (-signal.SIGTERM, 143)
    assert tree(work) == before and leftovers(work) == []


# --- reruns, concurrent runs, modes, SIGKILL leftovers -----------------------------------------
def test_rerun_replaces_the_set_and_concurrent_runs_do_not_mix(work):
    done = cli("series", "v0.npy", "v1.npy", "v2.npy", *DVC, "--out-dir", "out", cwd=work)
    assert done.returncode == 0, done.stderr
    assert (work / "out" / "state_02.npz").exists()
    runs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "napari_dvc_correct.cli",
                "series",
                "v0.npy",
                second,
                *DVC,
                "--out-dir",
                "out",
            ],
            cwd=work,
            env=environment(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )  # fmt: skip
        for second in ("v1.npy", "v2.npy")
    ]
    for run in runs:
        assert run.wait(timeout=TIMEOUT) == 0, run.stderr.read()
        run.stdout.close()
        run.stderr.close()
    out = work / "out"
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([SET_MARKER, "state_01.npz", "increment_00_01.npz", "summary.csv"])
    manifest = json.loads((out / SET_MARKER).read_text())
    assert sorted(manifest["files"]) == sorted(n for n in names if n != SET_MARKER)
    with open(out / "summary.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    from napari_dvc_correct.io.npz import load_field

    written = load_field(out / "state_01.npz").metadata["deformed"]
    assert rows[1]["volume"] == written  # the table and the field come from the same run
    assert leftovers(work) == [] and sorted(p.name for p in work.iterdir() if p.is_dir()) == ["out"]


def test_modes_follow_the_umask_and_sigkill_leftovers_are_cleaned(work):
    code, _ = signalled("write", signal.SIGKILL, "correlate", "v0.npy", "v1.npy", *DVC, "--out",
                        "new.npz", cwd=work)  # fmt: skip
    assert code == -signal.SIGKILL
    left = leftovers(work)
    assert len(left) == 1 and left[0].startswith(".new.npz" + TEMP_MARK), left
    assert not (work / "new.npz").exists()
    done = cli("correlate", "v0.npy", "v1.npy", *DVC, "--out", "new.npz", cwd=work, umask=0o027)
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE((work / "new.npz").stat().st_mode) == 0o640
    assert leftovers(work) == []  # the next run removed the dead run's temporary file
    os.chmod(work / "field.npz", 0o604)
    done = cli("correct", "v0.npy", "v1.npy", "--field", "new.npz", "--max-passes", "1",
               "--quiet", "--out", "field.npz", cwd=work, umask=0o077)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE((work / "field.npz").stat().st_mode) == 0o604  # overwriting keeps it


# --- inputs are never overwritten (issue 27 items 1-2) -----------------------------------------
def _points_files(folder: Path) -> None:
    rows = ["z,y,x"] + [f"{z},{y},{x}" for z in (8, 12, 16) for y in (8, 16) for x in (8, 16)]
    (folder / "pts.csv").write_text("\n".join(rows) + "\n")
    (folder / "pts.tsv").write_text("\n".join(r.replace(",", "\t") for r in rows) + "\n")
    field = ["z,y,x,uz,uy,ux"] + [f"{r},0,0.3,0" for r in rows[1:]]
    (folder / "r_points.csv").write_text("\n".join(field) + "\n")  # a field at those points
    (folder / "sp").mkdir()
    (folder / "sp" / "pts_in.csv").write_text((folder / "pts.csv").read_text())


INPUTS_KEPT = [
    # correct --field r_points.csv --out r.npz would write its side file r_points.csv
    (["correct", "v0.npy", "v1.npy", "--field", "r_points.csv", "--subvolume", "9", "--quiet",
      "--out", "r.npz"], "side file r_points.csv, which is the input"),
    # ... and, with the names the other way, replace the reference volume by a grid
    (["correct", "r_grid.npz", "v1.npy", "--field", "r_points.csv", "--subvolume", "9",
      "--quiet", "--out", "r.tsv"], "side file r_grid.npz, which is the input"),
    # a side path that is a folder: refused before r.npz is replaced
    (["correct", "v0.npy", "v1.npy", "--field", "r_points.csv", "--subvolume", "9", "--quiet",
      "--out", "sp.npz"], "which is a folder"),
    (["correlate", "v0.npy", "v1.npy", *DVC, "--points", "pts.tsv", "--out", "pts.tsv"],
     "is also an input"),
    (["series", "v0.npy", "v1.npy", *DVC, "--points", "sp/pts_in.csv", "--out-format", "table",
      "--out-dir", "sp"], "holds the input sp/pts_in.csv"),
]  # fmt: skip


def test_no_output_overwrites_an_input_points_or_side_files_included(work):
    _points_files(work)
    np.savez(work / "r_grid.npz", volume=np.load(work / "v0.npy"))
    (work / "r.npz").write_bytes((work / "field.npz").read_bytes())
    (work / "sp.npz").write_bytes((work / "field.npz").read_bytes())
    (work / "sp_points.csv").mkdir()
    before = tree(work)
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda arguments: cli(*arguments, cwd=work),
                                [arguments for arguments, _ in INPUTS_KEPT]))  # fmt: skip
    for (arguments, message), done in zip(INPUTS_KEPT, results):
        assert done.returncode == 2, (arguments, done.stderr)
        assert message in done.stderr and done.stderr.count("\n") == 1, (arguments, done.stderr)
        assert tree(work) == before and leftovers(work) == [], arguments


def test_a_killed_tiled_correction_leaves_a_folder_the_next_run_removes(work):
    """Issue 27 item 9: SIGKILL cannot be handled, but its temporary folder is recognisable
    (``.dvc-correct.ndc-tmp-PID-HOST-…``) and the next run into the same --temp-dir removes it."""
    (work / "temporary").mkdir()
    arguments = ["correct", "v0.npy", "v1.npy", "--field", "field.npz", "--max-passes", "1",
                 "--tiled", "--temp-dir", "temporary", "--quiet", "--out", "c.npz"]  # fmt: skip
    code, err = signalled("scratch", signal.SIGKILL, *arguments, cwd=work)
    assert code == -signal.SIGKILL, err
    left = [p.name for p in (work / "temporary").iterdir()]
    assert len(left) == 1 and left[0].startswith(".dvc-correct" + TEMP_MARK), left
    done = cli(*arguments, cwd=work)
    assert done.returncode == 0, done.stderr
    assert not any((work / "temporary").iterdir())  # the dead run's folder and its own: gone


def test_signals_after_the_final_rename_and_swallowed_ones_are_reported_honestly(work):
    """Issue 27 item 10: a signal during a set's swap lands when it is done (the earlier set
    is never left as a hidden folder) and the message says the outputs are complete; so does
    one right after a field is written; one swallowed by a library still stops the run."""
    arguments = ["series", "v0.npy", "v1.npy", *DVC, "--out-dir", "out"]
    assert cli(*arguments, cwd=work).returncode == 0
    code, err = signalled("swap", signal.SIGINT, *arguments, cwd=work)
    assert code == 130 and "after writing out: those outputs are complete" in err, err
    assert "Traceback" not in err and leftovers(work) == []
    assert (work / "out" / "state_01.npz").exists()

    before = (work / "field.npz").read_bytes()
    code, err = signalled("written", signal.SIGINT, "correlate", "v0.npy", "v2.npy", *DVC,
                          "--out", "field.npz", cwd=work)  # fmt: skip
    assert code == 130 and "after writing field.npz: those outputs are complete" in err, err
    assert (work / "field.npz").read_bytes() != before and leftovers(work) == []

    before = tree(work)
    code, err = signalled("swallowed", signal.SIGINT, "correlate", "v0.npy", "v1.npy", *DVC,
                          "--out", "field.npz", cwd=work)  # fmt: skip
    assert code == 130 and "nothing written, earlier outputs unchanged" in err, err
    assert tree(work) == before and leftovers(work) == []
