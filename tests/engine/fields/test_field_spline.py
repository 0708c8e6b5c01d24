"""The field spline (engine/fields/field_spline.py) against closed forms: exact affine, node values, hull."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields import field_spline
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.slabs import iter_slabs

GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


def _field_from(function, origin=(5.0, 6.0, 7.0), step=(4.0, 4.0, 5.0), shape=(8, 9, 7)):
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(function, field.points.reshape(*shape, 3))
    return field


def test_affine_field_is_reproduced_exactly_inside_and_outside_the_grid():
    function = synthetic.affine(GRADIENT, (20.0, 20.0, 20.0), (1.0, 2.0, -3.0))
    spline = field_spline.FieldSpline.from_field(_field_from(function))
    points = np.random.default_rng(0).uniform(-15.0, 70.0, (5000, 3))
    assert np.abs(spline(points) - function(points)).max() < 1e-9


def test_smooth_field_is_interpolated_within_a_few_hundredths_of_a_voxel():
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=8.0, slip=6.0)
    field = _field_from(band)
    spline = field_spline.FieldSpline.from_field(field)
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
    values = field_spline.densify(field, field.points)
    assert np.allclose(values, field.displacement, atol=1e-9)


def test_lattice_and_point_evaluation_agree_and_chunks_do_not_matter(tmp_path):
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=8.0, slip=6.0, shift=(1.0, 2.0, 3.0))
    field = _field_from(band)
    shape = (30, 33, 41)
    whole = field_spline.densify(field, shape=shape, dtype=np.float64)
    grids = np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij")
    points = np.stack([g.ravel() for g in grids], axis=1)
    assert np.abs(whole.reshape(-1, 3) - field_spline.densify(field, points)).max() < 1e-12
    # tiny chunks, written into a memory map, give the same field
    out = np.lib.format.open_memmap(tmp_path / "dense.npy", "w+", np.float32, (*shape, 3))
    field_spline.densify(field, shape=shape, out=out, chunk_voxels=700)
    assert np.abs(out - whole).max() < 1e-4
    slabs = list(iter_slabs(shape, 33 * 41 * 4))
    assert len(slabs) == 8 and all(s.stop - s.start <= 4 for s in slabs)


def test_outside_nan_marks_exactly_the_points_outside_the_hull():
    field = _field_from(synthetic.translation((1.0, 1.0, 1.0)))
    hull_low = np.asarray(field.origin)
    hull_high = hull_low + (np.asarray(field.shape) - 1) * np.asarray(field.step)
    points = np.random.default_rng(2).uniform(-10.0, 60.0, (4000, 3))
    inside = np.all((points >= hull_low) & (points <= hull_high), axis=1)
    values = field_spline.densify(field, points, outside="nan")
    assert np.array_equal(np.isnan(values[:, 0]), ~inside)
    assert np.allclose(values[inside], 1.0)
    dense = field_spline.densify(field, shape=(40, 45, 45), outside="nan")
    z, y, x = field_spline.FieldSpline.from_field(field).hull_slices((40, 45, 45))
    assert np.all(np.isfinite(dense[z, y, x]))
    assert np.isnan(dense).any(axis=-1).sum() == 40 * 45 * 45 - dense[z, y, x, 0].size


def test_inverse_map_solves_x_plus_u_of_x():
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=6.0, slip=8.0, shift=(2.0, -1.0, 3.0))
    spline = field_spline.FieldSpline.from_field(_field_from(band))
    targets = np.random.default_rng(3).uniform(0.0, 40.0, (3000, 3))
    reference, converged = spline.invert(targets)
    assert converged.all()
    assert np.abs(reference + spline(reference) - targets).max() < 1e-4


def test_inverse_on_a_lattice_starts_from_the_neighbour_and_gives_the_same_answer():
    band = synthetic.shear_band((20.0, 22.0, 17.0), width=6.0, slip=8.0, shift=(2.0, -1.0, 3.0))
    spline = field_spline.FieldSpline.from_field(_field_from(band))
    grids = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in (6, 7, 40)], indexing="ij")
    lattice = np.stack([g.reshape(-1) for g in grids], axis=1)  # rows along x: warm starts
    order = np.random.default_rng(4).permutation(len(lattice))  # no neighbours: cold starts
    warm, warm_ok = spline.invert(lattice)
    shuffled, cold_ok = spline.invert(lattice[order])
    cold = np.empty_like(warm)
    cold[order] = shuffled
    assert warm_ok.all() and cold_ok.all()
    assert np.abs(warm + spline(warm) - lattice).max() < 1e-4
    assert np.abs(warm - cold).max() < 1e-6


def test_a_field_with_holes_is_refused_with_advice():
    field = _field_from(synthetic.translation((1.0, 0.0, 0.0)))
    field.u[2, 2, 2] = np.nan
    with pytest.raises(ValueError, match="clean"):
        field_spline.densify(field, np.zeros((1, 3)))
