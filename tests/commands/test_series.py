"""``series`` with ``correlate``'s placement and format options (commands/series.py)."""

import csv

import numpy as np
import pytest

from napari_dvc_correct.cli import main
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.placement import Box, grid_for_region
from napari_dvc_correct.io.formats import read_points
from napari_dvc_correct.io.npz import load_field

SHAPE = (36, 36, 36)
SHIFT = np.array([1.4, -0.6, 2.2])  # per state
DVC = ["--subvolume", "15", "--step", "6", "--quiet"]


def _write_states(folder, shape, margin, seed, field_of) -> list[str]:
    """States 0, 1, 2 of one textured sample as ``.npy`` files, state k moved by
    ``field_of(k)`` (``U_0→k`` in the cut volume's voxels), cut from a volume ``margin`` larger
    on every side."""
    big = synthetic.textured_volume(tuple(n + 2 * margin for n in shape), 2.0, seed=seed)
    crop = tuple(slice(margin, margin + n) for n in shape)
    paths = []
    for k in range(3):
        truth = field_of(k)
        moved = synthetic.deform_volume(big, lambda p, t=truth: t(np.asarray(p) - margin))
        path = folder / f"state{k}.npy"
        np.save(path, np.ascontiguousarray(moved[crop]))
        paths.append(str(path))
    return paths


@pytest.fixture(scope="module")
def volumes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("states")
    return _write_states(folder, SHAPE, 8, 21, lambda k: synthetic.translation(k * SHIFT))


def test_series_in_a_roi_written_as_spam(volumes, tmp_path):
    out_dir = tmp_path / "series"
    roi = "8:30,:,10:34"
    code = main(
        ["series", *volumes, "--out-dir", str(out_dir), "--roi", roi, "--out-format", "spam",
         *DVC]
    )  # fmt: skip
    assert code == 0
    names = sorted(p.name for p in out_dir.iterdir() if not p.name.startswith("."))
    assert names == [
        "increment_00_01.tsv", "increment_01_02.tsv", "state_01.tsv", "state_02.tsv",
        "summary.csv",
    ]  # fmt: skip
    origin, step, shape = grid_for_region(SHAPE, 15, 6, Box((8, 0, 10), (30, 36, 34)))
    axes = [o + s * np.arange(n) for o, s, n in zip(origin, step, shape)]
    expected = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    assert 8 < len(expected) < 8 * 8 * 8  # fewer nodes than on the whole volume
    for k in (1, 2):
        field = read_points(out_dir / f"state_{k:02d}.tsv", "spam")
        # the nodes of the grid in the box, as correlate --roi places them
        np.testing.assert_allclose(np.sort(field.points, axis=0), np.sort(expected, axis=0))
        assert np.all((field.points >= (8, 0, 10)) & (field.points < (30, 36, 34)))
        good = field.valid
        assert good.all()
        assert np.abs(field.u[good] - k * SHIFT).max() < 0.1
    with open(out_dir / "summary.csv") as stream:
        rows = list(csv.DictReader(stream))
    assert rows[2]["field_file"] == "state_02.tsv"


def test_series_at_points_follows_them_incrementally(volumes, tmp_path):
    points = np.array([[18.0, 18.0, 18.0], [14.5, 20.25, 16.0], [21.0, 12.0, 19.5]])
    points_file = tmp_path / "points.csv"
    np.savetxt(points_file, points, delimiter=",", header="z,y,x", comments="")
    out_dir = tmp_path / "series"
    code = main(["series", *volumes, "--out-dir", str(out_dir), "--points", str(points_file), *DVC])
    assert code == 0
    for k in (1, 2):
        field = read_points(out_dir / f"state_{k:02d}.csv", "table")
        np.testing.assert_allclose(field.points, points, atol=1e-9)  # the first state's points
        assert np.abs(field.u - k * SHIFT).max() < 0.05
    # the second increment was measured where the points are in state 1
    increment = read_points(out_dir / "increment_01_02.csv", "table")
    np.testing.assert_allclose(increment.points, points + SHIFT, atol=0.05)
    assert np.abs(increment.u - SHIFT).max() < 0.05


def test_series_grid_on_a_cylinder_keeps_the_npz_default(volumes, tmp_path):
    out_dir = tmp_path / "series"
    code = main(
        ["series", *volumes[:2], "--out-dir", str(out_dir), "--cylinder", "18,18,8",
         "--strategy", "total", *DVC]
    )  # fmt: skip
    assert code == 0
    field = load_field(out_dir / "state_01.npz")
    assert field.metadata["region"]["kind"] == "cylinder"
    y, x = np.meshgrid(*field.axis_coordinates()[1:], indexing="ij")
    outside = np.hypot(y - 18, x - 18) > 8
    assert outside.any() and not field.valid[:, outside].any()
    assert field.valid[:, ~outside].mean() > 0.9


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--roi", "40:50,:,:"], "no node fits along axis z"),
        (["--points", "{points}", "--self-correct"], "--self-correct"),
        (["--points", "{points}", "--out-format", "npz"], "npz holds grids"),
        (["--points", "{points}", "--roi", "0:30,:,:"], "not both"),
        (["--points", "{missing}"], "points file not found"),
        (["--points", "{points}", "--tiled"], "runs in memory only"),
        (["--points", "{points}", "--max-memory", "4GB"], "runs in memory only"),
    ],
)
def test_series_refuses_bad_placement_and_writes_nothing(volumes, tmp_path, capsys, extra, message):
    points_file = tmp_path / "points.csv"
    np.savetxt(points_file, [[18.0, 18.0, 18.0]], delimiter=",", header="z,y,x", comments="")
    extra = [e.format(points=points_file, missing=tmp_path / "none.csv") for e in extra]
    out_dir = tmp_path / "series"
    assert main(["series", *volumes, "--out-dir", str(out_dir), *extra, *DVC]) == 2
    assert message in capsys.readouterr().err
    assert not out_dir.exists()


