"""The lattice inverse (engine/fields/inverse_lattice.py) against per-voxel Newton (FieldSpline.invert).

The accuracy asked is 1e-3 voxel (warp.INVERSE_ACCURACY) where the reference position lies in the
grid's hull: far below the DVC's own uncertainty, so the forward warp's gray values move by less
than 1e-3 times their gradient. Beyond the hull, where the field is an extrapolation, 10 times that
(inverse_lattice.OUTSIDE_RELAXATION) unless asked otherwise.
"""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample_with_gradient
from napari_dvc_correct.engine.fields import field_spline, warp
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.inverse_lattice import (
    OUTSIDE_RELAXATION,
    LatticeInverter,
    auto_stride,
)

ACCURACY = 1e-3
SHAPE = (48, 52, 56)
BOX = tuple(slice(0, n) for n in SHAPE)


def _spline(function, origin=(8.0, 8.0, 8.0), step=(8.0, 8.0, 8.0), shape=(5, 5, 6)):
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(function, field.points.reshape(*shape, 3))
    return field_spline.FieldSpline.from_field(field)


def _exact(spline, box=BOX):
    return spline.invert(warp.box_lattice(box))


def _error(fast, exact):
    return np.abs(fast.positions - exact).max(axis=1)


def _assert_close(fast, exact, spline):
    """Within the accuracy where ``X`` is in the hull, within the relaxed one elsewhere."""
    error = _error(fast, exact)
    hull = field_spline.inside_hull(spline, exact)
    assert error[hull].max() < ACCURACY
    assert error.max() < OUTSIDE_RELAXATION * ACCURACY
    return error


def _band(width=8.0, slip=6.0):
    return synthetic.shear_band((24.0, 26.0, 28.0), width=width, slip=slip, shift=(1.5, -2.0, 2.5))


def test_affine_field_is_interpolated_exactly_and_solved_only_at_the_coarse_nodes():
    gradient = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])
    spline = _spline(synthetic.affine(gradient, (24.0, 26.0, 28.0), (3.0, -4.0, 5.0)))
    exact, converged = _exact(spline)
    fast = spline.invert_lattice(BOX, accuracy=ACCURACY)
    assert converged.all() and fast.converged.all()
    assert _error(fast, exact).max() < 1e-9
    stride = auto_stride(spline.step)
    assert stride == 4
    index = warp.box_lattice(BOX).astype(int)
    on_node = np.all(index % stride == 0, axis=1)
    assert np.array_equal(fast.exact, on_node)  # no cell failed its check


def test_smooth_large_displacement_is_mostly_interpolated_within_the_accuracy():
    def smooth(points):
        rotation = synthetic.rotation_z(4.0, (24.0, 26.0, 28.0), (6.0, -7.5, 9.0))(points)
        wave = 0.3 * np.sin(np.asarray(points)[..., [2, 0, 1]] / 16.0)  # strains up to 2 %
        return rotation + wave

    spline = _spline(smooth)
    exact, converged = _exact(spline)
    fast = spline.invert_lattice(BOX, accuracy=ACCURACY)
    assert converged.all() and fast.converged.all()
    _assert_close(fast, exact, spline)
    assert fast.exact.mean() < 0.1


def test_narrow_shear_band_falls_back_to_newton_in_the_band_only():
    spline = _spline(_band(width=8.0, slip=6.0))  # band width = node step, 37 % peak shear
    exact, converged = _exact(spline)
    fast = spline.invert_lattice(BOX, accuracy=ACCURACY)
    assert converged.all() and fast.converged.all()
    _assert_close(fast, exact, spline)
    # without the check (any error accepted) the interpolation misses by more: the check is needed
    unchecked = spline.invert_lattice(BOX, accuracy=1e6)
    assert _error(unchecked, exact).max() > 3 * ACCURACY
    # the voxels solved by Newton lie in and near the band, the others are interpolated
    normal = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    distance = np.abs((exact - (24.0, 26.0, 28.0)) @ normal)
    hull = field_spline.inside_hull(spline, exact)
    near, far = distance < 8.0, (distance > 16.0) & hull
    assert fast.exact[near & hull].mean() > 0.8
    assert fast.exact[far].mean() < 0.1


def test_borders_and_extrapolation_beyond_the_hull():
    # the grid's hull covers the middle of the box only: a third of the voxels map outside it
    spline = _spline(_band(width=12.0, slip=4.0), shape=(4, 5, 5))
    exact, converged = _exact(spline)
    fast = spline.invert_lattice(BOX, accuracy=ACCURACY)
    assert converged.all() and fast.converged.all()
    _assert_close(fast, exact, spline)
    hull = field_spline.inside_hull(spline, exact)
    assert 0.1 < hull.mean() < 0.7
    assert np.array_equal(fast.in_hull, field_spline.inside_hull(spline, fast.positions))
    # asked for the same accuracy outside the hull, it gets it, with more Newton there
    strict = spline.invert_lattice(BOX, accuracy=ACCURACY, outside_accuracy=ACCURACY)
    assert _error(strict, exact).max() < ACCURACY
    assert strict.exact[~hull].mean() > fast.exact[~hull].mean() + 0.05


