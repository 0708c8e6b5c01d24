"""Exports: every format read back independently, with axis order and atomicity checked."""

from __future__ import annotations

import csv
import json
import re
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest
import tifffile

from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.io import export
from napari_dvc_correct.io.npz import load_field


@pytest.fixture
def field() -> DisplacementField:
    """A 3x4x5 grid where every value tells where it sits: u = (100 i, 10 j, k) + 0.25 component."""
    shape = (3, 4, 5)
    i, j, k = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    u = np.stack([100.0 * i + 0.25, 10.0 * j - 0.5, 1.0 * k + 0.125], axis=-1)
    status = np.zeros(shape, np.uint8)
    status[0, 0, 1] = Status.DIVERGED
    provenance = np.zeros(shape, np.uint8)
    provenance[0, 0, 1] = Provenance.REPLACED
    return DisplacementField(
        origin=(7.0, 8.0, 9.0),
        step=(4.0, 5.0, 6.0),
        u=u,
        zncc=np.linspace(0.5, 1.0, 60, dtype=np.float32).reshape(shape),
        status=status,
        iterations=np.arange(60, dtype=np.int32).reshape(shape),
        provenance=provenance,
        params={"subvolume": 15, "step": 4},
        metadata={"note": "test"},
    )


def test_hdf5_round_trip(field, tmp_path):
    strain = np.random.default_rng(0).random(field.shape)
    residual = np.ones((8, 9, 10), np.float32)
    path = export.export_hdf5(
        field,
        tmp_path / "f.h5",
        extra={"equivalent strain": strain},
        volumes={"residual": residual},
        voxel_size=(2.0, 1.0, 0.5),
    )
    with h5py.File(path, "r") as h5:
        group = h5["field"]
        np.testing.assert_array_equal(group["u"][()], field.u)
        np.testing.assert_array_equal(group["status"][()], field.status)
        np.testing.assert_array_equal(group["iterations"][()], field.iterations)
        np.testing.assert_array_equal(group["points"][()], field.points)
        np.testing.assert_array_equal(group.attrs["origin"], field.origin)
        np.testing.assert_array_equal(group.attrs["step"], field.step)
        np.testing.assert_array_equal(group.attrs["voxel_size"], [2.0, 1.0, 0.5])
        assert json.loads(group.attrs["params"]) == field.params
        assert json.loads(group.attrs["status_names"])[str(int(Status.DIVERGED))] == "diverged"
        np.testing.assert_array_equal(h5["grid/equivalent strain"][()], strain)
        np.testing.assert_array_equal(h5["volumes/residual"][()], residual)


def _read_vti(path):
    """Minimal reader for the raw-appended XML ImageData we write (independent of the writer)."""
    blob = path.read_bytes()
    start = blob.index(b'<AppendedData encoding="raw">')
    marker = blob.index(b"_", start) + 1
    header = blob[:start].decode("ascii") + "</VTKFile>"
    root = ET.fromstring(header)
    image = root.find("ImageData")
    arrays = {}
    dtypes = {"Float32": "<f4", "Float64": "<f8", "Int32": "<i4", "UInt8": "u1"}
    for node in image.iter("DataArray"):
        offset = marker + int(node.get("offset"))
        nbytes = int(np.frombuffer(blob[offset : offset + 8], "<u8")[0])
        data = np.frombuffer(blob[offset + 8 : offset + 8 + nbytes], dtypes[node.get("type")])
        arrays[node.get("Name")] = data.reshape(-1, int(node.get("NumberOfComponents")))
    return image.attrib, arrays


def test_vti_layout_is_what_paraview_expects(field, tmp_path):
    strain = np.arange(60, dtype=np.float64).reshape(field.shape) / 100
    path = export.export_vtk(
        field, tmp_path / "f.vti", extra={"eq strain": strain}, voxel_size=(2.0, 1.0, 0.5)
    )
    attrib, arrays = _read_vti(path)
    # extent, origin and spacing in x, y, z order; physical units
    assert attrib["WholeExtent"] == "0 4 0 3 0 2"
    np.testing.assert_allclose([float(v) for v in attrib["Origin"].split()], [4.5, 8.0, 14.0])
    np.testing.assert_allclose([float(v) for v in attrib["Spacing"].split()], [3.0, 5.0, 8.0])
    vectors = arrays["displacement"]
    assert vectors.shape == (60, 3)
    # VTK point index = k + nx * (j + ny * i): x fastest; vector components (ux, uy, uz)
    i, j, k = 2, 1, 3
    index = k + 5 * (j + 4 * i)
    np.testing.assert_allclose(vectors[index], field.u[i, j, k][::-1] * [0.5, 1.0, 2.0])
    np.testing.assert_array_equal(arrays["status"].ravel(), field.status.ravel())
    np.testing.assert_allclose(arrays["eq_strain"].ravel(), strain.ravel())
    np.testing.assert_allclose(arrays["zncc"].ravel(), field.zncc.ravel())


