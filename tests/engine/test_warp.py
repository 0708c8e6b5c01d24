"""Densification, warping and gray residuals (engine/warp.py) against closed forms."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from napari_dvc_correct.engine import synthetic, warp
from napari_dvc_correct.engine.field import DisplacementField, grid_for_volume

GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


def _field_from(function, origin=(5.0, 6.0, 7.0), step=(4.0, 4.0, 5.0), shape=(8, 9, 7)):
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(function, field.points.reshape(*shape, 3))
    return field


def test_affine_field_is_reproduced_exactly_inside_and_outside_the_grid():
    function = synthetic.affine(GRADIENT, (20.0, 20.0, 20.0), (1.0, 2.0, -3.0))
    spline = warp.FieldSpline.from_field(_field_from(function))
    points = np.random.default_rng(0).uniform(-15.0, 70.0, (5000, 3))
    assert np.abs(spline(points) - function(points)).max() < 1e-9


def test_smooth_field_is_interpolated_within_a_few_hundredths_of_a_voxel():
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=8.0, slip=6.0)
    field = _field_from(band)
    spline = warp.FieldSpline.from_field(field)
    inside = np.random.default_rng(1).uniform((5, 6, 7), (33, 38, 37), (5000, 3))
    error = np.abs(spline(inside) - band(inside)).max()
    assert error < 0.05
    # the spline passes through the nodes
    assert np.abs(spline(field.points) - field.displacement).max() < 1e-9


@settings(max_examples=20, deadline=None)
@given(
    shape=st.tuples(*[st.integers(1, 6)] * 3),
    seed=st.integers(0, 1000),
)
def test_densify_at_the_nodes_returns_the_node_values(shape, seed):
    rng = np.random.default_rng(seed)
    field = DisplacementField(
        origin=(3.0, 4.0, 5.0), step=(2.0, 3.0, 4.0), u=rng.normal(size=(*shape, 3))
    )
    values = warp.densify(field, field.points)
    assert np.allclose(values, field.displacement, atol=1e-9)


def test_lattice_and_point_evaluation_agree_and_chunks_do_not_matter(tmp_path):
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=8.0, slip=6.0, shift=(1.0, 2.0, 3.0))
    field = _field_from(band)
    shape = (30, 33, 41)
    whole = warp.densify(field, shape=shape, dtype=np.float64)
    grids = np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij")
    points = np.stack([g.ravel() for g in grids], axis=1)
    assert np.abs(whole.reshape(-1, 3) - warp.densify(field, points)).max() < 1e-12
    # tiny chunks, written into a memory map, give the same field
    out = np.lib.format.open_memmap(tmp_path / "dense.npy", "w+", np.float32, (*shape, 3))
    warp.densify(field, shape=shape, out=out, chunk_voxels=700)
    assert np.abs(out - whole).max() < 1e-4
    slabs = list(warp.iter_slabs(shape, chunk_voxels=33 * 41 * 4))
    assert len(slabs) == 8 and all(s.stop - s.start <= 4 for s in slabs)


def test_outside_nan_marks_exactly_the_points_outside_the_hull():
    field = _field_from(synthetic.translation((1.0, 1.0, 1.0)))
    hull_low = np.asarray(field.origin)
    hull_high = hull_low + (np.asarray(field.shape) - 1) * np.asarray(field.step)
    points = np.random.default_rng(2).uniform(-10.0, 60.0, (4000, 3))
    inside = np.all((points >= hull_low) & (points <= hull_high), axis=1)
    values = warp.densify(field, points, outside="nan")
    assert np.array_equal(np.isnan(values[:, 0]), ~inside)
    assert np.allclose(values[inside], 1.0)
    dense = warp.densify(field, shape=(40, 45, 45), outside="nan")
    z, y, x = warp.FieldSpline.from_field(field).hull_slices((40, 45, 45))
    assert np.all(np.isfinite(dense[z, y, x]))
    assert np.isnan(dense).any(axis=-1).sum() == 40 * 45 * 45 - dense[z, y, x, 0].size


def test_inverse_map_solves_x_plus_u_of_x():
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=6.0, slip=8.0, shift=(2.0, -1.0, 3.0))
    spline = warp.FieldSpline.from_field(_field_from(band))
    targets = np.random.default_rng(3).uniform(0.0, 40.0, (3000, 3))
    reference, converged = spline.invert(targets)
    assert converged.all()
    assert np.abs(reference + spline(reference) - targets).max() < 1e-4


def test_a_field_with_holes_is_refused_with_advice():
    field = _field_from(synthetic.translation((1.0, 0.0, 0.0)))
    field.u[2, 2, 2] = np.nan
    with pytest.raises(ValueError, match="clean"):
        warp.densify(field, np.zeros((1, 3)))


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=3)
    band = synthetic.shear_band((20.0, 20.0, 20.0), width=7.0, slip=6.0, shift=(1.5, -2.0, 2.5))
    deformed = synthetic.deform_volume(reference, band)
    origin, step, shape = grid_for_volume(reference.shape, 9, 3)
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(*shape, 3))
    return reference, deformed, field


def test_pull_back_and_forward_warp_undo_a_known_deformation(pair):
    reference, deformed, field = pair
    contrast = float(reference.std())
    core = (slice(8, 32),) * 3
    pulled = warp.pull_back(deformed, field)
    assert np.mean(np.abs(pulled - reference)[core]) < 0.01 * contrast
    assert np.mean(np.abs(deformed - reference)[core]) > 0.5 * contrast  # not vacuous
    moved = warp.warp_forward(reference, field, chunk_voxels=5000)
    assert np.mean(np.abs(moved - deformed)[core]) < 0.01 * contrast
    # chunking does not change the result
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)


def test_gray_residual_is_small_for_the_true_field_and_nan_where_undefined(pair):
    reference, deformed, field = pair
    contrast = float(reference.std())
    zero = field.replace(u=np.zeros_like(field.u))
    for mode in ("reference", "loaded"):
        residual = warp.gray_residual(reference, deformed, field, mode)
        assert residual.dtype == np.float32 and residual.shape == reference.shape
        z, y, x = warp.FieldSpline.from_field(field).hull_slices(reference.shape)
        outside = np.ones(reference.shape, bool)
        outside[z, y, x] = False
        if mode == "reference":
            assert np.all(np.isnan(residual[outside]))
        mean = warp.mean_gray_residual(reference, deformed, field, mode, chunk_voxels=3000)
        assert mean == pytest.approx(float(np.nanmean(residual)), rel=1e-5)
        wrong = warp.mean_gray_residual(reference, deformed, zero, mode)
        assert mean < 0.02 * wrong
    in_hull = warp.gray_residual(reference, deformed, field)
    everywhere = warp.gray_residual(reference, deformed, field, region="volume")
    assert np.isfinite(everywhere).mean() > np.isfinite(in_hull).mean() + 0.2
    assert np.nanmean(everywhere) < 0.05 * contrast
    with pytest.raises(ValueError, match="mode"):
        warp.gray_residual(reference, deformed, field, mode="sideways")


def test_forward_warp_with_residual_matches_the_separate_calls(pair):
    reference, deformed, field = pair
    moved, mean = warp.warp_forward_with_residual(reference, deformed, field, chunk_voxels=4000)
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)
    expected = warp.mean_gray_residual(reference, deformed, field, "loaded")
    assert mean == pytest.approx(expected, rel=1e-6)
