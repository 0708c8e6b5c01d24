"""Commands refuse bad (pair, field, mask, output) before any work, and clean before evaluating.

Issue 12: items 1 (evaluate checks the pair and the field), 3 (output = input), 4 (correct
refuses fields outside the volumes and empty masks in both frames), 6 (a cleaning step the CLI
can run), 7 (folders and unwritable outputs refused at once; modes) and 9 (--smoothing).
"""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from napari_dvc_correct import cli
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import (
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)
from napari_dvc_correct.io.npz import load_field, save_field

SHAPE = (24, 24, 24)


def grid_field(shape=SHAPE, u=(0.0, 0.0, 0.0), **metadata) -> DisplacementField:
    origin, step, grid = grid_for_volume(shape, 9, 6)
    field = DisplacementField.zeros(origin, step, grid, metadata=dict(metadata))
    field.u[...] = u
    return field


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("checks")
    clean = synthetic.two_phase_volume(SHAPE, seed=5)
    truth = synthetic.translation((0.0, 0.5, 0.0))
    np.save(folder / "ref.npy", synthetic.add_noise(clean, 2.0, seed=6).astype(np.float32))
    np.save(folder / "def.npy", synthetic.add_noise(synthetic.deform_volume(clean, truth), 2.0, 7))
    np.save(folder / "ref20.npy", np.load(folder / "ref.npy")[:20])
    np.save(folder / "zeros.npy", np.zeros(SHAPE, np.uint8))
    save_field(grid_field(u=(0.0, 0.5, 0.0)), folder / "good.npz")
    save_field(grid_field(volume_shape=[48, 48, 48]), folder / "f48.npz")
    save_field(grid_field(shape=(48, 48, 48)), folder / "outside.npz")
    save_field(grid_field(u=(0.0, 1e6, 0.0)), folder / "huge.npz")
    masked = grid_field(u=(0.0, 0.5, 0.0))
    masked.u[0] = np.nan  # a masked correlate leaves no value outside the mask
    masked.status[0] = Status.MASKED
    masked.provenance[0] = Provenance.MASKED
    save_field(masked, folder / "masked.npz")
    return folder


def run(files, capsys, *arguments):
    code = cli.main([str(files / a) if a.endswith((".npy", ".npz")) and "/" not in a else a
                     for a in arguments])  # fmt: skip
    out, err = capsys.readouterr()
    return code, out, err


def snapshot(folder):
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in folder.iterdir() if p.is_file()}


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["ref.npy", "ref20.npy", "--field", "good.npz"], "must have the same shape"),
        (["ref.npy", "def.npy", "--field", "f48.npz"], "measured on volumes of shape (48, 48, 48)"),
        (["ref.npy", "def.npy", "--field", "huge.npz"], "larger than the volume"),
    ],
)
def test_evaluate_checks_the_pair_and_the_field(files, capsys, arguments, message):
    before = snapshot(files)
    code, _, err = run(files, capsys, "evaluate", *arguments, "--quiet", "--out-dir",
                       str(files / "report"))  # fmt: skip
    assert code == 2 and message in err and err.count("\n") == 1, err
    assert not (files / "report").exists() and snapshot(files) == before


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--field", "outside.npz"], "grid does not fit the volume"),
        (["--field", "huge.npz"], "displacements up to 1e+06 voxels"),
        (["--field", "good.npz", "--mask", "zeros.npy"], "the mask is empty"),
        (["--field", "good.npz", "--mask", "zeros.npy", "--frame", "reference"], "mask is empty"),
        (["--field", "good.npz", "--out", "good.npz"], "is also an input"),
        (["--field", "good.npz", "--out", "ref.npy"], "is also an input"),
        (["--field", "good.npz", "--out", "other.txt"], "must end with .npz"),
    ],
)
def test_correct_refuses_fields_masks_and_outputs(files, capsys, arguments, message):
    before = snapshot(files)
    if "--out" not in arguments:
        arguments = [*arguments, "--out", str(files / "corrected.npz")]
    code, out, err = run(files, capsys, "correct", "ref.npy", "def.npy", "--quiet", *arguments)
    assert code == 2 and message in err and err.count("\n") == 1, err
    assert "nan -> nan" not in out
    assert snapshot(files) == before


def test_correlate_refuses_its_input_a_folder_and_an_unwritable_folder(files, capsys, tmp_path):
    volume = files / "vol.npz"
    np.savez(volume, volume=np.load(files / "ref.npy"))
    before = volume.read_bytes()
    for out, message in (
        (str(volume), "is also an input"),
        (str(tmp_path / "sub.npz"), "is a folder"),
        ("/proc/out.npz", "cannot write into /proc"),
    ):
        (tmp_path / "sub.npz").mkdir(exist_ok=True)
        code, out_text, err = run(files, capsys, "correlate", "vol.npz", "def.npy", "--out", out)
        assert code == 2 and message in err, err
        assert "device:" not in out_text  # refused before any work
    assert volume.read_bytes() == before


@pytest.mark.parametrize("value", ["-2", "nan", "inf"])
def test_smoothing_must_be_finite_and_not_negative(files, capsys, value):
    with pytest.raises(SystemExit) as stop:
        cli.main(["correct", str(files / "ref.npy"), str(files / "def.npy"), "--field",
                  str(files / "good.npz"), "--out", str(files / "c.npz"), "--smoothing", value])  # fmt: skip
    assert stop.value.code == 2
    assert "--smoothing: must be a finite number >= 0" in capsys.readouterr().err


def test_clean_fills_a_masked_field_and_keeps_its_provenance(files, capsys, tmp_path):
    out = tmp_path / "cleaned.npz"
    code, printed, err = run(files, capsys, "clean", "masked.npz", "--fill-masked", "--out",
                             str(out))  # fmt: skip
    assert code == 0, err
    cleaned = load_field(out)
    assert np.isfinite(cleaned.u).all()
    assert np.allclose(cleaned.u[0], (0.0, 0.5, 0.0), atol=1e-6)  # inpainted from the others
    assert (cleaned.provenance[0] == Provenance.MASKED).all()
    assert f"{cleaned.shape[1] * cleaned.shape[2]} masked nodes filled" in printed
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o666 & ~_umask()
    code, _, err = run(files, capsys, "clean", "masked.npz", "--out", str(files / "masked.npz"))
    assert code == 2 and "is also an input" in err


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_evaluate_cleans_a_field_with_failed_nodes_and_says_so(files, capsys, tmp_path):
    """Right after a masked correlate: evaluated as the panel does, not refused (was exit 2)."""
    out = tmp_path / "report"
    code, printed, err = run(files, capsys, "evaluate", "ref.npy", "def.npy", "--field",
                             "masked.npz", "--no-volumes", "--quiet", "--out-dir", str(out))  # fmt: skip
    assert code == 0, err
    assert "masked: cleaned before evaluating" in printed and "masked nodes filled" in printed
    assert (out / "report.md").is_file()


def test_correlate_never_writes_over_the_npz_its_scans_are_named_in(files, capsys):
    volume = files / "pair.npz"
    np.savez(volume, reference=np.load(files / "ref.npy"), deformed=np.load(files / "def.npy"))
    before = volume.read_bytes()
    code, out, err = run(files, capsys, "correlate", f"{volume}:reference", f"{volume}:deformed",
                         "--out", "pair.npz", "--quiet")  # fmt: skip
    assert code == 2 and "is also an input" in err, err
    assert volume.read_bytes() == before
