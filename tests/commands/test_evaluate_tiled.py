"""``evaluate --tiled``: the same report as in memory, and a clear refusal when memory is short."""

import csv

import numpy as np
import pytest
import tifffile

from napari_dvc_correct import cli
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.io.npz import save_field

SHAPE = (32, 36, 40)


def grid_field(function):
    origin, step, grid = grid_for_volume(SHAPE, 9, 4)
    base = DisplacementField.zeros(origin, step, grid)
    return base.replace(u=synthetic.sample_displacement(function, base.points).reshape((*grid, 3)))


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans_tiled")
    clean = synthetic.two_phase_volume(SHAPE, seed=21)
    truth = synthetic.shear_band(center=(16.0, 18.0, 20.0), width=4.0, slip=3.0)
    reference = synthetic.add_noise(clean, 3.0, seed=22)
    deformed = synthetic.add_noise(synthetic.deform_volume(clean, truth), 3.0, seed=23)
    tifffile.imwrite(folder / "ref.tif", np.clip(reference, 0, 255).astype(np.uint8))
    tifffile.imwrite(folder / "def.tif", deformed.astype(np.float32))
    save_field(grid_field(truth), folder / "exact.npz")
    save_field(grid_field(synthetic.translation((0.0, 0.0, 0.0))), folder / "rigid.npz")
    return folder


def _rows(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def _run(scans, out, *extra):
    return cli.main(
        ["evaluate", str(scans / "ref.tif"), str(scans / "def.tif"),
         "--field", str(scans / "rigid.npz"), "--compare", str(scans / "exact.npz"),
         "--bins", "4", "--bin-by", "exact", "--quiet", "--out-dir", str(out), *extra]
    )  # fmt: skip


def test_tiled_evaluate_writes_the_report_of_the_in_memory_run(scans, capsys):
    assert _run(scans, scans / "memory") == 0
    assert _run(scans, scans / "tiled", "--tiled", "--block", "16,16,24", "--workers", "2") == 0
    memory, tiled = scans / "memory", scans / "tiled"
    assert sorted(p.name for p in memory.iterdir()) == sorted(p.name for p in tiled.iterdir())
    for table in ("summary.csv", "phases.csv", "strain_bins.csv", "background.csv"):
        ours, theirs = _rows(memory / table), _rows(tiled / table)
        assert len(ours) == len(theirs) and ours[0].keys() == theirs[0].keys(), table
        for a, b in zip(ours, theirs):
            for key in a:
                try:
                    x, y = float(a[key]), float(b[key])
                except ValueError:
                    assert a[key] == b[key], (table, key)
                    continue
                # 6 significant digits in the tables (a value on a rounding boundary may differ
                # by one unit of the last digit); residuals agree to ~1e-7 of the gray range
                last_digit = 10.0 ** (np.floor(np.log10(abs(x))) - 5) if x and np.isfinite(x) else 0
                tolerance = max(1e-5, 1.01 * last_digit)
                assert y == pytest.approx(x, rel=2e-6, abs=tolerance, nan_ok=True), (table, key)
    for name in ("residual_exact.tif", "labels_mapped_rigid.tif", "labels_reference.tif",
                 "labels_deformed.tif", "equivalent_strain_exact.tif"):  # fmt: skip
        a, b = tifffile.imread(memory / name), tifffile.imread(tiled / name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        if a.dtype == np.float32:
            np.testing.assert_allclose(b, a, atol=1e-4, equal_nan=True, err_msg=name)
        else:
            assert np.mean(a != b) <= 1e-4, name
    text = (tiled / "report.md").read_text()
    assert "residual_slices.png" in text and "`residual_exact.tif`" in text


def test_tiled_evaluate_refuses_a_tiny_memory_limit_and_writes_nothing(scans, capsys):
    out = scans / "refused"
    code = _run(scans, out, "--max-memory", "1MB")
    captured = capsys.readouterr()
    assert code != 0
    assert "--max-memory" in captured.err and "estimated" in captured.err
    assert not out.exists()
    assert not [p for p in scans.iterdir() if p.name.startswith(".refused")]


def test_tiled_evaluate_with_a_specimen_region(scans, capsys):
    """--roi with --tiled (issue 26): the region read block by block, the in-memory numbers."""
    folder = scans
    rows = []
    for name, extra in (("memory_roi", []), ("tiled_roi", ["--tiled", "--block", "16"])):
        out = folder / name
        code = cli.main([
            "evaluate", str(folder / "ref.tif"), str(folder / "def.tif"),
            "--field", str(folder / "exact.npz"), "--roi", "4:28,6:26,", "--no-volumes",
            "--quiet", "--out-dir", str(out), *extra,
        ])  # fmt: skip
        assert code == 0, capsys.readouterr().err
        with open(out / "summary.csv", newline="") as stream:
            rows.append(next(csv.DictReader(stream)))
    for key in ("mean_residual", "background_used", "accuracy_index", "error_median"):
        assert float(rows[1][key]) == pytest.approx(float(rows[0][key]), rel=1e-5)
