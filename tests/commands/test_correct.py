"""The ``correct`` and ``series`` subcommands and ``correlate --self-correct``."""

import csv

import numpy as np
import pytest

from napari_dvc_correct.cli import main
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance
from napari_dvc_correct.io.npz import load_field, save_field

SHAPE = (36, 36, 36)
SHIFT = np.array([1.4, -0.6, 2.2])
DVC = ["--subvolume", "15", "--step", "8", "--quiet"]


@pytest.fixture(scope="module")
def volumes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("volumes")
    big = synthetic.textured_volume(tuple(n + 16 for n in SHAPE), 2.0, seed=21)
    crop = tuple(slice(8, 8 + n) for n in SHAPE)
    paths = []
    for k in range(3):
        moved = synthetic.deform_volume(big, synthetic.translation(k * SHIFT))
        path = folder / f"state{k}.npy"
        np.save(path, np.ascontiguousarray(moved[crop]))
        paths.append(str(path))
    return paths


def correlated_field_file(volumes, tmp_path, one_wrong_node: bool = False):
    """``correlate`` of states 0 and 1 written to ``field.npz``; with ``one_wrong_node`` one node
    is moved 1.5 voxel off (a translation alone has nothing a pass could correct)."""
    field_path = tmp_path / "field.npz"
    assert main(["correlate", volumes[0], volumes[1], "--out", str(field_path), *DVC]) == 0
    if one_wrong_node:
        wrong = load_field(field_path)
        wrong.u[1, 1, 1] += (0.0, 1.5, 0.0)
        save_field(wrong, field_path)
    return field_path