def test_legacy_vtk_layout(field, tmp_path):
    path = export.export_vtk(field, tmp_path / "f.vtk")
    blob = path.read_bytes()
    head = blob[:300].decode("ascii", errors="replace")
    assert "DATASET STRUCTURED_POINTS" in head
    assert "DIMENSIONS 5 4 3" in head
    assert re.search(r"ORIGIN 9\.0 8\.0 7\.0", head)
    assert re.search(r"SPACING 6\.0 5\.0 4\.0", head)
    start = blob.index(b"VECTORS displacement float\n") + len(b"VECTORS displacement float\n")
    vectors = np.frombuffer(blob[start : start + 60 * 12], ">f4").reshape(60, 3)
    np.testing.assert_allclose(vectors, field.u.reshape(-1, 3)[:, ::-1])
    start = blob.index(b"SCALARS status unsigned_char 1\nLOOKUP_TABLE default\n")
    start += len(b"SCALARS status unsigned_char 1\nLOOKUP_TABLE default\n")
    status = np.frombuffer(blob[start : start + 60], "u1")
    np.testing.assert_array_equal(status, field.status.ravel())


def test_tiff_stacks_per_component(field, tmp_path):
    written = export.export_tiff(
        field, tmp_path / "run.tif", extra={"eps": np.full(field.shape, 0.5)}, voxel_size=2.0
    )
    names = sorted(p.name for p in written)
    assert names == sorted(
        f"run_{q}.tif" for q in ("uz", "uy", "ux", "magnitude", "zncc", "status", "eps")
    )
    np.testing.assert_allclose(tifffile.imread(tmp_path / "run_uy.tif"), field.u[..., 1])
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "run_status.tif"), field.status)
    with tifffile.TiffFile(tmp_path / "run_ux.tif") as tif:
        info = json.loads(tif.imagej_metadata["Info"])
        assert tif.imagej_metadata["spacing"] == pytest.approx(8.0)  # step z * voxel size
    assert info["scale"] == [8.0, 10.0, 12.0]
    assert info["translate"] == [14.0, 16.0, 18.0]


def test_volume_tiff_rejects_2d(tmp_path):
    with pytest.raises(ValueError, match="3-D"):
        export.export_volume_tiff(np.zeros((4, 4)), tmp_path / "x.tif")
    assert not (tmp_path / "x.tif").exists()