def _same_summaries(a_path, b_path):
    """The two summary tables: the same rows and columns, numbers to 1e-4 relative (they are
    printed to 6 digits; see tests/tiled/test_series.py for why the runs agree)."""
    with open(a_path) as a_stream, open(b_path) as b_stream:
        a_rows, b_rows = list(csv.DictReader(a_stream)), list(csv.DictReader(b_stream))
    assert len(a_rows) == len(b_rows) and a_rows[0].keys() == b_rows[0].keys()
    for a, b in zip(a_rows, b_rows):
        for key in a:
            try:
                assert float(b[key]) == pytest.approx(float(a[key]), rel=1e-4, nan_ok=True), key
            except ValueError:  # not a number: file names, the strategy
                assert b[key] == a[key]


@pytest.mark.parametrize(
    "extra",
    [
        ["--strategy", "total", "--roi", "6:30,:,:"],
        ["--strategy", "incremental", "--self-correct", "--correct", "both", "--max-passes", "1"],
    ],
)
def test_series_tiled_writes_the_files_of_the_in_memory_series(volumes, tmp_path, capsys, extra):
    # IC-GN tolerance 1e-5, as in tests/tiled/: the converged fields do not depend on the start
    common = ["series", *volumes, "--tolerance", "1e-5", *extra, *DVC[:-1]]
    assert main([*common, "--out-dir", str(tmp_path / "a"), "--quiet"]) == 0
    capsys.readouterr()
    temporary = tmp_path / "temporary"
    temporary.mkdir()
    tiled = ["--tiled", "--batch", "2", "--workers", "2", "--temp-dir", str(temporary)]
    assert main([*common, "--out-dir", str(tmp_path / "b"), *tiled]) == 0  # not quiet: the plan
    assert "tiled series: correlation: estimated peak memory" in capsys.readouterr().err
    assert not any(temporary.iterdir())  # the warped volumes and masks are gone
    names = sorted(p.name for p in (tmp_path / "a").iterdir() if not p.name.startswith("."))
    assert names == sorted(p.name for p in (tmp_path / "b").iterdir() if not p.name.startswith("."))
    for name in names:
        if name.endswith(".npz"):
            a, b = load_field(tmp_path / "a" / name), load_field(tmp_path / "b" / name)
            assert b.metadata["tiled"]["batches"] > 1  # correlated in batches
            np.testing.assert_array_equal(b.status, a.status)
            np.testing.assert_array_equal(b.provenance, a.provenance)
            np.testing.assert_allclose(b.u, a.u, rtol=0, atol=1e-4)  # NaN where both are NaN
            assert b.metadata.get("series", {}).keys() == a.metadata.get("series", {}).keys()
    _same_summaries(tmp_path / "a" / "summary.csv", tmp_path / "b" / "summary.csv")


def test_series_tiled_refuses_a_run_over_max_memory_and_writes_nothing(volumes, tmp_path, capsys):
    out_dir = tmp_path / "series"
    code = main(["series", *volumes, "--out-dir", str(out_dir), "--max-memory", "1MB", *DVC])
    assert code == 2
    assert "--max-memory" in capsys.readouterr().err
    assert not out_dir.exists()


