"""The numba cache folder is keyed on every engine source, so no kernel runs stale inlined code."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from napari_dvc_correct.engine import _numba_setup


def _engine_copy(tmp_path: Path) -> Path:
    engine = tmp_path / "engine"
    (engine / "cuda").mkdir(parents=True)
    (engine / "a.py").write_text("x = 1\n")
    (engine / "cuda" / "b.py").write_text("y = 2\n")
    return engine


def test_the_stamp_changes_with_any_engine_file_and_only_then(tmp_path):
    engine = _engine_copy(tmp_path)
    first = _numba_setup.engine_source_stamp(engine)
    assert _numba_setup.engine_source_stamp(engine) == first
    os.utime(engine / "a.py", (0, 0))  # a new mtime alone is no change
    assert _numba_setup.engine_source_stamp(engine) == first
    (engine / "cuda" / "b.py").write_text("y = 3\n")  # a callee's module changes
    second = _numba_setup.engine_source_stamp(engine)
    assert second != first
    (engine / "c.py").write_text("")  # a new module
    assert _numba_setup.engine_source_stamp(engine) not in (first, second)


def test_the_versioned_folder_is_used_and_stale_ones_removed(tmp_path, monkeypatch):
    monkeypatch.setattr(_numba_setup.numba.config, "CACHE_DIR", "")
    stale = tmp_path / "numba-old"
    recent = tmp_path / "numba-other-worktree"
    stale.mkdir()
    recent.mkdir()
    old = time.time() - 2 * _numba_setup.STALE_CACHE_AGE
    os.utime(stale, (old, old))
    folder = _numba_setup.use_versioned_cache(tmp_path, "abc")
    assert folder == tmp_path / "numba-abc" and folder.is_dir()
    assert _numba_setup.numba.config.CACHE_DIR == str(folder)
    assert not stale.exists() and recent.exists()


def test_an_unwritable_root_leaves_numba_its_own_places(tmp_path, monkeypatch):
    monkeypatch.setattr(_numba_setup.numba.config, "CACHE_DIR", "")
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert _numba_setup.use_versioned_cache(blocker, "abc") is None
    assert _numba_setup.numba.config.CACHE_DIR == ""


def test_a_process_caches_under_the_stamp_unless_the_user_chose_a_folder(tmp_path):
    code = "import numba; import napari_dvc_correct.engine._numba_setup as s; print(numba.config.CACHE_DIR)"
    src = str(Path(_numba_setup.__file__).parents[2])
    env = {**os.environ, "PYTHONPATH": src, "XDG_CACHE_HOME": str(tmp_path)}
    env.pop("NUMBA_CACHE_DIR", None)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    expected = tmp_path / "napari-dvc-correct" / f"numba-{_numba_setup.engine_source_stamp()}"
    assert out.stdout.strip() == str(expected)
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == str(tmp_path / "mine")
