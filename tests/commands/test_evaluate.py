"""The evaluate command: a report folder for one or several fields, and clear refusals."""

import csv

import numpy as np
import pytest
import tifffile

from napari_dvc_correct import cli
from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.io.npz import save_field

SHAPE = (32, 32, 32)


def grid_field(function, shape=SHAPE):
    origin, step, grid = grid_for_volume(shape, 9, 4)
    base = DisplacementField.zeros(origin, step, grid)
    return base.replace(u=synthetic.sample_displacement(function, base.points).reshape((*grid, 3)))


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans")
    clean = synthetic.two_phase_volume(SHAPE, seed=21)
    truth = synthetic.shear_band(center=(16.0, 16.0, 16.0), width=4.0, slip=3.0)
    reference = synthetic.add_noise(clean, 3.0, seed=22)
    deformed = synthetic.add_noise(synthetic.deform_volume(clean, truth), 3.0, seed=23)
    tifffile.imwrite(folder / "ref.tif", np.clip(reference, 0, 255).astype(np.uint8))
    np.save(folder / "def.npy", deformed)
    save_field(grid_field(truth), folder / "exact.npz")
    save_field(grid_field(synthetic.translation((0.0, 0.0, 0.0))), folder / "rigid.npz")
    save_field(
        grid_field(synthetic.translation((0.0, 0.0, 0.0)), shape=(64, 64, 64)), folder / "big.npz"
    )
    return folder


def test_evaluate_writes_a_report_for_two_fields(scans, capsys):
    out = scans / "report"
    code = cli.main(
        ["evaluate", str(scans / "ref.tif"), str(scans / "def.npy"),
         "--field", str(scans / "rigid.npz"), "--compare", str(scans / "exact.npz"),
         "--bins", "4", "--bin-by", "exact", "--quiet", "--out-dir", str(out)]
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "rigid: mean residual" in printed and "exact: mean residual" in printed
    assert "report.md" in printed
    with open(out / "summary.csv", newline="") as stream:
        rows = {row["field"]: row for row in csv.DictReader(stream)}
    assert float(rows["exact"]["accuracy_index"]) > float(rows["rigid"]["accuracy_index"])
    assert float(rows["exact"]["accuracy_index"]) == pytest.approx(1.0, abs=0.01)
    for name in ("report.md", "phases.csv", "strain_bins.csv", "accuracy_vs_strain.png",
                 "residual_vs_strain.png", "residual_slices.png", "residual_exact.tif",
                 "residual_rigid.tif", "labels_reference.tif", "labels_deformed.tif",
                 "equivalent_strain_exact.tif"):  # fmt: skip
        assert (out / name).stat().st_size > 0, name
    residual = tifffile.imread(out / "residual_exact.tif")
    assert residual.shape == SHAPE and np.nanmean(residual) < 6.0
    assert "ref.tif (32, 32, 32)" in (out / "report.md").read_text()


def test_user_thresholds_names_and_options(scans, capsys):
    out = scans / "user"
    code = cli.main(
        ["evaluate", str(scans / "ref.tif"), str(scans / "def.npy"),
         "--field", str(scans / "exact.npz"), "--names", "truth", "--phases", "125",
         "--phases-deformed", "130", "--mode", "loaded", "--gradient", "least-squares",
         "--strain", "green-lagrange", "--no-volumes", "--quiet", "--out-dir", str(out)]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    with open(out / "phases.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert float(rows[0]["gray_upper"]) == 125.0 and float(rows[2]["gray_upper"]) == 130.0
    assert not list(out.glob("*.tif"))
    assert "truth: mean residual" in capsys.readouterr().out
    assert "green-lagrange strain, least-squares gradient" in (out / "report.md").read_text()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--phases", "500"], "outside the gray range of the reference volume"),
        (["--phases", "150,120"], "strictly increasing"),
        (["--phases", "120,abc"], "--phases must be 'auto' or comma-separated"),
        (["--phases", "100.2,100.7"], "has no voxel in the reference volume"),
        (["--field", "big.npz"], "grid does not fit the volume"),
        (["--field", "missing.npz"], "field file not found"),
        (["--phase-pair", "0"], "--phase-pair must be two phase numbers"),
        (["--names", "a,b"], "2 names for 1 fields"),
        (["--bin-by", "nothing"], "bin_by names no evaluated field"),
        (["--strain-window", "4", "--gradient", "least-squares"], "odd number of nodes"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(scans, capsys, extra, message):
    out = scans / "never"
    arguments = ["evaluate", str(scans / "ref.tif"), str(scans / "def.npy"), "--field",
                 str(scans / "exact.npz"), "--quiet", "--out-dir", str(out)]  # fmt: skip
    extra = [str(scans / e) if e.endswith(".npz") else e for e in extra]
    code = cli.main(arguments + extra)
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not out.exists()


def test_r0_of_the_pair_a_specimen_region_and_the_error_estimate(scans, capsys):
    """--background-field makes r0 and p of a field evaluated alone those of the pair (issue
    26); --roi keeps phases and residuals to the specimen; the error estimate is printed and
    written."""
    common = [str(scans / "ref.tif"), str(scans / "def.npy"), "--quiet", "--no-volumes"]
    alone, both = scans / "alone", scans / "both"
    assert (
        cli.main(
            [
                "evaluate",
                *common,
                "--field",
                str(scans / "rigid.npz"),
                "--background-field",
                str(scans / "exact.npz"),
                "--out-dir",
                str(alone),
            ]
        )
        == 0
    )
    assert cli.main(["evaluate", *common, "--field", str(scans / "rigid.npz"),
                     "--compare", str(scans / "exact.npz"), "--out-dir", str(both)]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "error estimate median" in printed and "measured with 'exact'" in printed
    rows = []
    for out in (alone, both):
        with open(out / "summary.csv", newline="") as stream:
            rows.append({row["field"]: row for row in csv.DictReader(stream)})
    for key in ("background_used", "accuracy_index", "error_median"):
        assert float(rows[0]["rigid"][key]) == pytest.approx(float(rows[1]["rigid"][key]), rel=1e-9)
    assert float(rows[1]["rigid"]["error_median"]) > 3 * float(rows[1]["exact"]["error_median"])
    region = scans / "region"
    assert cli.main(["evaluate", *common, "--field", str(scans / "exact.npz"),
                     "--roi", "4:28,4:28,4:28", "--out-dir", str(region)]) == 0  # fmt: skip
    with open(region / "phases.csv", newline="") as stream:
        voxels = sum(
            int(row["voxels"]) for row in csv.DictReader(stream) if row["state"] == "reference"
        )
    assert voxels == 24**3
    code = cli.main(["evaluate", *common, "--field", str(scans / "exact.npz"), "--roi", "4:28,,",
                     "--cylinder", "16,16,10", "--out-dir", str(scans / "two")])  # fmt: skip
    assert code != 0 and "one specimen region" in capsys.readouterr().err


def test_the_help_names_every_volume_and_field_format(capsys):
    # the reference said "(TIFF, folder of TIFF slices, .npy)" and --field "(.npz)", though an
    # .npz array (rock.npz:reference) and other tools' fields (--format) are read
    from napari_dvc_correct import cli

    with pytest.raises(SystemExit):
        cli.main(["evaluate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "reference volume G (TIFF, folder of TIFF slices, .npy, .npz" in text
    assert "ours (.npz, .dvcfield) or another tool's (see --format)" in text
