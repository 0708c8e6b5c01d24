"""The command line: correlate a pair, report, and refuse bad input with one line."""

import subprocess
import sys

import numpy as np
import pytest
import tifffile

from napari_dvc_correct import cli
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.io.npz import load_field


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=2),
        (40, 40, 40),
        synthetic.translation((0.4, -1.2, 2.5)),
    )
    tifffile.imwrite(folder / "ref.tif", (reference * 60000).astype(np.uint16))
    np.save(folder / "def.npy", deformed * 60000)
    return folder


def test_correlate_writes_a_field_and_a_summary(pair, capsys):
    out = pair / "field.npz"
    code = cli.main(
        [
            "correlate",
            str(pair / "ref.tif"),
            str(pair / "def.npy"),
            "--subvolume",
            "15",
            "--step",
            "8",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    field = load_field(out)
    good = field.valid
    assert good.mean() > 0.9
    assert np.allclose(field.u[good], [0.4, -1.2, 2.5], atol=0.02)
    printed = capsys.readouterr().out
    assert "POIs" in printed and "mean ZNCC of the matched" in printed
    # the usable fraction and the counts by status say the same thing (one definition)
    counts = field.node_counts()
    assert counts.text() in printed
    assert f"usable {int(good.sum())} of {field.n_points} nodes ({good.mean():.3f})" in printed


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["missing.tif", "def.npy"], "not found"),
        (["ref.tif", "def.npy", "--subvolume", "61"], "larger than the volume"),
        (["ref.tif", "def.npy", "--step", "0"], "step"),
        (["ref.tif", "bad.npy"], "same shape"),
        (["ref.tif", "flat.npy"], "3-D"),
        (["ref.tif", "nan.npy"], "NaN"),
        (["ref.tif", "fake.tif"], "not a readable TIFF"),
        (["ref.tif", "def.npy", "--subvolume", "14"], "odd"),
    ],
)
def test_bad_input_exits_non_zero_with_one_line_and_writes_nothing(
    pair, capsys, arguments, message
):
    np.save(pair / "bad.npy", np.zeros((40, 40, 41)))
    np.save(pair / "flat.npy", np.zeros((40, 40)))
    nan = np.zeros((40, 40, 40))
    nan[3, 3, 3] = np.nan
    np.save(pair / "nan.npy", nan)
    (pair / "fake.tif").write_bytes(b"this is not a tiff")
    out = pair / "never.npz"
    paths = [str(pair / a) if a.endswith((".tif", ".npy")) else a for a in arguments]
    code = cli.main(["correlate", *paths, "--out", str(out)])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not out.exists()
    assert not list(pair.glob(".never*"))


def test_cli_and_engine_do_not_import_napari_or_qt():
    code = (
        "import sys; import napari_dvc_correct.cli as c; c.build_parser();"
        "import napari_dvc_correct.engine.correlation.correlate;"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('napari', 'qtpy', 'PyQt6', 'PyQt5',"
        " 'PySide6', 'magicgui', 'vispy')]; print(bad); assert not bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_entry_point_runs(pair, tmp_path):
    exe = subprocess.run(
        [sys.executable, "-m", "napari_dvc_correct.cli", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "correlate" in exe.stdout


def test_tiled_run_matches_the_in_memory_run(pair, tmp_path):
    common = [str(pair / "ref.tif"), str(pair / "def.npy"), "--subvolume", "15", "--step", "8"]
    assert cli.main(["correlate", *common, "--out", str(tmp_path / "memory.npz")]) == 0
    assert (
        cli.main(
            ["correlate", *common, "--tiled", "--batch", "2", "--out", str(tmp_path / "tiled.npz")]
        )
        == 0
    )
    memory = load_field(tmp_path / "memory.npz")
    tiled = load_field(tmp_path / "tiled.npz")
    both = memory.valid & tiled.valid
    assert both.mean() > 0.9
    assert np.max(np.abs(memory.u[both] - tiled.u[both])) < 1e-4


def test_a_specimen_in_air_without_a_region_gets_the_hint_to_give_one(tmp_path, capsys):
    """The cracked real-rock crop without a mask left 9 % of its nodes in the air without a
    word; a run whose nodes find no texture over a third of the volume now says what to do."""
    reference, deformed = synthetic.make_pair(
        lambda s: synthetic.textured_volume(s, 2.0, seed=3),
        (40, 40, 40),
        synthetic.translation((0.3, 0.5, -0.4)),
    )
    reference[:, :, 26:] = 0.0  # air: nothing to match
    deformed[:, :, 26:] = 0.0
    np.save(tmp_path / "ref.npy", reference * 1000)
    np.save(tmp_path / "def.npy", deformed * 1000)
    common = [str(tmp_path / "ref.npy"), str(tmp_path / "def.npy"), "--subvolume", "11"]
    common += ["--step", "6", "--quiet"]
    assert cli.main(["correlate", *common, "--out", str(tmp_path / "a.npz")]) == 0
    printed = capsys.readouterr().out
    field = load_field(tmp_path / "a.npz")
    none = int(np.count_nonzero(field.status == 5))  # Status.LOW_TEXTURE
    assert none >= 0.05 * field.n_points
    assert f"hint: {none} of {field.n_points} nodes" in printed and "--roi" in printed
    # the same run inside the specimen (--roi): no hint
    roi = ["--roi", ":,:,:26"]
    assert cli.main(["correlate", *common, *roi, "--out", str(tmp_path / "b.npz")]) == 0
    assert "hint:" not in capsys.readouterr().out
