"""spam TSV (io/formats/spam.py): spam's own layout, statuses, round trips."""

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.engine.fields.scattered import ScatteredField, to_grid
from napari_dvc_correct.io.formats import read_field, read_points, sniff_format, spam, write_field

HEADER = (
    "NodeNumber\tZpos\tYpos\tXpos\tFzz\tFzy\tFzx\tZdisp\tFyz\tFyy\tFyx\tYdisp\tFxz\tFxy\tFxx"
    "\tXdisp\terror\titerations\treturnStatus\tdeltaPhiNorm"
)


def spam_file(path, points, u, phi, status=None, pixel_search=False):
    """A TSV laid out as spam-ldic writes it (Phi rows: F row then the displacement)."""
    lines = [HEADER + ("\tpixelSearchCC" if pixel_search else "")]
    for n, (p, d, f) in enumerate(zip(points, u, phi)):
        rs = 2 if status is None else status[n]
        row = [n, *p, *f[0], d[0], *f[1], d[1], *f[2], d[2], 0.01, 5, rs, 0.0005]
        if pixel_search:
            row.append(0.93)
        lines.append("\t".join(f"{v:.7f}" if isinstance(v, float) else str(v) for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_translation_in_spam_layout_reads_as_z_y_x(known, tmp_path, grid_points):
    u = known.translation(grid_points)
    path = spam_file(tmp_path / "t.tsv", grid_points, u, np.broadcast_to(np.eye(3), (60, 3, 3)))
    assert sniff_format(path) == "spam"
    field = read_field(path)
    assert isinstance(field, DisplacementField)
    assert field.shape == (3, 4, 5) and field.origin == (8.0, 9.0, 10.0)
    assert field.step == (6.0, 5.0, 4.0)
    np.testing.assert_allclose(field.u[1, 2, 3], known.shift, atol=1e-7)
    np.testing.assert_allclose(field.gradient, 0.0, atol=1e-7)
    assert np.all(field.status == Status.CONVERGED)


def test_an_affine_field_in_spam_layout_gives_its_displacement_and_gradient(
    known, tmp_path, grid_points
):
    phi = np.broadcast_to(np.eye(3) + known.gradient, (60, 3, 3))  # spam's F is I + du/dX
    path = spam_file(tmp_path / "a.tsv", grid_points, known.affine(grid_points), phi)
    field = read_field(path)
    np.testing.assert_allclose(field.displacement, known.affine(field.points), atol=1e-6)
    np.testing.assert_allclose(field.gradient[2, 3, 4], known.gradient, atol=1e-7)


def test_spam_return_status_and_pixel_search_cc(known, tmp_path, grid_points):
    codes = np.array([2, 1, -1, -2, -3, 0, -5] + [2] * 53)
    path = spam_file(
        tmp_path / "ps.tsv",
        grid_points,
        known.translation(grid_points),
        np.broadcast_to(np.eye(3), (60, 3, 3)),
        status=codes,
        pixel_search=True,
    )
    points = read_points(path)
    expected = [
        Status.CONVERGED,
        Status.MAX_ITERATIONS,
        Status.DIVERGED,
        Status.SINGULAR,
        Status.OUT_OF_BOUNDS,
        Status.NOT_COMPUTED,
        Status.NOT_COMPUTED,
    ]
    assert points.status[:7].tolist() == [int(s) for s in expected]
    assert points.valid[:7].tolist() == [True, True, False, False, False, False, False]
    np.testing.assert_allclose(points.zncc, 0.93, atol=1e-6)
    assert points.iterations[0] == 5
    np.testing.assert_array_equal(spam.status_to_spam(points.status[:5]), codes[:5])


def test_bin_ratio_scales_positions_and_displacements(known, tmp_path, grid_points):
    path = spam_file(
        tmp_path / "b.tsv",
        grid_points,
        known.translation(grid_points),
        np.broadcast_to(np.eye(3), (60, 3, 3)),
    )
    points = spam.read(path, bin_ratio=2.0)
    np.testing.assert_allclose(points.points, grid_points * 2.0, atol=1e-6)
    np.testing.assert_allclose(points.u, np.broadcast_to(known.shift * 2.0, (60, 3)), atol=1e-6)


def test_grid_round_trip(known, tmp_path, grid_points):
    field = to_grid(
        ScatteredField(
            grid_points,
            known.affine(grid_points),
            gradient=np.broadcast_to(known.gradient, (60, 3, 3)),
        )
    )
    field.zncc[:] = 0.87
    field.status[0, 0, 0] = Status.LOW_ZNCC
    field.provenance[0, 0, 1] = Provenance.CORRECTED
    write_field(field, tmp_path / "out.tsv", "spam")
    back = read_field(tmp_path / "out.tsv")
    assert back.same_grid(field)
    # a failed node is written as NaN with its status, as in every export (issue 27 item 12)
    assert np.isnan(back.u[0, 0, 0]).all()  # (spam's F is written finite there)
    back.u[0, 0, 0], back.gradient[0, 0, 0] = field.u[0, 0, 0], field.gradient[0, 0, 0]
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)
    np.testing.assert_allclose(back.gradient, field.gradient, atol=1e-6)
    np.testing.assert_array_equal(back.status, field.status)
    np.testing.assert_array_equal(back.provenance, field.provenance)
    np.testing.assert_allclose(back.zncc, field.zncc, atol=1e-6)


def test_scattered_round_trip_keeps_the_points_and_their_order(known, tmp_path, scattered_points):
    field = ScatteredField(scattered_points, known.affine(scattered_points))
    spam.write(field, tmp_path / "s.tsv")
    back = read_points(tmp_path / "s.tsv")
    np.testing.assert_allclose(back.points, scattered_points, atol=1e-6)
    np.testing.assert_allclose(back.u, field.u, atol=1e-6)


def test_a_file_that_is_not_spam_is_refused(known, tmp_path):
    path = tmp_path / "x.tsv"
    path.write_text("a\tb\n1\t2\n")
    with pytest.raises(ValueError, match="not a spam TSV"):
        spam.read(path)