def test_points_that_do_not_converge_are_flagged_and_converged_points_solve_the_equation():
    spline = _spline(_band(width=3.0, slip=10.0))  # 170 % shear: the map folds over
    exact, converged = _exact(spline, BOX)
    assert 0 < (~converged).sum()
    fast = spline.invert_lattice(BOX, accuracy=ACCURACY)
    assert (~fast.converged).sum() > 0
    # where Newton fails in the hull, the fast path runs Newton too (outside it, it may accept
    # an interpolated root within the relaxed accuracy: checked with the residual below)
    assert fast.exact[~converged & fast.in_hull].all()
    targets = warp.box_lattice(BOX)
    good = fast.converged
    assert good.mean() > 0.9
    residual = np.abs(fast.positions + spline(fast.positions) - targets).max(axis=1)
    assert residual[good & fast.in_hull].max() < ACCURACY
    assert residual[good].max() < OUTSIDE_RELAXATION * ACCURACY
    # where the map folds over, x has several reference positions and Newton from two starts
    # may find two of them; elsewhere the answers agree
    error = _error(fast, exact)[converged & good]
    assert np.all((error < OUTSIDE_RELAXATION * ACCURACY) | (error > 0.5))
    assert 0.5 < np.mean(error < ACCURACY) < 0.95


def test_the_answer_does_not_depend_on_how_the_volume_is_cut_into_boxes():
    spline = _spline(_band(width=8.0, slip=6.0))
    whole = spline.invert_lattice(BOX)
    positions = whole.positions.reshape(*SHAPE, 3)
    for box in [
        (slice(3, 20), slice(0, 52), slice(5, 31)),
        (slice(21, 48), slice(17, 50), slice(31, 56)),
    ]:
        part = spline.invert_lattice(box)
        expected = positions[box].reshape(-1, 3)
        assert np.array_equal(part.positions, expected)
        assert np.array_equal(part.exact, whole.exact.reshape(SHAPE)[box].ravel())
    # plane ranges of one inverter (the coarse stage shared) give the same answer
    inverter = LatticeInverter(spline, BOX)
    planes = [inverter.solve(slice(z, min(z + 7, SHAPE[0]))).positions for z in range(0, 48, 7)]
    assert np.array_equal(np.concatenate(planes), whole.positions)


def test_forward_warp_equals_the_exact_warp_within_the_gradient_times_the_accuracy():
    spline = _spline(_band(width=8.0, slip=6.0))
    reference = synthetic.textured_volume(SHAPE, 2.0, seed=5)
    coefficients = prefilter(reference)
    sampler = warp.spline_sampler(coefficients)
    fast, fast_hull = warp.warp_forward_block(sampler, spline, BOX)
    exact, exact_hull = warp.warp_forward_block(sampler, spline, BOX, accuracy=None)
    assert np.array_equal(np.isnan(fast), np.isnan(exact))
    defined = np.isfinite(exact)
    assert defined.mean() > 0.7
    source, _ = _exact(spline)
    gradient = sample_with_gradient(coefficients, source[defined.ravel()])[:, 1:]
    hull = field_spline.inside_hull(spline, source[defined.ravel()])
    accuracy = np.where(hull, ACCURACY, OUTSIDE_RELAXATION * ACCURACY)
    bound = accuracy * np.abs(gradient).sum(axis=1) + 1e-5
    assert np.all(np.abs(fast - exact)[defined] <= bound)
    assert np.abs(fast - exact)[defined].max() > 0  # the two paths really differ
    assert (fast_hull != exact_hull).mean() < 1e-3


def test_invalid_arguments_are_refused():
    spline = _spline(_band())
    with pytest.raises(ValueError, match="stride"):
        spline.invert_lattice(BOX, stride=0)
    with pytest.raises(ValueError, match="accuracy"):
        spline.invert_lattice(BOX, accuracy=0.0)
    with pytest.raises(ValueError, match="accuracy"):
        spline.invert_lattice(BOX, outside_accuracy=-1.0)


@pytest.mark.parametrize("stride", [1, 4])
def test_the_coarse_stage_in_one_kernel_equals_its_three_kernels_one_by_one(stride):
    """``_coarse_stage`` (one cache load) gives what the Newton, check and combine kernels
    give called in turn, bit for bit."""
    from napari_dvc_correct.engine.fields import inverse_lattice as lattice

    spline = _spline(
        synthetic.shear_band((24.0, 26.0, 28.0), width=4.0, slip=3.0, shift=(0.4, -0.8, 1.1))
    )
    box = (slice(5, 40), slice(0, 52), slice(3, 50))
    inverter = LatticeInverter(spline, box, accuracy=ACCURACY, stride=stride)
    first_node = inverter.starts // stride - lattice.BELOW
    v = np.empty_like(inverter.v)
    ok = np.empty_like(inverter.node_ok)
    gain = np.empty(ok.shape)
    fail = np.zeros_like(inverter.fail)
    lattice._coarse_inverse(inverter.args, first_node, stride, 50, inverter.polish, v, ok, gain)
    if stride > 1:
        bad = np.empty(tuple(n + 1 for n in fail.shape), np.int64)
        limits = (
            ACCURACY / lattice.CHECK_SAFETY,
            OUTSIDE_RELAXATION * ACCURACY / lattice.CHECK_SAFETY,
        )
        lattice._check_points(
            inverter.args, spline.grid_shape, first_node, stride, *limits, v, gain, bad
        )
        lattice._combine(ok, gain, bad, fail)
        assert fail.any() and not fail.all()  # the band's cells fall back to Newton
    np.testing.assert_array_equal(inverter.v, v)
    np.testing.assert_array_equal(inverter.node_ok, ok)
    np.testing.assert_array_equal(inverter.fail, fail)