def test_series_report_plots_residual_p_and_error_against_the_load(volumes, tmp_path, capsys):
    """``--evaluate --loads``: each state against its own pair, the numbers of an evaluation of
    the written field, the states at the given loads, and a bad load list refused first."""
    from napari_dvc_correct.commands.evaluate import ready_for_evaluation
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields

    out_dir = tmp_path / "series"
    bad = ["series", *volumes, "--out-dir", str(out_dir), "--evaluate", "--loads", "1", *DVC]
    assert main(bad) == 2
    assert "one load value per deformed state" in capsys.readouterr().err
    assert not out_dir.exists()
    command = ["series", *volumes, "--out-dir", str(out_dir), "--strategy", "total", *DVC]
    assert main([*command, "--evaluate", "--loads", "0.5, 2", "--load-label", "force [kN]"]) == 0
    with open(out_dir / "series_evaluation.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert [(r["state"], r["tick"], r["load"]) for r in rows] == [
        ("1", "state 1", "0.5"),
        ("2", "state 2", "2"),
    ]
    reference = np.load(volumes[0])
    for k, row in enumerate(rows, start=1):
        field, _ = ready_for_evaluation(load_field(out_dir / f"state_{k:02d}.npz"), "f")
        item = evaluate_fields(reference, np.load(volumes[k]), {"f": field})["f"]
        assert float(row["accuracy"]) == pytest.approx(item.accuracy, abs=1e-5)
        assert float(row["mean_residual"]) == pytest.approx(item.mean_residual, rel=1e-5)
        assert float(row["error_median"]) == pytest.approx(item.error["median"], rel=1e-4)
        # a pure translation, well measured: p near 1, errors well under a voxel
        assert float(row["accuracy"]) > 0.9 and float(row["error_median"]) < 0.2
    png = (out_dir / "series_plot.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    page = (out_dir / "series_report.md").read_text()
    # the curve is named for what was evaluated (it read "field")
    assert "![series](series_plot.png)" in page and "| state 2 | 2 | total |" in page
    assert {row["field"] for row in rows} == {"total"}


BAND_SHAPE, BAND_WIDTH, BAND_SLIP = (40, 40, 40), 3.0, 3.0  # slip per state, voxels


def _band(k):
    """The known ``U_0→k`` of the bending series: a narrow shear band (half-width 3 voxels,
    well inside a 15-voxel subvolume, which a first-order match cannot follow) and a shift."""
    center = np.array(BAND_SHAPE) / 2
    shift = (0.6 * k, -0.4 * k, 0.8 * k)
    return synthetic.shear_band(center, width=BAND_WIDTH, slip=k * BAND_SLIP, shift=shift)


@pytest.fixture(scope="module")
def bending(tmp_path_factory):
    return _write_states(tmp_path_factory.mktemp("bending"), BAND_SHAPE, 12, 5, _band)


def test_a_corrected_series_report_has_the_uncorrected_and_corrected_curves(
    bending, tmp_path, capsys
):
    """``--self-correct --evaluate``: two rows per state, ``total`` (the series without
    correction, as a plain run writes it) and ``total, corrected``, each the evaluation of that
    field on its own pair; where the known field bends, the corrected one is closer to it."""
    from napari_dvc_correct.commands.evaluate import ready_for_evaluation
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields

    dvc = ["--strategy", "total", "--subvolume", "15", "--step", "5", "--quiet"]
    plain_dir, out_dir = tmp_path / "plain", tmp_path / "corrected"
    assert main(["series", *bending, "--out-dir", str(plain_dir), *dvc]) == 0
    command = ["series", *bending, "--out-dir", str(out_dir), *dvc, "--self-correct"]
    assert main([*command, "--max-passes", "1", "--evaluate"]) == 0
    printed = capsys.readouterr().out
    assert "state 2:" in printed and "(uncorrected " in printed
    with open(out_dir / "series_evaluation.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert [(r["state"], r["field"]) for r in rows] == [
        ("1", "total"), ("1", "total, corrected"), ("2", "total"), ("2", "total, corrected"),
    ]  # fmt: skip
    page = (out_dir / "series_report.md").read_text()
    assert "| state 2 |  | total |" in page and "| state 2 |  | total, corrected |" in page
    reference = np.load(bending[0])
    for k in (1, 2):
        plain = load_field(plain_dir / f"state_{k:02d}.npz")
        corrected = load_field(out_dir / f"state_{k:02d}.npz")
        assert corrected.metadata["series"]["corrected_total"] is True
        fields = {
            "total": ready_for_evaluation(plain, "a")[0],
            "total, corrected": ready_for_evaluation(corrected, "b")[0],
        }
        items = evaluate_fields(reference, np.load(bending[k]), fields)
        here = {r["field"]: r for r in rows if r["state"] == str(k)}
        for name in fields:
            item = items[name]
            assert float(here[name]["accuracy"]) == pytest.approx(item.accuracy, abs=1e-5)
            assert float(here[name]["mean_residual"]) == pytest.approx(item.mean_residual, rel=1e-5)
        # against the known field: the corrected total is closer where the band bends it
        truth = _band(k)(corrected.points.reshape(-1, 3))
        across = np.abs((corrected.points.reshape(-1, 3) - 20.0) @ (np.array([1, 0, 1]) / 2**0.5))
        band = across < BAND_WIDTH
        errors = {
            name: np.linalg.norm(field.u.reshape(-1, 3) - truth, axis=1)[band]
            for name, field in (("total", plain), ("total, corrected", corrected))
        }
        rmse = {name: float(np.sqrt(np.mean(e**2))) for name, e in errors.items()}
        assert rmse["total, corrected"] < 0.6 * rmse["total"], rmse
        assert float(here["total, corrected"]["accuracy"]) > float(here["total"]["accuracy"])


def test_the_help_says_what_the_strategies_and_the_field_format_are(capsys):
    # --strategy said only "default: incremental"; --out-format said "format of --out", an
    # option the series does not have

    from napari_dvc_correct import cli

    with pytest.raises(SystemExit):
        cli.main(["series", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "total: every state against the first" in text
    assert "incremental: each state against the one before" in text
    assert "format of --out " not in text and "format of --out (" not in text
    assert "format of the field files in --out-dir" in text
