"""pyALDVC .npz and ALDVC .mat (io/formats/aldvc.py): x, y, z layouts, 0/1-based, round trips."""

import numpy as np
import pytest
from scipy.io import savemat

from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.fields.scattered import ScatteredField, to_grid
from napari_dvc_correct.io.formats import aldvc, read_field, read_points, sniff_format, write_field


def xyz(points_zyx):
    return np.column_stack([points_zyx[:, 2], points_zyx[:, 1], points_zyx[:, 0]])


def pyaldvc_npz(path, points, u, gradient_xyz, status=None):
    """As pyALDVC's export_npz writes: coordinates [x, y, z] 0-based, U_1 [u, v, w]."""
    n = len(points)
    np.savez_compressed(
        path,
        coordinates=xyz(points),
        U_1=xyz(u),
        F_1=np.broadcast_to(gradient_xyz, (n, 3, 3)),
        zncc_1=np.full(n, 0.91),
        status_1=np.zeros(n, np.int8) if status is None else status,
        grid_shape=np.array([3, 4, 5]),
        para_json=np.array('{"winsize": [32, 32, 32], "winstepsize": [8, 8, 8]}'),
    )
    return path


def test_a_translation_in_pyaldvc_npz_reads_as_z_y_x(known, tmp_path, grid_points):
    path = pyaldvc_npz(
        tmp_path / "r.npz", grid_points, known.translation(grid_points), np.zeros((3, 3))
    )
    assert sniff_format(path) == "aldvc"
    field = read_field(path)
    assert field.shape == (3, 4, 5) and field.origin == (8.0, 9.0, 10.0)
    np.testing.assert_allclose(field.u[2, 1, 0], known.shift)
    assert field.params == {"subvolume": 33, "step": 8}


def test_an_affine_field_in_pyaldvc_npz(known, tmp_path, grid_points):
    path = pyaldvc_npz(
        tmp_path / "a.npz", grid_points, known.affine(grid_points), known.gradient[::-1, ::-1]
    )
    field = read_field(path)
    np.testing.assert_allclose(field.displacement, known.affine(field.points), atol=1e-12)
    np.testing.assert_allclose(field.gradient[0, 0, 0], known.gradient, atol=1e-12)
    np.testing.assert_allclose(field.zncc, 0.91, atol=1e-6)


def test_pyaldvc_status_codes(known, tmp_path, grid_points):
    status = np.zeros(60, np.int8)
    status[:8] = np.arange(8)
    path = pyaldvc_npz(
        tmp_path / "s.npz",
        grid_points,
        known.affine(grid_points),
        known.gradient[::-1, ::-1],
        status,
    )
    points = read_points(path)
    expected = [
        "CONVERGED",
        "MAX_ITERATIONS",
        "OUT_OF_BOUNDS",
        "MASKED",
        "SINGULAR",
        "DIVERGED",
        "MASKED",
        "DIVERGED",
    ]
    assert points.status[:8].tolist() == [int(Status[name]) for name in expected]


def test_an_affine_field_in_matlab_aldvc_layout(known, tmp_path, grid_points):
    """MATLAB ALDVC: 1-based coordinatesFEM [x y z], interleaved U and column-major F."""
    n = len(grid_points)
    u_interleaved = xyz(known.affine(grid_points)).reshape(-1, 1)  # [u1 v1 w1 u2 ...]
    f_interleaved = np.tile(known.gradient[::-1, ::-1].T.reshape(-1), n).reshape(
        -1, 1
    )  # [F11 F21 F31 F12 ...]
    disp = np.empty((1,), dtype=object)
    disp[0] = {"U": u_interleaved}
    grad = np.empty((1,), dtype=object)
    grad[0] = {"F": f_interleaved}
    savemat(
        tmp_path / "results_ws32_st8.mat",
        {
            "DVCpara": {
                "winsize": np.array([32.0, 32.0, 32.0]),
                "winstepsize": np.array([8.0] * 3),
            },
            "DVCmesh": {"coordinatesFEM": xyz(grid_points) + 1.0},
            "ResultDisp": disp,
            "ResultDefGrad": grad,
        },
    )
    field = read_field(tmp_path / "results_ws32_st8.mat")
    assert field.origin == (8.0, 9.0, 10.0)  # 1-based in the file
    np.testing.assert_allclose(field.displacement, known.affine(field.points), atol=1e-12)
    np.testing.assert_allclose(field.gradient[1, 1, 1], known.gradient, atol=1e-12)


