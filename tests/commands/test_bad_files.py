"""Bad files and absurd option values end in one line and exit status 2, before any work
(issue 27 items 5, 6 and 13): no traceback, no MemoryError, nothing written."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct import cli
from napari_dvc_correct.engine import synthetic

SHAPE = (32, 32, 32)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bad")
    volume = synthetic.textured_volume(SHAPE, 2.0, seed=4).astype(np.float32)
    np.save(folder / "ref.npy", volume)
    np.save(folder / "def.npy", volume)
    (folder / "header.csv").write_text("z,y,x\n")
    (folder / "short.csv").write_text("z,y,x\n10,10,10\n12,12\n")
    (folder / "blank.csv").write_text("z,y,x\n10,,10\n")
    (folder / "header.tsv").write_text(
        "NodeNumber\tZpos\tYpos\tXpos\tZdisp\tYdisp\tXdisp\treturnStatus\n"
    )
    (folder / "header.disp").write_text("n\tx\ty\tz\tstatus\tobjmin\tu\tv\tw\n")
    (folder / "empty.mat").write_bytes(b"")
    return folder


CASES = [
    (["correlate", "--search", "300"], "--search 300: search radius 300 voxels is larger than"),
    (["correlate", "--points", "header.csv"], "header.csv: no points"),
    (["correlate", "--points", "short.csv"], "short.csv: not a table of numbers"),
    (["correlate", "--points", "blank.csv"], "blank.csv: a point has an empty"),
    (["correlate", "--self-correct", "--smoothing", "1e308"], "smoothing must be a sigma from 0"),
    (["correct", "--field", "header.tsv"], "header.tsv: the file holds no points"),
    (["correct", "--field", "header.disp"], "header.disp: the file holds no points"),
    (["correct", "--field", "empty.mat"], "empty.mat: a .mat without DVCmesh"),
    (["correct", "--field", "empty.mat", "--format", "aldvc"], "empty.mat: not a readable aldvc"),
]


@pytest.mark.parametrize(("arguments", "message"), CASES)
def test_bad_files_and_values_are_one_line_and_exit_2(files, capsys, monkeypatch, arguments,
                                                      message):  # fmt: skip
    monkeypatch.chdir(files)
    before = sorted(p.name for p in files.iterdir())
    command, *options = arguments
    code = cli.main([command, "ref.npy", "def.npy", "--subvolume", "9", "--quiet", *options,
                     "--out", "out.csv" if "--points" in options else "out.npz"])  # fmt: skip
    out, err = capsys.readouterr()
    assert code == 2 and message in err and err.count("\n") == 1, err
    assert "device:" not in out  # refused before any work
    assert sorted(p.name for p in files.iterdir()) == before


def test_a_memory_size_no_machine_has_is_an_option_error(files, capsys, monkeypatch):
    monkeypatch.chdir(files)
    with pytest.raises(SystemExit) as stop:
        cli.main(["correlate", "ref.npy", "def.npy", "--max-memory", "1e400GB", "--out", "o.npz"])
    assert stop.value.code == 2
    assert "'1e400GB' is not a memory size" in capsys.readouterr().err
    from napari_dvc_correct.tiled.memory import parse_memory

    for size in ("1e400GB", float("inf"), 2**70):
        with pytest.raises(ValueError, match="memory size"):
            parse_memory(size)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["correct", "--field", "f.npz", "--grid-step", "0"], "--grid-step: must be >= 1"),
        (["correlate", "--tiled", "--temp-dir", "missing/x"], "is not an existing folder"),
    ],
)
def test_option_values_refused_by_the_parser(files, capsys, monkeypatch, arguments, message):
    """Issue 27 item 13: --grid-step 0 is not 'no regridding'; --temp-dir is never created
    (with its missing parents) and left behind."""
    monkeypatch.chdir(files)
    before = sorted(p.name for p in files.iterdir())
    command, *options = arguments
    with pytest.raises(SystemExit) as stop:
        cli.main([command, "ref.npy", "def.npy", *options, "--out", "o.npz"])
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert sorted(p.name for p in files.iterdir()) == before
