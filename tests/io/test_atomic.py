"""Atomic writes: modes as a plain write gives them, recognisable temporary names, output sets."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from napari_dvc_correct.io.atomic import (
    HOST_TAG,
    SET_MARKER,
    TEMP_MARK,
    atomic_dir,
    atomic_path,
    remove_stale,
    temp_name,
)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_new_file_gets_the_mode_of_a_plain_write(tmp_path, umask_022):
    with open(tmp_path / "plain.txt", "w") as stream:
        stream.write("x")
    with atomic_path(tmp_path / "out.txt") as temp:
        temp.write_text("x")
    assert mode(tmp_path / "out.txt") == mode(tmp_path / "plain.txt") == 0o644


def test_overwriting_keeps_the_existing_mode(tmp_path, umask_022):
    target = tmp_path / "out.txt"
    target.write_text("old")
    os.chmod(target, 0o640)
    with atomic_path(target) as temp:
        temp.write_text("new")
    assert target.read_text() == "new" and mode(target) == 0o640


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "out.npz") as temp:
        temp.write_text("half")
        raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []


def test_temporary_names_are_recognisable_and_keep_the_suffix(tmp_path):
    name = temp_name(tmp_path / "field.npz").name
    assert name.startswith(".field.npz") and TEMP_MARK in name and name.endswith(".npz")
    assert f"{TEMP_MARK}{os.getpid()}-" in name


def test_stale_leftovers_of_dead_processes_are_removed(tmp_path):
    """A SIGKILL leaves a temporary file; the next write into the folder removes it."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    pid = int(dead.stdout)
    stale = temp_name(tmp_path / "out.npz", pid=pid)
    stale.write_text("left by a killed run")
    stale_dir = temp_name(tmp_path / "report", pid=pid)
    stale_dir.mkdir()
    other_machine = tmp_path / stale.name.replace(
        HOST_TAG, "abcdef" if HOST_TAG != "abcdef" else "fedcba"
    )
    other_machine.write_text("a run on another machine of a shared file system")
    live = temp_name(tmp_path / "other.npz")  # this process: running, kept
    live.write_text("mine")
    foreign = tmp_path / ".hidden.npz"
    foreign.write_text("not ours")
    with atomic_path(tmp_path / "out.npz") as temp:
        temp.write_text("new")
    assert not stale.exists() and not stale_dir.exists()
    assert live.exists() and foreign.exists() and other_machine.exists()
    assert (tmp_path / "out.npz").exists()
    assert remove_stale(tmp_path) == []


def test_output_set_replaces_the_earlier_set_whole(tmp_path):
    out = tmp_path / "set"
    with atomic_dir(out) as temp:
        (temp / "a.csv").write_text("1")
        (temp / "b.csv").write_text("1")
    with atomic_dir(out) as temp:
        (temp / "a.csv").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [SET_MARKER, "a.csv"]
    assert (out / "a.csv").read_text() == "2"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]


def test_failed_output_set_keeps_the_earlier_one(tmp_path):
    out = tmp_path / "set"
    with atomic_dir(out) as temp:
        (temp / "a.csv").write_text("1")
    with pytest.raises(KeyboardInterrupt), atomic_dir(out) as temp:
        (temp / "a.csv").write_text("2")
        raise KeyboardInterrupt
    assert (out / "a.csv").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]


def test_output_set_never_replaces_a_foreign_folder(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.docx").write_text("precious")
    with pytest.raises(ValueError, match="did not write"), atomic_dir(out) as temp:
        (temp / "a.csv").write_text("2")
    assert (out / "thesis.docx").read_text() == "precious"
    # an older set without the marker is recognised by its file names
    (out / "thesis.docx").unlink()
    (out / "summary.csv").write_text("old")
    with atomic_dir(out, patterns=("*.csv",)) as temp:
        (temp / "a.csv").write_text("2")
    assert not (out / "summary.csv").exists()


def test_files_that_belong_together_are_replaced_together(tmp_path):
    from napari_dvc_correct.io.atomic import atomic_files

    field, side = tmp_path / "f.npz", tmp_path / "f_points.csv"
    field.write_text("old field")
    side.write_text("old side")
    with pytest.raises(KeyboardInterrupt), atomic_files(field, side) as (a, b):
        a.write_text("new field")
        raise KeyboardInterrupt  # between the two writes
    assert field.read_text() == "old field" and side.read_text() == "old side"
    with atomic_files(field, side) as (a, b):
        a.write_text("new field")
        b.write_text("new side")
    assert field.read_text() == "new field" and side.read_text() == "new side"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.npz", "f_points.csv"]


def test_a_field_and_its_side_file_are_written_both_or_neither(tmp_path, monkeypatch):
    """Issue 27 item 3: a side path that is a folder, or a failing second rename, leaves the
    field as it was."""
    from napari_dvc_correct.io import atomic
    from napari_dvc_correct.io.atomic import atomic_files

    field, side = tmp_path / "r.npz", tmp_path / "r_points.csv"
    field.write_text("old field")
    side.mkdir()
    with pytest.raises(ValueError, match="is a folder"), atomic_files(field, side) as (a, b):
        a.write_text("new field")
        b.write_text("new side")
    assert field.read_text() == "old field"
    side.rmdir()
    side.write_text("old side")
    real_replace = os.replace

    def failing_replace(source, target):
        if Path(target) == side:
            raise OSError(28, "No space left on device")
        return real_replace(source, target)

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    with pytest.raises(OSError, match="No space"), atomic_files(field, side) as (a, b):
        a.write_text("new field")
        b.write_text("new side")
    monkeypatch.setattr(atomic.os, "replace", real_replace)
    assert field.read_text() == "old field" and side.read_text() == "old side"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz", "r_points.csv"]
    new = tmp_path / "new.npz"
    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    with pytest.raises(OSError), atomic_files(new, side) as (a, b):
        a.write_text("new field")
        b.write_text("new side")
    monkeypatch.setattr(atomic.os, "replace", real_replace)
    assert not new.exists() and side.read_text() == "old side"


def test_rewriting_a_set_never_deletes_a_file_its_manifest_does_not_list(tmp_path):
    """Issue 27 item 4: a user's file added to an output folder after the run stays."""
    out = tmp_path / "set"
    with atomic_dir(out) as temp:
        (temp / "a.csv").write_text("1")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="notes.txt"), atomic_dir(out) as temp:
        (temp / "a.csv").write_text("2")
    assert (out / "notes.txt").read_text() == "mine" and (out / "a.csv").read_text() == "1"
    (out / "notes.txt").unlink()
    with atomic_dir(out) as temp:
        (temp / "b.csv").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [SET_MARKER, "b.csv"]


def test_a_folder_that_takes_no_files_is_said_in_words(tmp_path):
    import os

    from napari_dvc_correct.io.atomic import check_writable

    check_writable(tmp_path)
    assert list(tmp_path.iterdir()) == []  # the probe is gone
    if os.path.isdir("/proc/self"):
        with pytest.raises(PermissionError, match=r"cannot write into /proc \("):
            check_writable("/proc")