@pytest.mark.parametrize("suffix", [".npz", ".mat"])
def test_round_trip(known, tmp_path, grid_points, scattered_points, suffix):
    grid_field = to_grid(
        ScatteredField(
            grid_points,
            known.affine(grid_points),
            gradient=np.broadcast_to(known.gradient, (60, 3, 3)),
        )
    )
    grid_field.zncc[:] = 0.8
    grid_field.status[0, 0, 0] = Status.LOW_ZNCC
    write_field(grid_field, tmp_path / f"g{suffix}", "aldvc")
    back = read_field(tmp_path / f"g{suffix}", "aldvc")
    assert back.same_grid(grid_field)
    # a failed node is written as NaN with its status, as in every export (issue 27 item 12)
    assert np.isnan(back.u[0, 0, 0]).all() and np.isnan(back.gradient[0, 0, 0]).all()
    back.u[0, 0, 0], back.gradient[0, 0, 0] = grid_field.u[0, 0, 0], grid_field.gradient[0, 0, 0]
    np.testing.assert_allclose(back.u, grid_field.u, atol=1e-6)
    np.testing.assert_allclose(back.gradient, grid_field.gradient, atol=1e-6)
    np.testing.assert_array_equal(back.status, grid_field.status)
    scattered = ScatteredField(scattered_points, known.affine(scattered_points))
    aldvc.write(scattered, tmp_path / f"s{suffix}")
    again = read_points(tmp_path / f"s{suffix}", "aldvc")
    np.testing.assert_allclose(again.points, scattered_points, atol=1e-6)
    np.testing.assert_allclose(again.u, scattered.u, atol=1e-6)


def test_an_npz_of_another_kind_is_refused(known, tmp_path):
    np.savez(tmp_path / "x.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="neither ours"):
        sniff_format(tmp_path / "x.npz")


def test_frame_pairs_are_chosen_among_those_the_file_holds(tmp_path, capsys):
    """A .mat or .npz of several frame pairs: the pair asked is read, a pair it does not hold
    is refused naming those it does ('--frame-pair 0' read a .mat's last pair, 3 of 2 gave
    'IndexError: list index out of range'), and the commands say which pair they read."""
    from argparse import Namespace

    from napari_dvc_correct.commands._field_formats import read_input_field

    coords = np.array([[x, y, z] for z in (4.0, 10.0) for y in (4.0, 10.0) for x in (4.0, 10.0)])
    pairs = [np.tile([0.5, -0.25, 1.0], (8, 1)), np.tile([1.5, 0.75, -2.0], (8, 1))]
    cells = np.empty(2, dtype=object)
    cells[0], cells[1] = pairs
    mat = tmp_path / "run.mat"
    savemat(mat, {"coordinatesFEM": coords, "ResultDisp": cells, "winsize": 12})
    npz = tmp_path / "run.npz"
    np.savez(npz, coordinates=coords, U_1=pairs[0], U_2=pairs[1])
    for path in (mat, npz):
        for frame in (1, 2):
            u = read_points(path, frame=frame).u
            np.testing.assert_allclose(u, pairs[frame - 1][:, ::-1])  # x, y, z -> z, y, x
        for frame in (0, 3, -1):
            with pytest.raises(ValueError, match=r"holds 2 frame pair\(s\) \(1, 2\)"):
                read_points(path, frame=frame)
        args = Namespace(format="auto", frame_pair=2, command="correct")
        read_input_field(args, str(path))
        assert "holds 2 frame pairs: read pair 2" in capsys.readouterr().err
