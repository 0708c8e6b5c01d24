"""Our readers on files really written by spam, pyALDVC, CCPi/Bay ``dvc`` and OpenCorr.

The files and the known field of their test pair are in ``../shared/data/formats`` (see its
README): ``u(X) = t + G (X - c)`` in (z, y, x) voxels, with G neither isotropic nor symmetric, so
a reader that swaps axes, transposes the gradient or reads F as the displacement gradient fails.
The tolerances are the errors the README measured for each tool, with a margin. Every reader is
met here: spam TSV, pyALDVC ``.npz``/``.mat``/CSV, CCPi ``.disp``, OpenCorr CSV (the plain
table reader), and the napari reader that opens them all as field layers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from napari_dvc_correct._reader import napari_get_reader
from napari_dvc_correct.io.formats import read_field, read_points, sniff_format

FORMATS = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "formats"
pytestmark = pytest.mark.skipif(
    not (FORMATS / "truth.json").is_file(),
    reason=f"the other tools' real files are not here ({FORMATS}: ../shared is absent)",
)


def truth():
    known = json.loads((FORMATS / "truth.json").read_text())
    t, g, c = (np.asarray(known[k], np.float64) for k in ("t_zyx", "G_zyx", "c_zyx"))
    return (lambda points: t + (np.asarray(points) - c) @ g.T), g


# file, format sniffed, points, largest rms error per axis (voxels; the README's rms + margin)
ON_THE_TEST_PAIR = [
    ("spam/reg_ldic/ref-def-ldic.tsv", "spam", 125, 0.10),
    ("spam/pixelsearch_ldic/ref-def-ldic.tsv", "spam", 125, 0.10),
    ("spam/pixelsearch_ldic/ref-def-pixelSearch.tsv", "spam", 125, 0.40),
    ("spam/reg_ldic/ref-def-registration.tsv", "spam", 1, 0.03),
    ("pyaldvc/aldvc.npz", "aldvc", 125, 0.03),
    ("pyaldvc/aldvc.mat", "aldvc", 125, 0.03),
    ("pyaldvc/csv/aldvc_frame_01.csv", "table", 125, 0.03),
    ("ccpi_dvc/snow48/snow48.disp", "idvc", 125, 0.03),
]


@pytest.mark.parametrize(("name", "fmt", "count", "rms"), ON_THE_TEST_PAIR)
def test_real_files_give_the_known_field_in_z_y_x(name, fmt, count, rms):
    exact, _ = truth()
    path = FORMATS / name
    assert sniff_format(path) == fmt
    points = read_points(path)
    assert points.n_points == count and points.valid.all()
    error = points.u - exact(points.points)
    assert np.all(np.sqrt(np.mean(error**2, axis=0)) < rms), error
    # the other axis orders are far worse: an axis swap or 1-based positions would fail
    swapped = points.u[:, ::-1] - exact(points.points)
    assert np.sqrt(np.mean(swapped**2)) > np.sqrt(np.mean(error**2)) + 0.1


@pytest.mark.parametrize(
    ("name", "tolerance"),
    [("spam/reg_ldic/ref-def-registration.tsv", 0.002), ("pyaldvc/aldvc.npz", 0.003)],
)
def test_real_gradients_are_du_dX_in_z_y_x(name, tolerance):
    """spam writes F = I + du/dX (z, y, x rows); pyALDVC writes du/dX in x, y, z."""
    _, g = truth()
    gradient = np.median(read_points(FORMATS / name).gradient, axis=0)
    assert np.abs(gradient - g).max() < tolerance, gradient
    assert gradient[0, 2] > 0.008 and abs(gradient[2, 0]) < 0.002  # du_z/dX_x, not du_x/dX_z


def test_spam_ldic_is_a_regular_grid_one_spacing_from_the_origin():
    field = read_field(FORMATS / "spam/reg_ldic/ref-def-ldic.tsv")
    assert field.shape == (5, 5, 5) and field.origin == (8.0, 8.0, 8.0)
    assert field.step == (8.0, 8.0, 8.0)


def test_ccpi_failures_and_rows_out_of_order():
    """Rows are in processing order; status -1 (Range_Fail) is not a usable node, nor are the
    four rows 2-5 that report success with a zero objective at the search's start (1, -1, 0),
    0.4-1.3 voxel off (the README's degenerate rows)."""
    edge = read_points(FORMATS / "ccpi_dvc/snow48_edge/snow48_edge.disp")
    assert edge.n_points == 125 and int((~edge.valid).sum()) == 5
    ids = np.asarray(edge.metadata["source"]["point_ids"])
    assert sorted(ids[~edge.valid].tolist()) == [1, 2, 3, 4, 5]
    assert edge.metadata["source"]["degenerate_rows"] == 4
    exact, _ = truth()
    error = np.linalg.norm(edge.u - exact(edge.points), axis=1)
    assert np.all(error[np.isin(ids, [2, 3, 4, 5])] > 0.3)  # truly wrong: refused rightly
    assert np.max(error[edge.valid]) < 0.1  # every row kept is a measurement
    assert np.median(error[edge.valid]) < 0.05
    clean = read_points(FORMATS / "ccpi_dvc/snow48/snow48.disp")
    assert clean.metadata["source"]["degenerate_rows"] == 0
    repository = read_points(FORMATS / "ccpi_dvc/repo_dvc_test/completed_central_grid.disp")
    assert repository.n_points == 5  # 12 columns (with phi the psi), 1-based labels n
    # x, y, z of the file are numpy axes 2, 1, 0
    rows = np.loadtxt(FORMATS / "ccpi_dvc/repo_dvc_test/completed_central_grid.disp", skiprows=1)
    assert np.allclose(repository.points, rows[:, [3, 2, 1]])
    assert np.allclose(repository.u, rows[:, [8, 7, 6]])


@pytest.mark.parametrize("name", ["al_foam4_1_fftcc_icgn1_r30.csv",
                                  "al_foam4_1_fftcc_icgn1(gpu)_r30.csv"])  # fmt: skip
def test_opencorr_tables_are_read_by_name(name):
    """OpenCorr's columns x,y,z,u,v,w (u along x); the GPU file adds a ``feature`` column."""
    assert sniff_format(FORMATS / "opencorr" / name) == "table"
    points = read_points(FORMATS / "opencorr" / name)
    assert points.n_points == 5733
    assert np.allclose(points.points[0], [60.0, 35.0, 35.0])  # (z, y, x) of the first POI
    rows = np.genfromtxt(FORMATS / "opencorr" / name, delimiter=",", names=True, max_rows=3)
    assert np.allclose(points.u[:3], np.column_stack([rows["w"], rows["v"], rows["u"]]))
    table = np.genfromtxt(FORMATS / "opencorr" / name, delimiter=",", names=True)
    # its own quality columns are kept: ZNCC, and the IC-GN iterations ('iteration' was not
    # read; 33 points of the CPU file stopped at its max_iteration 20)
    np.testing.assert_allclose(points.zncc, table["ZNCC"], rtol=1e-6)
    np.testing.assert_array_equal(points.iterations, table["iteration"])


# file, the grid each tool was asked for: shape, origin and step (z, y, x voxels), nodes failed
ON_A_GRID = [
    ("spam/reg_ldic/ref-def-ldic.tsv", (5, 5, 5), 8.0, 8.0, 0, 0.10),
    ("spam/pixelsearch_ldic/ref-def-pixelSearch.tsv", (5, 5, 5), 8.0, 8.0, 0, 0.40),
    ("pyaldvc/aldvc.npz", (5, 5, 5), 11.0, 6.0, 0, 0.03),
    ("pyaldvc/aldvc.mat", (5, 5, 5), 11.0, 6.0, 0, 0.03),
    ("pyaldvc/csv/aldvc_frame_01.csv", (5, 5, 5), 11.0, 6.0, 0, 0.03),
    ("ccpi_dvc/snow48/snow48.disp", (5, 5, 5), 12.0, 6.0, 0, 0.03),
    ("ccpi_dvc/snow48_edge/snow48_edge.disp", (5, 5, 5), 12.0, 6.0, 5, 0.05),
]


@pytest.mark.parametrize(("name", "shape", "origin", "step", "failed", "rms"), ON_A_GRID)
def test_the_napari_reader_opens_real_fields_on_their_grid(name, shape, origin, step, failed, rms):
    """File > Open of another tool's field: |u| and the vectors placed at the tool's own nodes
    (scale = step, translate = origin), |u| the known field's there, a failed node left empty."""
    reader = napari_get_reader(str(FORMATS / name))
    assert reader is not None
    (magnitude, image, kind), (vectors, _, vector_kind) = reader(str(FORMATS / name))
    assert (kind, vector_kind) == ("image", "vectors")
    assert magnitude.shape == shape
    assert image["scale"] == (step,) * 3 and image["translate"] == (origin,) * 3
    assert len(vectors) == np.prod(shape) - failed  # an arrow per usable node
    exact, _ = truth()
    nodes = origin + step * np.stack(np.indices(shape), -1).reshape(-1, 3)
    expected = np.linalg.norm(exact(nodes), axis=1).reshape(shape)
    assert int(np.isnan(magnitude).sum()) == failed
    difference = (magnitude - expected)[~np.isnan(magnitude)]
    assert np.sqrt(np.mean(difference**2)) < rms * np.sqrt(3), difference


def test_the_napari_reader_refuses_the_repository_run_with_a_reason():
    """CCPi's repository example has five points in one plane: claimed by suffix, then refused
    with a message that says why no grid can be made."""
    path = FORMATS / "ccpi_dvc/repo_dvc_test/completed_central_grid.disp"
    reader = napari_get_reader(str(path))
    assert reader is not None
    with pytest.raises(ValueError, match="one plane or line"):
        reader(str(path))


@pytest.mark.parametrize(
    "name",
    [
        "opencorr/al_foam4_1_fftcc_icgn1_r30_time.csv",  # OpenCorr's timings
        "ccpi_dvc/snow48/snow48.stat",  # CCPi's run statistics
        "pyaldvc/aldvc_summary.json",  # pyALDVC's run summary
    ],
)
def test_the_tools_other_files_are_not_taken_for_fields(name):
    assert napari_get_reader(str(FORMATS / name)) is None
    with pytest.raises(ValueError):
        read_points(FORMATS / name)


def test_ccpi_input_points_open_as_points_not_as_a_field():
    """CCPi's ``grid.roi`` (input points, no displacement): a Points layer in z, y, x (x is the
    fastest of its labels 1..125), not a field."""
    path = FORMATS / "ccpi_dvc/snow48/grid.roi"
    [(data, _, kind)] = napari_get_reader(str(path))(str(path))
    assert kind == "points" and data.shape == (125, 3)
    np.testing.assert_array_equal(data[:2], [[12.0, 12.0, 12.0], [12.0, 12.0, 18.0]])
    with pytest.raises(ValueError):
        read_points(path)


def test_a_spam_registration_is_refused_as_a_field():
    """A spam-reg TSV is one Φ at the volume's centre: read as points it is that point (above),
    as a field it is refused with what to give instead. It opened as a 1-node layer, and
    ``correct`` asked for '--grid-step N' (the point sits at 23.5)."""
    path = FORMATS / "spam" / "reg_ldic" / "ref-def-registration.tsv"
    with pytest.raises(ValueError, match=r"single point \(z, y, x = \(23.5, 23.5, 23.5\)\).*"
                       "spam-reg registration.*-pf"):  # fmt: skip
        read_field(path)
