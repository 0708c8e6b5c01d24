"""The npe2 reader on other tools' field files (io.formats): they open as the plugin's layers."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct._reader import napari_get_reader
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.scattered import ScatteredField
from napari_dvc_correct.io.formats import write_field
from napari_dvc_correct.layers import field_of


@pytest.fixture
def field() -> DisplacementField:
    shape = (3, 4, 5)
    u = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1)
    return DisplacementField(origin=(7.0, 7.0, 7.0), step=(4.0, 4.0, 4.0), u=0.1 * u)


@pytest.mark.parametrize(
    "name,fmt",
    [
        ("ldic.tsv", "spam"),
        ("run.disp", "idvc"),
        ("r.mat", "aldvc"),
        ("r.npz", "aldvc"),
        ("f.csv", "table"),
    ],
)
def test_other_tools_fields_open_as_field_layers(field, tmp_path, name, fmt):
    path = tmp_path / name
    write_field(field, path, fmt)
    reader = napari_get_reader(str(path))
    assert reader is not None
    layers = reader(str(path))
    stem = path.stem
    names = [kwargs["name"] for _, kwargs, _ in layers]
    assert f"displacement ({stem})" in names and f"|u| ({stem})" in names
    for _data, kwargs, _layer_type in layers:
        assert kwargs["scale"] == (4.0, 4.0, 4.0) and kwargs["translate"] == (7.0, 7.0, 7.0)
        np.testing.assert_allclose(field_of(kwargs["metadata"]).u, field.u, atol=1e-6)


def test_scattered_points_open_on_a_grid(tmp_path):
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 20, size=(200, 3))
    path = tmp_path / "pts.csv"
    write_field(ScatteredField(points, np.tile([1.0, 2.0, 3.0], (200, 1))), path, "table")
    layers = napari_get_reader(str(path))(str(path))
    grid = field_of(layers[0][1]["metadata"])
    assert grid.metadata["scattered"]["interpolated"] > 0


def test_tables_and_mat_files_that_are_not_fields_are_declined(tmp_path):
    csv = tmp_path / "other.csv"
    csv.write_text("time,force\n0,1\n1,2\n")
    assert napari_get_reader(str(csv)) is None
    tsv = tmp_path / "other.tsv"
    tsv.write_text("a\tb\n1\t2\n")
    assert napari_get_reader(str(tsv)) is None
    from scipy.io import savemat

    savemat(tmp_path / "other.mat", {"a": np.zeros(3)})
    assert napari_get_reader(str(tmp_path / "other.mat")) is None


def test_a_ccpi_point_cloud_opens_as_a_points_layer(tmp_path):
    """A CCPi ``.roi`` (``n x y z``, no header) opens as a Points layer in z, y, x voxels, which
    the Correlate panel measures at; napari said 'No compatible readers are available'."""
    roi = tmp_path / "grid.roi"
    roi.write_text("1\t12\t14\t16\n2\t18\t14\t16.5\n")
    reader = napari_get_reader(str(roi))
    assert reader is not None
    [(data, kwargs, kind)] = reader(str(roi))
    assert kind == "points" and kwargs["name"] == "grid"
    np.testing.assert_array_equal(data, [[16.0, 14.0, 12.0], [16.5, 14.0, 18.0]])
    (tmp_path / "other.roi").write_text("an ImageJ ROI is binary\n")
    assert napari_get_reader(str(tmp_path / "other.roi")) is None