def test_correct_writes_a_corrected_field_and_prints_the_passes(volumes, tmp_path, capsys):
    field_path = correlated_field_file(volumes, tmp_path, one_wrong_node=True)
    out = tmp_path / "corrected.npz"
    code = main(
        ["correct", volumes[0], volumes[1], "--field", str(field_path), "--out", str(out),
         "--max-passes", "2", "--quiet"]
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "mean gray residual" in printed and "pass" in printed
    corrected = load_field(out)
    passes = corrected.metadata["correction_passes"]
    assert passes[0]["pass"] == 0 and len(passes) >= 2
    # the correcting matches' order, subvolume and why, as the panel shows them
    assert "order" in printed and "subvolume" in printed
    assert f"{passes[1]['subvolume']}³" in printed
    assert corrected.metadata["correction"]["pass_method"] in printed
    assert "you chose: first order, " in printed
    # the residual column's frame and the noise floor's, which are not on one scale
    assert "mean gray residual: mean of |map(F) − G'|, loaded frame" in printed
    assert "noise floor: the local acceptance's, node windows in the reference frame" in printed
    # the gray-level map the residuals were judged with, and what was flagged
    assert corrected.metadata["gray_levels"]["description"] in printed
    assert "flagged after the passes: " in printed
    assert corrected.metadata["corrected_from"] == str(field_path)
    error = corrected.displacement[corrected.valid.reshape(-1)] - SHIFT
    assert np.sqrt(np.mean(error**2)) < 0.05
    # the regularised estimate is off by default
    assert corrected.metadata["correction"]["noise_fit"] is None
    assert "regularised: " not in printed


def test_correct_with_the_regularised_estimate_says_what_it_did(volumes, tmp_path, capsys):
    field_path = correlated_field_file(volumes, tmp_path)
    out = tmp_path / "corrected.npz"
    args = ["correct", volumes[0], volumes[1], "--field", str(field_path), "--out", str(out)]
    assert main([*args, "--max-passes", "1", "--noise-fit", "--quiet"]) == 0
    record = load_field(out).metadata["correction"]["noise_fit"]
    assert record["fitted_nodes"] == len(record["fitted"])
    printed = capsys.readouterr().out
    if record["not_run"]:  # a field file without the matches' uncertainties
        assert f"regularised: no node ({record['not_run']})" in printed
    else:
        assert f"regularised: {record['fitted_nodes']} nodes" in printed


def test_correct_can_switch_the_regularised_estimate_on_and_off(tmp_path):
    from napari_dvc_correct.cli import build_parser
    from napari_dvc_correct.commands.correct import correction_records_from_args

    base = ["correct", "g.npy", "f.npy", "--field", "d.npz", "--out", str(tmp_path / "o.npz")]
    for extra, expected in (([], False), (["--no-noise-fit"], False), (["--noise-fit"], True)):
        options, _ = correction_records_from_args(build_parser().parse_args(base + extra))
        assert options.noise_fit is expected


def test_correct_reads_the_match_uncertainties_of_our_own_field_file(volumes, tmp_path):
    """A field written by ``correlate`` keeps its matches' uncertainties through ``correct``'s
    reader: on a clean translation, where every node is its own converged match, the correction
    knows it and runs no pass (a pass could only re-measure the same images)."""
    field_path = correlated_field_file(volumes, tmp_path)
    written = load_field(field_path)
    assert written.uncertainty is not None
    out = tmp_path / "corrected.npz"
    args = ["correct", volumes[0], volumes[1], "--field", str(field_path), "--out", str(out)]
    assert main([*args, "--quiet"]) == 0
    corrected = load_field(out)
    assert corrected.metadata["correction"]["stop_reason"].startswith("no pass run")
    np.testing.assert_allclose(corrected.uncertainty, written.uncertainty)
    np.testing.assert_allclose(corrected.u, written.u)


def test_correct_refuses_bad_input_and_writes_nothing(volumes, tmp_path, capsys):
    out = tmp_path / "corrected.npz"
    missing = ["correct", volumes[0], volumes[1], "--field", str(tmp_path / "no.npz")]
    assert main([*missing, "--out", str(out)]) == 2
    assert "not found" in capsys.readouterr().err
    field_path = tmp_path / "field.npz"
    save_field(DisplacementField.zeros((7.0, 7.0, 7.0), (8.0, 8.0, 8.0), (3, 3, 3)), field_path)
    wrong = ["correct", volumes[0], volumes[1], "--field", str(field_path)]
    assert main([*wrong, "--out", str(tmp_path / "corrected.txt")]) == 2
    assert main([*wrong, "--out", str(out), "--max-passes", "0"]) == 2
    assert not out.exists()


def test_correlate_self_correct(volumes, tmp_path, capsys):
    out = tmp_path / "field.npz"
    args = ["correlate", volumes[0], volumes[1], "--out", str(out), *DVC]
    assert main([*args, "--self-correct", "--max-passes", "1"]) == 0
    printed = capsys.readouterr().out
    field = load_field(out)
    assert field.metadata["correction"]["max_passes"] == 1
    # a translation, every node its own converged match: nothing a pass could correct, and
    # the command says so rather than re-measuring the noise
    stop = field.metadata["correction"]["stop_reason"]
    assert stop.startswith("no pass run") and f"stopped: {stop}" in printed
    assert len(field.metadata["correction_passes"]) == 1
    assert field.metadata["correction"]["passes_applied"] == 0
    error = field.displacement[field.valid.reshape(-1)] - SHIFT
    assert np.sqrt(np.mean(error**2)) < 0.05


def test_correct_prints_the_method_of_its_passes(volumes, tmp_path, capsys):
    field_path = correlated_field_file(volumes, tmp_path, one_wrong_node=True)
    capsys.readouterr()
    out = tmp_path / "corrected.npz"
    args = ["correct", volumes[0], volumes[1], "--field", str(field_path), "--out", str(out)]
    assert main([*args, "--max-passes", "1"]) == 0
    printed = capsys.readouterr().out
    field = load_field(out)
    assert f"correcting matches, pass 1: {field.metadata['correction']['pass_method']}" in printed
    assert len(field.metadata["correction_passes"]) == 2


def test_correct_tiled_gives_the_in_memory_field(volumes, tmp_path, capsys):
    field_path = correlated_field_file(volumes, tmp_path)
    common = ["correct", volumes[0], volumes[1], "--field", str(field_path), "--max-passes", "2"]
    assert main([*common, "--out", str(tmp_path / "a.npz"), "--quiet"]) == 0
    capsys.readouterr()
    (tmp_path / "temporary").mkdir()
    tiled = ["--batch", "2", "--workers", "2", "--temp-dir", str(tmp_path / "temporary")]
    assert main([*common, "--out", str(tmp_path / "b.npz"), *tiled]) == 0  # not quiet: the plan
    assert "tiled correction: estimated peak memory" in capsys.readouterr().err
    assert not any((tmp_path / "temporary").iterdir())  # the warped volumes are gone
    a, b = load_field(tmp_path / "a.npz"), load_field(tmp_path / "b.npz")
    np.testing.assert_array_equal(a.status, b.status)
    assert np.nanmax(np.abs(a.u - b.u)) < 1e-4  # see tests/tiled/test_correction.py
    assert b.metadata["correction"]["tiled"]["scheduler"] == "local threads"
    assert len(b.metadata["correction_passes"]) == len(a.metadata["correction_passes"])


def test_correct_tiled_refuses_a_run_over_max_memory_and_writes_nothing(volumes, tmp_path, capsys):
    field_path = correlated_field_file(volumes, tmp_path)
    out = tmp_path / "corrected.npz"
    args = ["correct", volumes[0], volumes[1], "--field", str(field_path), "--out", str(out)]
    assert main([*args, "--max-memory", "1MB", "--quiet"]) == 2
    assert "--max-memory" in capsys.readouterr().err
    assert not out.exists()


def test_correlate_tiled_self_correct(volumes, tmp_path):
    out = tmp_path / "field.npz"
    args = ["correlate", volumes[0], volumes[1], "--out", str(out), *DVC, "--tiled"]
    assert main([*args, "--batch", "2", "--self-correct", "--max-passes", "1"]) == 0
    field = load_field(out)
    assert field.metadata["tiled"]["batches"] == 8  # the correlation, in batches
    assert "tiled" in field.metadata["correction"]  # and the correction, out of core
    # a translation: nothing a pass could correct (tests/tiled run the tiled passes)
    assert field.metadata["correction"]["stop_reason"].startswith("no pass run")
    assert len(field.metadata["correction_passes"]) == 1
    error = field.displacement[field.valid.reshape(-1)] - SHIFT
    assert np.sqrt(np.mean(error**2)) < 0.05


@pytest.mark.parametrize("strategy", ["incremental", "total"])
def test_series_writes_one_field_per_state_and_a_summary(volumes, tmp_path, strategy):
    out_dir = tmp_path / "series"
    code = main(["series", *volumes, "--strategy", strategy, "--out-dir", str(out_dir), *DVC])
    assert code == 0
    for k in (1, 2):
        field = load_field(out_dir / f"state_{k:02d}.npz")
        good = field.valid.reshape(-1)
        assert good.mean() > 0.9
        assert np.abs(field.displacement[good] - k * SHIFT).max() < 0.1
    increments = sorted(p.name for p in out_dir.glob("increment_*.npz"))
    assert increments == (
        ["increment_00_01.npz", "increment_01_02.npz"] if strategy == "incremental" else []
    )
    with open(out_dir / "summary.csv") as stream:
        rows = list(csv.DictReader(stream))
    assert [row["state"] for row in rows] == ["0", "1", "2"]
    assert rows[2]["field_file"] == "state_02.npz"
    assert float(rows[2]["mean_displacement"]) == pytest.approx(np.linalg.norm(2 * SHIFT), 0.05)


def test_series_with_self_correction_marks_corrected_nodes(volumes, tmp_path):
    out_dir = tmp_path / "series"
    code = main(
        ["series", *volumes[:2], "--out-dir", str(out_dir), "--self-correct", "--max-passes",
         "1", *DVC]
    )  # fmt: skip
    assert code == 0
    field = load_field(out_dir / "state_01.npz")
    assert field.metadata["series"]["corrected_total"] is True
    applied = field.metadata["correction"]["passes_applied"]
    expected = Provenance.CORRECTED if applied else Provenance.MEASURED
    assert np.any(field.provenance == expected)


def test_series_needs_two_volumes(volumes, tmp_path, capsys):
    assert main(["series", volumes[0], "--out-dir", str(tmp_path / "s"), *DVC]) == 2
    assert "at least 2" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
