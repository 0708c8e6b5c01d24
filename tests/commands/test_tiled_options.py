"""The large-volume options of the correlate command (commands/_tiled_options.py)."""

import argparse

import numpy as np
import pytest
import tifffile

from napari_dvc_correct.commands._tiled_options import add_tiled_arguments, run_tiled, wants_tiled
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.tiled import MemoryBudgetError, correlate_tiled


def _parser():
    parser = argparse.ArgumentParser()
    parser.add_argument("reference")
    parser.add_argument("deformed")
    parser.add_argument("--mask")
    parser.add_argument("--quiet", action="store_true")
    add_tiled_arguments(parser)
    return parser


def test_options_parse_and_switch_tiling_on():
    parser = _parser()
    assert not wants_tiled(parser.parse_args(["g", "f"]))
    args = parser.parse_args(["g", "f", "--max-memory", "1.5GiB", "--batch", "4,5,6"])
    assert args.max_memory == 1.5 * 2**30 and args.batch == (4, 5, 6)
    assert wants_tiled(args)
    assert parser.parse_args(["g", "f", "--batch", "7"]).batch == (7, 7, 7)
    assert wants_tiled(parser.parse_args(["g", "f", "--scheduler", "tcp://host:8786"]))
    assert wants_tiled(parser.parse_args(["g", "f", "--tiled"]))
    for bad in (["--max-memory", "lots"], ["--batch", "4,5"], ["--batch", "0"], ["--workers", "0"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["g", "f", *bad])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiled_cli")
    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=2)
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.6, -1.2, 0.4)))
    tifffile.imwrite(folder / "g.tif", (reference * 50000).astype(np.uint16))
    tifffile.imwrite(folder / "f.tif", (deformed * 50000).astype(np.uint16))
    return folder


def test_run_tiled_reads_files_and_states_the_memory(files, capsys):
    params = CorrelationParams(subvolume=15, step=8)
    args = _parser().parse_args([str(files / "g.tif"), str(files / "f.tif"), "--batch", "2"])
    field = run_tiled(args, params, progress=lambda report: None)
    assert "estimated peak memory" in capsys.readouterr().err
    good = field.status == Status.CONVERGED
    assert good.mean() > 0.9
    assert np.abs(field.u[good] - (0.6, -1.2, 0.4)).max() < 0.05
    assert field.metadata["tiled"]["batches"] == 8
    same = correlate_tiled(files / "g.tif", files / "f.tif", params, batch_shape=2)
    np.testing.assert_array_equal(field.u, same.u)


def test_run_tiled_refuses_too_little_memory_as_bad_input(files):
    args = _parser().parse_args(
        [str(files / "g.tif"), str(files / "f.tif"), "--max-memory", "1MB", "--quiet"]
    )
    with pytest.raises(ValueError, match="--max-memory") as caught:
        run_tiled(args, CorrelationParams(subvolume=15, step=8))
    assert isinstance(caught.value, MemoryBudgetError)
