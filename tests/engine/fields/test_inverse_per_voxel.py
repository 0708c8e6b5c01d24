"""The fused forward warp (engine/fields/inverse_per_voxel.py: LatticeInverter.warp) against the two-pass one.

``warp`` samples ``G`` while it makes the positions, which never leave a row buffer; it must give
the positions of ``solve`` bit for bit (one code makes both) and ``interpolation.sample``'s values
at them to float32 rounding (another summation order: the four-wide row sums of engine/correlation/simd.py).
"""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
from napari_dvc_correct.engine.fields import warp
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.field_spline import FieldSpline
from napari_dvc_correct.engine.fields.inverse_lattice import LatticeInverter

SHAPE = (40, 44, 48)
BOX = tuple(slice(0, n) for n in SHAPE)
#: float32 rounding of a 64-tap sum of values of order 1, summed in another order
ROUNDING = 2e-6


@pytest.fixture(scope="module")
def case():
    centre = (20.0, 22.0, 24.0)
    band = synthetic.shear_band(centre, width=8.0, slip=6.0, shift=(1.5, -2.0, 2.5))
    field = DisplacementField.zeros((8.0, 8.0, 8.0), (8.0, 8.0, 8.0), (4, 4, 5))
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(4, 4, 5, 3))
    reference = synthetic.textured_volume(SHAPE, 2.0, seed=3)
    return FieldSpline.from_field(field), prefilter(reference)


def _two_pass(inverter, coefficients, planes=None):
    inverse = inverter.solve(planes)
    values = sample(coefficients, inverse.positions, cval=np.nan)
    values[~inverse.converged] = np.nan
    return values, inverse


def test_fused_warp_samples_the_positions_of_solve(case):
    spline, coefficients = case
    inverter = LatticeInverter(spline, BOX)
    values, in_hull = inverter.warp(coefficients)
    expected, inverse = _two_pass(inverter, coefficients)
    expected = expected.reshape(SHAPE)
    assert values.shape == SHAPE and values.dtype == np.float32
    assert np.array_equal(in_hull.ravel(), inverse.in_hull)
    assert np.array_equal(np.isnan(values), np.isnan(expected))
    # voxels whose source leaves G (NaN), voxels sampled near G's faces (mirrored taps), and
    # voxels solved by Newton in failed cells are all present
    assert 0.01 < np.isnan(values).mean() < 0.5
    assert 0.05 < inverse.exact.mean() < 0.9
    defined = np.isfinite(expected)
    difference = np.abs(values - expected)[defined]
    assert difference.max() < ROUNDING
    assert difference.max() > 0  # really another summation


def test_plane_ranges_and_boxes_give_the_same_values_bit_for_bit(case):
    spline, coefficients = case
    whole, whole_hull = LatticeInverter(spline, BOX).warp(coefficients)
    inverter = LatticeInverter(spline, BOX)
    parts = [inverter.warp(coefficients, slice(z, min(z + 7, SHAPE[0]))) for z in range(0, 40, 7)]
    assert np.array_equal(np.concatenate([p[0] for p in parts]), whole, equal_nan=True)
    assert np.array_equal(np.concatenate([p[1] for p in parts]), whole_hull)
    box = (slice(5, 31), slice(3, 44), slice(13, 30))  # starts off the coarse lattice
    part, part_hull = LatticeInverter(spline, box).warp(coefficients)
    assert np.array_equal(part, whole[box], equal_nan=True)
    assert np.array_equal(part_hull, whole_hull[box])


def test_warp_forward_uses_the_fused_path_with_an_in_memory_sampler(case):
    spline, coefficients = case
    sampler = warp.spline_sampler(coefficients)
    values, in_hull = warp.warp_forward_block(sampler, spline, BOX)
    fused, fused_hull = LatticeInverter(spline, BOX).warp(coefficients)
    assert np.array_equal(values, fused, equal_nan=True)
    assert np.array_equal(in_hull, fused_hull)
    # any other sampler gets the two-pass path: the same values to float32 rounding
    lazy, lazy_hull = warp.warp_forward_block(lambda p: sampler(p), spline, BOX)
    assert np.array_equal(np.isnan(lazy), np.isnan(values))
    assert np.nanmax(np.abs(lazy - values)) < ROUNDING
    assert np.array_equal(lazy_hull, in_hull)


# --- the interpolation weights between coarse nodes ---------------------------------------------
def test_lagrange_weights_reproduce_polynomials_up_to_degree_five():
    from napari_dvc_correct.engine.fields import inverse_per_voxel

    nodes = np.arange(-2.0, 4.0)
    np.testing.assert_array_equal(inverse_per_voxel.lagrange_weights(0.0), [0, 0, 1, 0, 0, 0])
    for t in (0.1, 0.5, 0.93):
        weights = np.asarray(inverse_per_voxel.lagrange_weights(t))
        for degree in range(6):
            assert weights @ nodes**degree == pytest.approx(t**degree, abs=1e-12)
    # per voxel of an axis: the first of its six coarse nodes and its position in the cell
    node, weight = inverse_per_voxel.axis_weights(3, 6, 4)  # voxels 3..8, a node every 4
    assert node.tolist() == [0, 1, 1, 1, 1, 2]  # cells 0, 1, 1, 1, 1, 2 from the first (0)
    np.testing.assert_allclose(weight[1], inverse_per_voxel.lagrange_weights(0.0))
    np.testing.assert_allclose(weight[2], inverse_per_voxel.lagrange_weights(0.25))


@pytest.mark.parametrize("start, count, stride", [(0, 57, 4), (3, 6, 4), (13, 40, 5), (7, 1, 3)])
def test_axis_weights_and_phase_table_equal_the_kernels_sums_bit_for_bit(start, count, stride):
    """The weights are computed with NumPy (no kernel to load): the same numbers as the
    compiled :func:`lagrange_weights` gives voxel by voxel."""
    from numba import njit

    from napari_dvc_correct.engine.fields import inverse_per_voxel

    @njit
    def compiled(start, count, stride):  # the weights as a kernel computes them
        node = np.empty(count, np.int64)
        weight = np.empty((count, 6))
        table = np.empty((stride, 6))
        for i in range(count):
            cell = (start + i) // stride
            node[i] = cell - start // stride
            w = inverse_per_voxel.lagrange_weights((start + i - cell * stride) / stride)
            for k in range(6):
                weight[i, k] = w[k]
        for p in range(stride):
            w = inverse_per_voxel.lagrange_weights(p / stride)
            for k in range(6):
                table[p, k] = w[k]
        return node, weight, table

    node, weight, table = compiled(start, count, stride)
    got_node, got_weight = inverse_per_voxel.axis_weights(start, count, stride)
    phase, got_table = inverse_per_voxel.phase_table(start, count, stride)
    np.testing.assert_array_equal(got_node, node)
    np.testing.assert_array_equal(got_weight, weight)
    np.testing.assert_array_equal(got_table, table)
    np.testing.assert_array_equal(phase, (start + np.arange(count)) % stride)
    assert got_weight.shape == (count, 6) and got_weight.flags.c_contiguous
