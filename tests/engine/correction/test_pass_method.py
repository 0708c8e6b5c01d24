"""How the correcting matches are parametrised (engine/correction/pass_method.py), on fields with a known curvature."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction.pass_method import (
    MIN_PASS_SUBVOLUME,
    correctable_nodes,
    correction_grid,
    correction_params,
    field_curvature,
    node_bend,
    nothing_to_correct,
    pass_method,
    pass_order,
)
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import (
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)


def _measured_affine_field():
    """A field every node of which is its own converged match (affine: no bend)."""
    params = CorrelationParams(subvolume=21, step=6)
    origin, step, shape = grid_for_volume((64, 64, 64), 21, 6)
    field = DisplacementField.zeros(origin, step, shape)
    points = field.points.reshape(*shape, 3)
    gradient = np.array([[0.02, 0.01, 0.0], [0.0, -0.015, 0.01], [0.01, 0.0, 0.02]])
    field.u[:] = synthetic.sample_displacement(synthetic.affine(gradient, (32,) * 3), points)
    field.params = params.to_dict()  # measured with these parameters ...
    field.uncertainty = np.full((*shape, 3), 0.01)  # ... by our matcher, which says how well
    return field, params, np.zeros(shape, bool)


def test_second_order_passes_where_the_field_bends_inside_a_subvolume():
    field, params, _ = _measured_affine_field()
    points = field.points.reshape(*field.shape, 3)
    assert field_curvature(field, params.half) < 1e-9
    assert pass_order(field, params) == 1
    # u_z = a x^2: u'' = 2a, so a first-order subvolume misses a M^2 (0.2 voxel here)
    a = 0.002
    field.u[..., 0] += a * (points[..., 2] - 32.0) ** 2
    assert field_curvature(field, params.half) == pytest.approx(a * params.half**2, rel=0.15)
    assert pass_order(field, params) == 2
    assert pass_order(field.copy(), params.replace(order=2)) == 2


def test_a_crack_s_jump_is_no_bend_once_its_nodes_are_left_out():
    field, params, _ = _measured_affine_field()
    points = field.points.reshape(*field.shape, 3)
    # a crack opening 2 voxels across the plane x = 32: a jump, not a bend a pass could follow
    side = points[..., 2] > 32.0
    field.u[..., 2] += np.where(side, 1.0, -1.0)
    assert field_curvature(field, params.half) > 0.1  # read as a bend of the whole field
    crack = np.abs(points[..., 2] - 32.0) < 4.0  # the crack's nodes, a shield of one step
    shield = np.abs(points[..., 2] - 32.0) < 4.0 + 6.0
    assert np.any(crack) and not np.all(shield)
    assert field_curvature(field, params.half, crack | shield) < 0.01
    assert pass_method(field, params, crack | shield)[0] == params  # the first run's
    assert pass_method(field, params)[0].order == 2
    # a real bend away from the crack still counts
    field.u[..., 0] += 0.002 * (points[..., 1] - 32.0) ** 2
    assert field_curvature(field, params.half, crack | shield) == pytest.approx(
        0.002 * params.half**2, rel=0.15
    )


def test_bending_fields_are_corrected_with_smaller_second_order_subvolumes():
    params = CorrelationParams(subvolume=21, step=6)
    origin, step, shape = grid_for_volume((64, 64, 64), 21, 6)
    field = DisplacementField.zeros(origin, step, shape)
    assert correction_params(field, params) == params  # a flat field: the paper's rule
    points = field.points.reshape(*shape, 3)
    field.u[..., 0] = 0.004 * (points[..., 2] - 32.0) ** 2
    chosen = correction_params(field, params)
    assert chosen.order == 2 and chosen.subvolume == 15  # 2/3 of the half-size, odd
    small = correction_params(field, CorrelationParams(subvolume=11, step=6))
    assert small.subvolume == MIN_PASS_SUBVOLUME == 11


def test_the_correcting_grid_follows_the_displaced_nodes_as_far_as_a_subvolume_fits():
    # the shear band's grid: 64^3, nodes 14, 19, ..., 49; correcting subvolume 17 (half 8) fits
    # with its centre in [8, 55]
    field = DisplacementField.zeros((14.0, 14.0, 14.0), (5.0, 5.0, 5.0), (8, 8, 8))
    params = CorrelationParams(subvolume=17, step=5, order=2)
    shift = np.array([8.0, -6.0, 2.4])  # z: 1.6 steps up, y: 1.2 steps down, x: < half a step
    origin, step, shape = correction_grid(field, (64,) * 3, params, field.points + shift)
    # z: one more node (54; 59 would not fit), y: one more below (9), x unchanged
    assert origin == (14.0, 9.0, 14.0) and step == field.step and shape == (9, 9, 8)
    # the first run's subvolume (25) fits nowhere beyond the grid: unchanged
    big = CorrelationParams(subvolume=25, step=5)
    assert correction_grid(field, (64,) * 3, big, field.points + shift) == (
        field.origin,
        field.step,
        field.shape,
    )
    # never smaller than the field's grid, whatever the read points
    inward = correction_grid(field, (64,) * 3, params, field.points[:1] * 0 + 30.0)
    assert inward == (field.origin, field.step, field.shape)


def test_noise_keeps_the_first_runs_subvolume_where_a_smaller_one_would_scatter_more():
    from napari_dvc_correct.engine.correction.pass_method import pass_method, predicted_scatter

    params = CorrelationParams(subvolume=21, step=6)
    origin, step, shape = grid_for_volume((64, 64, 64), 21, 6)
    field = DisplacementField.zeros(origin, step, shape)
    points = field.points.reshape(*shape, 3)
    field.u[..., 0] += 0.002 * (points[..., 2] - 32.0) ** 2  # bends a subvolume by 0.2 voxel
    # clean scans: the first run scattered by a thousandth of a voxel
    field.uncertainty = np.full((*shape, 3), 0.001)
    chosen, why = pass_method(field, params)
    assert chosen.order == 2 and chosen.subvolume < 21 and "second order" in why
    # noisy, weak texture: 0.05 voxel per component at 21³ -> about 0.2 at 15³ second order
    field.uncertainty = np.full((*shape, 3), 0.05)
    scatter = predicted_scatter(field, 21, chosen.subvolume)
    assert scatter == pytest.approx(
        np.sqrt(3) * 0.05 * (21 / chosen.subvolume) ** 1.5 * 1.5, rel=1e-9
    )
    # predicted errors: first order 21³ 0.22, second order 21³ 0.16, second order 15³ 0.23:
    # the noise forbids the smaller subvolume, and second order on the first run's wins
    chosen, why = pass_method(field, params)
    assert (chosen.order, chosen.subvolume) == (2, 21) and "predicted errors" in why
    # heavy noise: 0.2 voxel per component, nothing beats the first run's parameters
    field.uncertainty = np.full((*shape, 3), 0.2)
    chosen, why = pass_method(field, params)
    assert chosen == params and "predicted errors" in why


def test_the_node_bend_is_the_quadratic_term_a_first_order_subvolume_leaves():
    from napari_dvc_correct.engine.correction.pass_method import node_bend

    params = CorrelationParams(subvolume=21, step=6)
    shape = (5, 5, 16)
    field = DisplacementField.zeros((10.0, 10.0, 10.0), (6.0, 6.0, 6.0), shape)
    x = field.points[:, 2].reshape(shape)
    curvature = 0.004  # u_z = c (x - x0)² / 2: u'' = c, a bend of c M² / 2 at every node
    field.u[..., 0] = 0.5 * curvature * (x - 55.0) ** 2
    bend = node_bend(field, params.half)
    assert bend.shape == shape
    expected = 0.5 * curvature * params.half**2
    # the one-node Gaussian smoothing keeps a quadratic's second difference four nodes away
    # from the faces it reflects at
    inner = bend[..., 4:-4]
    assert np.allclose(inner, expected, rtol=0.01)
    assert bend.max() <= expected * 1.01  # the faces bend no more than the field does
    # an affine field bends nothing; a field with a NaN node tells nothing
    field.u[..., 0] = 0.01 * x
    assert np.allclose(node_bend(field, params.half), 0.0, atol=1e-12)
    field.u[0, 0, 0, 0] = np.nan
    assert np.isnan(node_bend(field, params.half)).all()


def test_a_pass_is_not_run_where_it_could_only_remeasure_the_first_runs_values():
    field, params, masked = _measured_affine_field()
    reason = nothing_to_correct(field, params, masked)
    assert reason.startswith("no pass run") and f"{field.n_points} measured nodes" in reason


def test_a_pass_runs_where_a_node_is_not_its_own_match_or_the_field_bends():
    field, params, masked = _measured_affine_field()
    replaced = field.copy()
    replaced.provenance[2, 3, 4] = Provenance.REPLACED  # the cleaning refilled one node
    assert nothing_to_correct(replaced, params, masked) == ""
    failed = field.copy()
    failed.status[1, 1, 1] = Status.MAX_ITERATIONS  # a match that did not converge
    assert nothing_to_correct(failed, params, masked) == ""
    # ... but a failed node outside the user's mask is not the correction's business
    outside = masked.copy()
    outside[1, 1, 1] = True
    assert nothing_to_correct(failed, params, outside) != ""
    # u_z = a x^2 bends a subvolume of half-size M by a M^2: 0.02 voxel runs a pass, 0.005 not
    points = field.points.reshape(*field.shape, 3)
    for bend, runs in ((0.02, True), (0.005, False)):
        bent = field.copy()
        bent.u[..., 0] += bend / params.half**2 * (points[..., 2] - 32.0) ** 2
        assert (nothing_to_correct(bent, params, masked) == "") is runs
    # a field our matcher did not measure with these parameters: a pass is its first match
    foreign = field.copy()
    foreign.uncertainty = None
    assert nothing_to_correct(foreign, params, masked) == ""
    assert nothing_to_correct(field, params.replace(subvolume=15), masked) == ""
    thin = field.copy()
    thin.u[:] = np.nan  # no bend can be told from non-finite nodes: a pass runs
    assert nothing_to_correct(thin, params, masked) == ""


def test_the_correctable_nodes_are_those_not_their_own_match_or_bent_and_measured():
    field, params, masked = _measured_affine_field()
    assert not correctable_nodes(field, params, masked).any()  # nothing_to_correct's field
    replaced = field.copy()
    replaced.provenance[2, 3, 4] = Provenance.REPLACED
    replaced.status[5, 5, 5] = Status.MAX_ITERATIONS
    found = correctable_nodes(replaced, params, masked)
    assert found.sum() == 2 and found[2, 3, 4] and found[5, 5, 5]
    outside = masked.copy()
    outside[5, 5, 5] = True  # the user's mask: not the correction's business
    assert correctable_nodes(replaced, params, outside).sum() == 1
    # a bump of 0.05 voxel in one corner bends only the nodes near it (one-node smoothing)
    points = field.points.reshape(*field.shape, 3)
    bumped = field.copy()
    corner = np.array([10.0, 10.0, 10.0])
    weight = np.exp(-np.sum((points - corner) ** 2, axis=-1) / (2 * 6.0**2))
    bumped.u[..., 2] += 0.5 * weight
    found = correctable_nodes(bumped, params, masked)
    bend = node_bend(bumped, params.half)
    assert np.array_equal(found, bend > 0.01)
    assert 0 < found.sum() < 0.5 * found.size and found[0, 0, 0] and not found[-1, -1, -1]
    # a field our matcher did not measure with these parameters: every measured node
    foreign = field.copy()
    foreign.uncertainty = None
    assert np.array_equal(correctable_nodes(foreign, params, outside), ~outside)


def test_the_window_geometry_of_a_uniform_box():
    """Uniform box: the second moment ``M (M + 1) / 3`` and, first order, the scatter of a mean
    of ``n`` voxels ``1 / √n``; a Gaussian window on the box has less of the one and more of the
    other, and second order scatters more than first."""
    from napari_dvc_correct.engine.correction.pass_method import window_geometry

    m2, noise = window_geometry(7, None, 1)
    assert m2 == pytest.approx(7 * 8 / 3) and noise == pytest.approx(15**-1.5)
    m2_second, noise_second = window_geometry(7, None)
    assert m2_second == pytest.approx(m2) and noise_second > 1.5 * noise
    m2_window, noise_window = window_geometry(7, 4.0)
    assert m2_window < m2 and noise_window > noise_second
    assert window_geometry(7, 100.0)[1] == pytest.approx(noise_second, rel=1e-3)


def test_a_window_where_the_bias_dominates_and_none_where_the_noise_does():
    """The second-order correcting matches get a Gaussian window where the field's bend predicts
    more error than the noise; none where the noise predicts more, or is not known."""
    from napari_dvc_correct.engine.correction.pass_method import pass_method

    params = CorrelationParams(subvolume=21, step=6)
    origin, step, shape = grid_for_volume((64, 64, 64), 21, 6)
    field = DisplacementField.zeros(origin, step, shape)
    points = field.points.reshape(*shape, 3)
    field.u[..., 0] += 0.004 * (points[..., 2] - 32.0) ** 2  # bends a subvolume by 0.4 voxel
    field.uncertainty = np.full((*shape, 3), 0.01)
    chosen, why = pass_method(field, params)
    assert (chosen.order, chosen.subvolume) == (2, 15) and chosen.window is not None
    assert f"Gaussian window of std {chosen.window:g}" in why
    cleaner = field.copy()
    cleaner.uncertainty = np.full((*shape, 3), 0.002)
    assert pass_method(cleaner, params)[0].window < chosen.window  # less noise: narrower
    field.uncertainty = np.full((*shape, 3), 0.03)  # the noise dominates: uniform
    chosen, why = pass_method(field, params)
    assert (chosen.order, chosen.subvolume, chosen.window) == (2, 15, None)
    assert "window" not in why
    field.uncertainty = None  # no uncertainty to weigh the noise by: uniform
    assert pass_method(field, params)[0].window is None
