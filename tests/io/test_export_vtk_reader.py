"""VTK files read back by VTK's own readers (the ``vtk`` package, testing extra)."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField, Status
from napari_dvc_correct.engine.fields.scattered import ScatteredField
from napari_dvc_correct.io import export

vtk = pytest.importorskip("vtk")
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402


def grid_field():
    field = DisplacementField.zeros((7.0, 8.0, 9.0), (4.0, 5.0, 6.0), (3, 4, 5))
    rng = np.random.default_rng(0)
    field.u = rng.normal(size=field.u.shape)
    field.zncc[:] = rng.uniform(0.5, 1.0, field.shape)
    field.status[1, 2, 3] = Status.DIVERGED
    return field


def read(reader_class, path):
    reader = reader_class()
    reader.SetFileName(str(path))
    if hasattr(reader, "ReadAllScalarsOn"):  # legacy readers keep only the first array otherwise
        reader.ReadAllScalarsOn()
        reader.ReadAllVectorsOn()
    reader.Update()
    return reader.GetOutput()


@pytest.mark.parametrize(
    "suffix,reader", [(".vti", "vtkXMLImageDataReader"), (".vtk", "vtkStructuredPointsReader")]
)
def test_image_data_reads_back_in_vtk(tmp_path, suffix, reader):
    field = grid_field()
    path = export.export_vtk(field, tmp_path / f"f{suffix}", voxel_size=(2.0, 1.0, 0.5))
    image = read(getattr(vtk, reader), path)
    assert image.GetDimensions() == (5, 4, 3)
    np.testing.assert_allclose(image.GetOrigin(), [4.5, 8.0, 14.0])
    np.testing.assert_allclose(image.GetSpacing(), [3.0, 5.0, 8.0])
    data = image.GetPointData()
    vectors = vtk_to_numpy(data.GetArray("displacement"))
    # VTK point (i, j, k) = (x, y, z) index; its world position must carry that node's vector
    k, j, i = 3, 2, 1  # x, y, z indices
    pid = image.ComputePointId([k, j, i])
    np.testing.assert_allclose(image.GetPoint(pid), [9 * 0.5 + 6 * 0.5 * k, 8 + 5 * j, 14 + 8 * i])
    # the diverged node: NaN and its status, as in every export (issue 27 item 12)
    assert np.isnan(vectors[pid]).all()
    status = vtk_to_numpy(data.GetArray("status"))
    assert status[pid] == Status.DIVERGED
    k = 2  # a good node next to it carries its vector
    pid = image.ComputePointId([k, j, i])
    np.testing.assert_allclose(vectors[pid], field.u[i, j, k][::-1] * [0.5, 1.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(vtk_to_numpy(data.GetArray("zncc")), field.zncc.ravel(), rtol=1e-6)


def test_scattered_points_read_back_in_vtk(tmp_path):
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 30, size=(17, 3))
    u = rng.normal(size=(17, 3))
    field = ScatteredField(points, u, zncc=np.linspace(0.5, 1.0, 17))
    path = export.export_vtk_points(field, tmp_path / "p.vtu", voxel_size=0.1)
    grid = read(vtk.vtkXMLUnstructuredGridReader, path)
    assert grid.GetNumberOfPoints() == 17 and grid.GetNumberOfCells() == 17
    xyz = vtk_to_numpy(grid.GetPoints().GetData())
    np.testing.assert_allclose(xyz, points[:, ::-1] * 0.1, rtol=1e-6)
    vectors = vtk_to_numpy(grid.GetPointData().GetArray("displacement"))
    np.testing.assert_allclose(vectors, u[:, ::-1] * 0.1, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(vtk_to_numpy(grid.GetPointData().GetArray("zncc")), field.zncc)
    with pytest.raises(ValueError, match=".vtu"):
        export.export_vtk_points(field, tmp_path / "p.vtk")