def test_csv_rows(field, tmp_path):
    path = export.export_csv(field, tmp_path / "f.csv", extra={"eps": np.full(field.shape, 0.1)})
    with open(path, newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == field.n_points
    row = rows[1]  # node (0, 0, 1)
    assert [float(row[c]) for c in ("z", "y", "x")] == [7.0, 8.0, 15.0]
    assert [float(row[c]) for c in ("uz", "uy", "ux")] == [0.25, -0.5, 1.125]
    assert row["status_name"] == "diverged"
    assert row["provenance_name"] == "replaced"
    assert float(row["eps"]) == pytest.approx(0.1)
    assert int(rows[-1]["iterations"]) == 59


def test_export_field_dispatch_and_unknown_suffix(field, tmp_path):
    (written,) = export.export_field(field, tmp_path / "f.npz")
    np.testing.assert_array_equal(load_field(written).u, field.u)
    assert len(export.export_field(field, tmp_path / "f.tiff")) == 6
    with pytest.raises(ValueError, match="unknown export format"):
        export.export_field(field, tmp_path / "f.xyz")


def test_extra_with_wrong_shape_is_refused(field, tmp_path):
    with pytest.raises(ValueError, match="grid shape"):
        export.export_csv(field, tmp_path / "f.csv", extra={"bad": np.zeros(3)})
    assert list(tmp_path.iterdir()) == []


def test_failed_export_leaves_the_old_file(field, tmp_path, monkeypatch):
    path = tmp_path / "f.vti"
    export.export_vtk(field, path)
    before = path.read_bytes()

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(export, "_write_vti", broken)
    with pytest.raises(OSError, match="disk full"):
        export.export_vtk(field.replace(u=field.u * 2), path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.vti"]


def test_the_uncertainty_travels_to_csv_vtk_and_tiff(field, tmp_path):
    sigma = np.random.default_rng(7).uniform(0.01, 0.2, (*field.shape, 3))
    sigma[0, 0, 0] = np.nan  # a node without a measured value
    with_sigma = field.replace(uncertainty=sigma)
    rows = list(csv.DictReader(open(export.export_csv(with_sigma, tmp_path / "f.csv"))))
    assert float(rows[1]["uncertainty_uy"]) == pytest.approx(sigma.reshape(-1, 3)[1, 1], rel=1e-6)
    assert rows[0]["uncertainty_uz"] == "nan"
    written = export.export_tiff(with_sigma, tmp_path / "f.tif")
    stack = tifffile.imread(tmp_path / "f_uncertainty_ux.tif")
    assert any(p.name == "f_uncertainty_ux.tif" for p in written)
    np.testing.assert_allclose(stack[1:, ...], sigma[1:, ..., 2].astype(np.float32))
    vti = (export.export_vtk(with_sigma, tmp_path / "f.vti")).read_bytes()
    assert b"uncertainty_uz" in vti and b"uncertainty_ux" in vti
    assert "uncertainty_uz" not in open(export.export_csv(field, tmp_path / "g.csv")).readline()


def test_every_export_marks_a_failed_node_the_same_way(tmp_path):
    """Issue 27 item 12: a low-ZNCC node (not filled in) is NaN, next to its status, in every
    export, as in the .npz's flat ``displacement``; a filled-in node keeps its value."""
    import csv as csv_module

    import h5py
    import tifffile

    from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
    from napari_dvc_correct.io.export import export_field
    from napari_dvc_correct.io.formats import read_points, write_field

    field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (2, 2, 2))
    field.u[...] = (0.1, 0.2, 0.3)
    field.zncc[...] = 0.99
    field.status[0, 0, 0], field.zncc[0, 0, 0] = Status.LOW_ZNCC, 0.3
    field.status[1, 1, 1], field.provenance[1, 1, 1] = Status.OUTLIER_REPLACED, Provenance.REPLACED
    assert np.isnan(field.measured_displacement[0]).all()
    export_field(field, tmp_path / "f.h5")
    with h5py.File(tmp_path / "f.h5") as h5:
        assert (
            np.isnan(h5["field/u"][0, 0, 0]).all() and np.isnan(h5["field/displacement"][0]).all()
        )
        assert h5["field/status"][0, 0, 0] == Status.LOW_ZNCC
        assert np.isfinite(h5["field/u"][1, 1, 1]).all()
    export_field(field, tmp_path / "f.csv")
    with open(tmp_path / "f.csv", newline="") as stream:
        rows = list(csv_module.DictReader(stream))
    assert rows[0]["uz"] == "nan" and rows[0]["status_name"] == "low zncc"
    assert float(rows[7]["uz"]) == 0.1 and rows[7]["provenance_name"] == "replaced"
    export_field(field, tmp_path / "f.tif")
    assert np.isnan(tifffile.imread(tmp_path / "f_uz.tif")[0, 0, 0])
    assert tifffile.imread(tmp_path / "f_status.tif")[0, 0, 0] == Status.LOW_ZNCC
    for fmt, suffix in [("spam", ".tsv"), ("table", ".csv"), ("idvc", ".disp"),
                        ("aldvc", ".mat"), ("aldvc", ".npz")]:  # fmt: skip
        write_field(field, tmp_path / f"w_{fmt}{suffix}", fmt)
        back = read_points(tmp_path / f"w_{fmt}{suffix}", fmt)
        assert np.isnan(back.u[0]).all() and not back.valid[0], fmt
        assert np.isfinite(back.u[7]).all(), fmt
    assert np.isfinite(field.u).all()  # the field itself is not changed


def test_the_error_estimate_of_an_evaluation_travels_to_every_export(field, tmp_path):
    """Evaluate leaves its per-node error estimate on the field (issue 26): a CSV column, a
    TIFF stack, a VTK array and a View quantity."""
    from napari_dvc_correct.engine.evaluation.error_estimate import attach_estimate, estimate_of
    from napari_dvc_correct.quantities import available_quantities, quantity_values

    estimate = np.random.default_rng(3).uniform(0.0, 1.0, field.shape)
    estimate[0, 0, 0] = np.nan
    marked = field.replace(metadata=dict(field.metadata))
    attach_estimate(marked, estimate, background_residual=2.0)
    np.testing.assert_allclose(estimate_of(marked), estimate, atol=1e-6)
    rows = list(csv.DictReader(open(export.export_csv(marked, tmp_path / "f.csv"))))
    assert float(rows[1]["error_estimate"]) == pytest.approx(estimate.reshape(-1)[1], abs=1e-6)
    assert rows[0]["error_estimate"] == "nan"
    written = export.export_tiff(marked, tmp_path / "f.tif")
    assert any(p.name == "f_error_estimate.tif" for p in written)
    assert b"error_estimate" in export.export_vtk(marked, tmp_path / "f.vti").read_bytes()
    assert "error estimate" in available_quantities(marked)
    assert "error estimate" not in available_quantities(field)
    np.testing.assert_allclose(
        quantity_values(marked, "error estimate"), estimate, atol=1e-6, equal_nan=True
    )
