"""What the subcommands share: outputs refused before any work, inputs gathered, progress shown."""

from argparse import Namespace

import pytest

from napari_dvc_correct.commands import _common as C
from napari_dvc_correct.engine.progress import Progress


def test_an_output_file_is_refused_before_any_work(tmp_path):
    field = tmp_path / "field.npz"
    field.write_bytes(b"input")
    assert C.check_output_path(str(tmp_path / "out.npz"), inputs=[str(field)]) == (
        tmp_path / "out.npz"
    )
    with pytest.raises(ValueError, match="is a folder: give a file name"):
        C.check_output_path(str(tmp_path))
    with pytest.raises(ValueError, match="must end with .npz"):
        C.check_output_path(str(tmp_path / "out.csv"))
    with pytest.raises(FileNotFoundError, match="output folder does not exist"):
        C.check_output_path(str(tmp_path / "nowhere" / "out.npz"))
    with pytest.raises(ValueError, match="is also an input"):
        C.check_output_path(str(field), inputs=[None, str(field)])
    assert not [p for p in tmp_path.iterdir() if p.name != "field.npz"]  # the probe is gone


def test_side_files_and_output_folders_never_replace_an_input(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    scan = data / "G.tif"
    scan.write_bytes(b"scan")
    with pytest.raises(ValueError, match="which is the input"):
        C.check_side_file(scan, [str(scan)], tmp_path / "G.npz")
    with pytest.raises(ValueError, match="which is a folder"):
        C.check_side_file(data, [], tmp_path / "x.npz")
    assert C.check_side_file(tmp_path / "out_points.csv", [str(scan)], tmp_path / "out.npz")
    with pytest.raises(ValueError, match="holds the input"):
        C.check_output_dir(str(data), inputs=[str(scan)])
    assert C.check_output_dir(str(tmp_path / "results"), inputs=[str(scan)]) == (
        tmp_path / "results"
    )


def test_an_existing_output_folder_that_takes_no_changes_is_refused_in_words(tmp_path, monkeypatch):
    # the folder is replaced whole; one that cannot change (read-only, immutable) failed only at
    # the swap, after the work, with "[Errno 1] Operation not permitted: 'ro' -> '.ro.ndc-tmp-...'"
    import os
    from pathlib import Path

    locked = tmp_path / "ro"
    locked.mkdir()
    real_open = os.open

    def refusing_open(path, *args, **kwargs):
        if Path(path).parent == locked:
            raise PermissionError(1, "Operation not permitted", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refusing_open)
    with pytest.raises(PermissionError, match="--out-dir: cannot write into .*ro"):
        C.check_output_dir(str(locked))
    assert C.check_output_dir(str(tmp_path / "new")) == tmp_path / "new"


def test_every_input_option_is_an_input():
    args = Namespace(reference="G.tif", deformed="F.tif", field=None, mask="m.tif",
                     volumes=["a.tif", "b.tif"], points="p.csv", out="o.npz")  # fmt: skip
    assert C.command_inputs(args) == ["G.tif", "F.tif", "a.tif", "b.tif", "m.tif", "p.csv"]


def test_drive_returns_the_result_and_the_bar_draws_each_stage(capsys):
    def work():
        yield Progress("IC-GN", 1, 2, "half")
        yield Progress("IC-GN", 2, 2, "all")
        return 42

    assert C.drive(work(), C.ProgressBar()) == 42
    lines = capsys.readouterr().err.splitlines()  # not a terminal: a line per stage and at the end
    assert lines == [
        f"{'IC-GN':>14} [{'#' * 15}{'.' * 15}] half",
        f"{'IC-GN':>14} [{'#' * 30}] all",
    ]
    assert C.drive(work(), C.ProgressBar(quiet=True)) == 42
    assert capsys.readouterr().err == ""
    C.warn(Namespace(command="correct"), "the mask is empty")
    assert capsys.readouterr().err == "napari-dvc-correct correct: warning: the mask is empty\n"


def test_an_npz_member_input_is_its_file(tmp_path):
    # `correlate rock.npz:reference rock.npz:deformed --out rock.npz` replaced the user's scans
    # with the field: the check compared the output with "rock.npz:reference", not "rock.npz"
    scans = tmp_path / "rock.npz"
    scans.write_bytes(b"scans")
    args = Namespace(reference=f"{scans}:reference", deformed=f"{scans}:deformed")
    assert C.command_inputs(args) == [str(scans), str(scans)]
    with pytest.raises(ValueError, match="is also an input"):
        C.check_output_path(str(scans), suffixes=None, inputs=C.command_inputs(args))
    with pytest.raises(ValueError, match="holds the input"):
        C.check_output_dir(str(tmp_path), inputs=C.command_inputs(args))
    odd = tmp_path / "a:b.tif"  # a file whose own name has a colon stays whole
    odd.write_bytes(b"scan")
    assert C.command_inputs(Namespace(reference=str(odd))) == [str(odd)]
