"""The npe2 manifest: valid, importable, and shipped as a real file inside the wheel."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _npe2() -> str:
    found = shutil.which("npe2", path=str(BIN)) or shutil.which("npe2")
    if found is None:
        pytest.fail("npe2 is not installed (it is in the 'testing' extra)")
    return found


def test_npe2_validate_with_imports():
    result = subprocess.run(
        [_npe2(), "validate", "napari-dvc-correct", "--imports"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "valid" in result.stdout


def test_manifest_contributions():
    from npe2 import PluginManifest

    manifest = PluginManifest.from_file(ROOT / "napari.yaml")
    assert {w.display_name for w in manifest.contributions.widgets} == {
        "Correlate",
        "View",
        "Self-correct",
        "Evaluate",
        "Export",
    }
    assert {s.key for s in manifest.contributions.sample_data} == {
        "soil_shear_band",
        "scan_series",
    }
    (reader,) = manifest.contributions.readers
    assert reader.accepts_directories and "*.npz" in reader.filename_patterns
    assert "*.dvcfield" in reader.filename_patterns  # a name only we claim: no reader dialog
    (writer,) = manifest.contributions.writers
    assert writer.filename_extensions == [".dvcfield", ".npz"]
    # the package's copy is a link to the top-level file
    packaged = ROOT / "src" / "napari_dvc_correct" / "napari.yaml"
    assert packaged.resolve() == (ROOT / "napari.yaml").resolve()


def test_wheel_ships_the_manifest_as_a_file(tmp_path):
    env = {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    result = subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--outdir", str(tmp_path), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    (wheel,) = tmp_path.glob("napari_dvc_correct-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        info = archive.getinfo("napari_dvc_correct/napari.yaml")
        mode = info.external_attr >> 16
        assert not stat.S_ISLNK(mode), "napari.yaml is stored as a symbolic link"
        content = archive.read(info).decode("utf-8")
        entry_points = archive.read(
            next(n for n in archive.namelist() if n.endswith("entry_points.txt"))
        ).decode("utf-8")
    assert content == (ROOT / "napari.yaml").read_text(encoding="utf-8")
    assert "napari_dvc_correct._reader:napari_get_reader" in content
    assert "napari-dvc-correct = napari_dvc_correct:napari.yaml" in entry_points
