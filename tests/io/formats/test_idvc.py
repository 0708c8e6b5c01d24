"""CCPi iDVC .disp (io/formats/idvc.py): x, y, z columns, status, objmin, round trips."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.fields.scattered import ScatteredField, to_grid
from napari_dvc_correct.io.formats import idvc, read_field, read_points, sniff_format, write_field


def disp_file(path, points, u, status=None, objmin=0.02, rotation=False):
    """A .disp as documented: n x y z status objmin u v w [phi theta psi], tab-separated."""
    header = "n\tx\ty\tz\tstatus\tobjmin\tu\tv\tw" + ("\tphi\ttheta\tpsi" if rotation else "")
    lines = [header]
    for n, (p, d) in enumerate(zip(points, u)):
        s = 0 if status is None else status[n]
        row = [n + 1, p[2], p[1], p[0], s, objmin, d[2], d[1], d[0]] + (
            [0.0] * 3 if rotation else []
        )
        lines.append("\t".join(str(v) for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_translation_in_idvc_layout_reads_as_z_y_x(known, tmp_path, scattered_points):
    path = disp_file(
        tmp_path / "r.disp", scattered_points, known.translation(scattered_points), rotation=True
    )
    assert sniff_format(path) == "idvc"
    points = read_points(path)
    np.testing.assert_allclose(points.points, scattered_points)
    np.testing.assert_allclose(points.u, np.broadcast_to(known.shift, (30, 3)))
    np.testing.assert_allclose(points.zncc, 0.99, atol=1e-6)  # znssd 0.02 = 2 (1 - 0.99)
    assert points.metadata["source"]["point_ids"][:3] == [1, 2, 3]


def test_an_affine_field_in_idvc_layout_on_a_grid(known, tmp_path, grid_points):
    path = disp_file(tmp_path / "a.disp", grid_points, known.affine(grid_points))
    field = read_field(path)
    assert field.shape == (3, 4, 5)
    np.testing.assert_allclose(field.displacement, known.affine(field.points), atol=1e-9)


def test_a_cloud_in_idvcs_order_x_slowest_is_our_grid(known, tmp_path, grid_points):
    """iDVC lays a regular cloud out x slowest, z fastest (pointcloud_conversion.py)."""
    order = np.lexsort((grid_points[:, 0], grid_points[:, 1], grid_points[:, 2]))
    cloud = grid_points[order]
    assert cloud[0, 2] == cloud[1, 2] and cloud[0, 0] != cloud[1, 0]  # z varies fastest
    path = disp_file(tmp_path / "x.disp", cloud, known.affine(cloud))
    field = read_field(path)
    assert field.shape == (3, 4, 5) and field.origin == (8.0, 9.0, 10.0)
    np.testing.assert_allclose(field.displacement, known.affine(field.points), atol=1e-9)


def test_idvc_status_codes(known, tmp_path, scattered_points):
    status = np.zeros(30, int)
    status[1], status[2] = -1, -2
    path = disp_file(
        tmp_path / "s.disp", scattered_points, known.translation(scattered_points), status
    )
    points = read_points(path)
    assert points.status[:3].tolist() == [Status.CONVERGED, Status.OUT_OF_BOUNDS, Status.DIVERGED]
    assert np.isnan(points.zncc[1])
    assert points.valid[:3].tolist() == [True, False, False]


def test_round_trip(known, tmp_path, grid_points, scattered_points):
    field = to_grid(ScatteredField(grid_points, known.affine(grid_points), zncc=np.full(60, 0.9)))
    write_field(field, tmp_path / "g.disp")
    back = read_field(tmp_path / "g.disp")
    assert back.same_grid(field)
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)
    np.testing.assert_allclose(back.zncc, 0.9, atol=1e-6)
    scattered = ScatteredField(scattered_points, known.affine(scattered_points))
    idvc.write(scattered, tmp_path / "s.disp")
    again = read_points(tmp_path / "s.disp")
    np.testing.assert_allclose(again.points, scattered_points, atol=1e-6)
    np.testing.assert_allclose(again.u, scattered.u, atol=1e-6)


def test_unknown_objective_is_refused(known, tmp_path, scattered_points):
    path = disp_file(tmp_path / "r.disp", scattered_points, known.translation(scattered_points))
    with pytest.raises(ValueError, match="objective"):
        idvc.read(path, objective="ssd")


def test_rows_that_report_a_perfect_match_at_the_search_start_are_failed():
    codes = np.array([0, 0, 0, 0, -1])
    objmin = np.array([0.0, 6e-4, 2e-15, 5e-4, 0.0])
    u_xyz = np.array([[1.0, -1.0, 0.0], [0.7, -1.1, 0.3], [2.0, 0.0, -1.0], [1.0, -1.0, 0.0],
                      [0.0, 0.0, 0.0]])  # fmt: skip
    assert idvc.degenerate_rows(codes, objmin, u_xyz).tolist() == [True, False, True, False, False]
    # a zero objective away from whole voxels is kept (not a search that read nothing)
    shifted = u_xyz + np.array([0.25, 0.0, 0.0])
    assert not idvc.degenerate_rows(codes, objmin, shifted).any()
    # on a noise-free pair every objective may be 0: nothing is called degenerate
    assert not idvc.degenerate_rows(codes, np.zeros(5), u_xyz).any()


def test_a_roi_point_cloud_reads_in_z_y_x(tmp_path):
    """``read_roi``: CCPi's ``n x y z`` rows (or ``x y z``) as z, y, x; other widths refused."""
    from napari_dvc_correct.io.formats.idvc import read_roi

    (tmp_path / "a.roi").write_text("1\t12\t14\t16\n7\t18.5\t14\t16\n")
    np.testing.assert_array_equal(read_roi(tmp_path / "a.roi"), [[16, 14, 12], [16, 14, 18.5]])
    (tmp_path / "b.roi").write_text("12 14 16\n")
    np.testing.assert_array_equal(read_roi(tmp_path / "b.roi"), [[16, 14, 12]])
    (tmp_path / "c.roi").write_text("1\t2\n")
    with pytest.raises(ValueError, match="c.roi: a .roi point cloud has rows 'n x y z'"):
        read_roi(tmp_path / "c.roi")
