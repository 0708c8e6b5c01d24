"""Which nodes a further correction pass can change (engine/correction/rematch_region.py), on known answers."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correction.acceptance import MIN_USEFUL_CHANGE
from napari_dvc_correct.engine.correction.rematch_region import (
    SPLINE_TAIL,
    applied_change,
    changed_nodes,
    expected_change,
    first_selection,
    only_confirms,
    remeasurement,
    reuse,
    select,
    spline_reach,
    spline_tail,
)
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.engine.fields.field_spline import FieldSpline


def test_the_spline_tail_is_the_field_splines_response_to_one_node():
    # the cardinal cubic spline: 1 at its node, max 0.137 beyond one step, then x0.268 per step
    assert SPLINE_TAIL[0] == pytest.approx(1.0)
    assert SPLINE_TAIL[1] == pytest.approx(0.1367, abs=2e-4)
    assert SPLINE_TAIL[3] / SPLINE_TAIL[2] == pytest.approx(2.0 - np.sqrt(3.0), rel=0.02)
    # the field spline (trend removed, padded) of one changed node in a line of 31 nodes
    values = np.zeros((1, 1, 31, 3))
    values[0, 0, 15, 2] = 1.0
    spline = FieldSpline((0.0, 0.0, 0.0), (1.0, 1.0, 4.0), values)
    x = np.linspace(0.0, 120.0, 2401)
    response = np.abs(spline(np.column_stack([np.zeros_like(x), np.zeros_like(x), x]))[:, 2])
    for d in (1, 2, 3):
        beyond = response[np.abs(x - 60.0) >= 4.0 * d]
        assert SPLINE_TAIL[d] * 0.95 <= beyond.max() <= SPLINE_TAIL[d] * 1.05, d


def test_the_spline_tail_is_computed_on_first_use_not_on_import():
    import subprocess
    import sys

    module = "napari_dvc_correct.engine.correction.rematch_region"
    code = (
        f"import {module} as m; assert m.spline_tail.cache_info().currsize == 0; "
        "m.spline_reach(0.5, 0.01); assert m.spline_tail.cache_info().currsize == 1"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    # the module's constant of before is the same array, read-only
    assert SPLINE_TAIL is spline_tail()
    assert not SPLINE_TAIL.flags.writeable
    with pytest.raises(AttributeError):
        from napari_dvc_correct.engine.correction import rematch_region

        rematch_region.NO_SUCH_NAME  # noqa: B018


def test_the_spline_reach_is_where_the_largest_change_falls_below_the_tolerance():
    assert spline_reach(0.05, 0.01) == 1  # 0.05 * 0.137 = 0.007
    assert spline_reach(0.5, 0.01) == 3  # 0.5 * 0.037 = 0.018 > 0.01, 0.5 * 0.0098 < 0.01
    assert spline_reach(0.0, 0.01) == 1


def test_a_change_counts_only_if_its_region_could_improve_above_the_floor():
    useful = np.full(4, 0.5 * MIN_USEFUL_CHANGE * 20.0)  # |grad G| = 20 gray levels / voxel
    change = np.array([0.005, 0.015, 0.025, 0.5])
    # clean scans: the bound is MIN_USEFUL_CHANGE
    changed, tolerance = changed_nodes(change, useful, 0.0)
    assert changed.tolist() == [False, True, True, True] and tolerance == pytest.approx(0.01)
    # noise worth the useful change again doubles it: 1/2 |grad G| c must beat 0.2 gray levels
    changed, tolerance = changed_nodes(change, useful, float(useful[0]))
    assert changed.tolist() == [False, False, True, True] and tolerance == pytest.approx(0.02)
    # no gradient: nothing a change could show
    assert not changed_nodes(change, np.zeros(4), 0.0)[0].any()


def test_a_change_counts_only_where_its_region_stays_above_the_floor_by_what_it_needs():
    useful = np.full(4, 0.5 * MIN_USEFUL_CHANGE * 20.0)  # 0.1 gray levels
    change = np.full(4, 0.5)  # each moved far more than the change bound
    region_tolerance = 0.3  # an improvement above the floor needs a fall of 0.4 gray levels
    # regions 0.1, 0.39 (less than a fall the noise allows), 0.41 above the floor; one unknown
    excess = np.array([0.1, 0.39, 0.41, np.nan])
    changed, tolerance = changed_nodes(change, useful, region_tolerance, excess)
    assert changed.tolist() == [False, False, True, True]
    assert tolerance == pytest.approx(MIN_USEFUL_CHANGE * (1.0 + region_tolerance / useful[0]))
    # ... and so another pass only confirms where too few such regions are left
    measured = np.ones(4, bool)
    stop, changed, _ = only_confirms(1, change, None, useful, region_tolerance, measured, 0.5,
                                     np.array([0.1, 0.2, 0.3, 0.41]))  # fmt: skip
    assert stop.startswith("only 1 node moved in pass 1")
    assert changed.tolist() == [False, False, False, True]
    assert only_confirms(1, change, None, useful, region_tolerance, measured, 0.5, excess)[0] == ""


def _grid(shape=(12, 12, 12), origin=(7.0, 7.0, 7.0), step=4.0):
    return (origin, (step,) * 3, shape)


def test_select_matches_and_judges_only_near_the_changed_nodes():
    grid = _grid()
    field = DisplacementField.zeros(*grid)
    changed = np.zeros(grid[2], bool)
    changed[2, 2, 2] = True
    change = np.where(changed, 0.05, 0.0)  # spline reach 1 step at tolerance 0.01
    points = field.points  # reference frame: nodes read delta at themselves
    selection = select(changed, change, points, points, grid, grid, half=5, tolerance=0.01)
    assert selection.reach == 1
    # ceil(5 / 4) = 2 steps of subvolume plus 1 of spline around node (2, 2, 2)
    expected = np.zeros(grid[2], bool)
    expected[:6, :6, :6] = True
    np.testing.assert_array_equal(selection.matched, expected)
    # judged: reading within one step of a matched node
    judged = np.zeros(grid[2], bool)
    judged[:7, :7, :7] = True
    np.testing.assert_array_equal(selection.judged, judged)
    # a changed node displaced by two steps in x: the matches follow its read point
    moved = points + np.array([0.0, 0.0, 8.0])
    shifted = select(changed, change, moved, moved, grid, grid, 5, 0.01)
    assert shifted.matched[:6, :6, 1:8].all() and not shifted.matched[..., 0].any()


def test_select_matches_the_nodes_new_to_the_correcting_grid():
    grid = _grid()
    bigger = ((3.0, 7.0, 7.0), grid[1], (13, 12, 12))  # one layer more, below in z
    changed = np.zeros(grid[2], bool)
    changed[11, 11, 11] = True
    field = DisplacementField.zeros(*grid)
    selection = select(
        changed, np.where(changed, 0.05, 0.0), field.points, field.points, bigger, grid, 5, 0.01
    )
    assert selection.matched[0].all()  # the new layer
    assert selection.matched[12, 11, 11] and not selection.matched[5, 5, 5]


def test_reuse_takes_the_previous_matches_less_what_was_applied():
    grid = _grid(shape=(4, 4, 4))
    previous = DisplacementField.zeros(*grid)
    previous.u[:] = (0.1, 0.2, 0.3)
    previous.zncc[:] = 0.9
    previous.status[:] = Status.CONVERGED
    # the new grid starts one step further in x; its last x layer is new (and matched)
    new_grid = ((7.0, 7.0, 11.0), grid[1], (4, 4, 4))
    delta = DisplacementField.zeros(*new_grid)
    delta.u[:] = np.nan
    delta.status[:] = Status.NOT_COMPUTED
    matched = np.zeros(new_grid[2], bool)
    matched[..., 3] = True
    matched[1, 1, 1] = True
    delta.u[matched] = 0.0
    delta.status[matched] = Status.CONVERGED
    applied = np.full((int((~matched).sum()), 3), 0.1)
    merged = reuse(delta, previous, matched, applied)
    np.testing.assert_allclose(merged.u[~matched], np.broadcast_to([0.0, 0.1, 0.2], (63 - 16, 3)))
    assert np.all(merged.u[matched] == 0.0) and np.all(merged.status == Status.CONVERGED)
    assert np.all(merged.zncc[~matched] == np.float32(0.9))


@pytest.mark.parametrize("loaded", [False, True])
def test_the_applied_change_is_read_at_the_reference_position(loaded):
    grid = _grid(shape=(6, 6, 6))
    field = DisplacementField.zeros(*grid)
    field.u[:] = (0.0, 0.0, 4.0)  # a shift of one step in x
    change = np.zeros((*grid[2], 3))
    change[..., 2] = np.arange(6.0)[None, None, :] * 0.01  # linear in the x index
    y = np.array([[15.0, 15.0, 15.0]])  # node index (2, 2, 2) of the lattice
    value = applied_change(field, change, y, loaded)[0, 2]
    # loaded frame: the reference position of y is X = y - 4 voxels, index 1 in x
    assert value == pytest.approx(0.01 if loaded else 0.02, abs=1e-9)


def _own_matches(shift=(0.0, 0.0, 6.0)):
    """A translated field on a 15³ grid (step 6, subvolume 11), every node its own converged
    match with these parameters."""
    params = CorrelationParams(subvolume=11, step=6)
    field = DisplacementField.zeros((10.0, 10.0, 10.0), (6.0,) * 3, (15, 15, 15))
    field.u[:] = shift
    field.params = params.to_dict()
    field.uncertainty = np.full((15, 15, 15, 3), 0.01)
    return field, params, np.zeros(field.shape, bool)


def test_the_first_pass_matches_and_judges_only_near_the_nodes_it_can_correct():
    field, params, masked = _own_matches()
    grid = (field.origin, field.step, field.shape)
    reads = field.points + field.u.reshape(-1, 3)  # one step further along x
    assert first_selection(field, params, masked, reads, grid, params.half) is None  # nothing
    field.provenance[7, 7, 5] = Provenance.REPLACED  # the cleaning refilled one node
    selection = first_selection(field, params, masked, reads, grid, params.half)
    # its read point is node (7, 7, 6); a subvolume (half 5 < one step) and the spline's
    # reach (one step) around it: the 5³ block of pass-grid nodes around that node
    expected = np.zeros(field.shape, bool)
    expected[5:10, 5:10, 4:9] = True
    assert np.array_equal(selection.matched, expected)
    # judged: the nodes whose update reads a matched correcting node (one step behind them)
    judged = np.zeros(field.shape, bool)
    judged[5:10, 5:10, 3:8] = True
    assert np.array_equal(selection.judged, judged) and selection.judged[7, 7, 5]
    # a node outside the user's mask is not corrected: no pass to run there
    masked[7, 7, 5] = True
    assert first_selection(field, params, masked, reads, grid, params.half) is None
    # every node correctable: every node matched, no selection
    field.uncertainty = None  # not our matcher's field: a pass is its first measurement
    assert first_selection(field, params, masked, reads, grid, params.half) is None


def test_the_remeasurement_of_a_node_is_no_motion_with_its_own_match_quality():
    field, _, _ = _own_matches()
    field.zncc[:] = 0.9
    field.zncc[7, 7, 5] = 0.5
    field.iterations[:] = 3
    delta = DisplacementField.zeros(field.origin, field.step, field.shape)
    delta.u[:] = 1.0
    reads = field.points + field.u.reshape(-1, 3)
    zero = remeasurement(delta, field, reads)
    assert np.all(zero.u == 0.0) and np.all(zero.gradient == 0.0)
    assert np.isnan(zero.uncertainty).all()
    assert zero.zncc[7, 7, 6] == pytest.approx(0.5)  # node (7, 7, 5) reads it, one step on
    assert np.all(zero.iterations[:, :, 1:] == 3)
    # a correcting node no update reads carries no quality of any node
    assert np.isnan(zero.zncc[:, :, 0]).all() and np.all(zero.iterations[:, :, 0] == 0)
    # where a pass matched only some nodes, reuse completes them with this
    matched = np.zeros(field.shape, bool)
    matched[7, 7, 6] = True
    merged = reuse(delta, zero, matched)
    assert np.all(merged.u[7, 7, 6] == 1.0) and np.all(merged.u[~matched] == 0.0)


def test_the_expected_change_follows_the_contraction_of_the_last_two_passes():
    measured = np.ones(4, bool)
    change = np.array([0.04, 0.02, 0.0, 0.01])
    assert np.array_equal(expected_change(change, None, measured), change)  # one pass only
    assert np.array_equal(expected_change(change, np.zeros(4), measured), change)
    previous = 10.0 * change  # the passes contract by 10: the next moves a tenth as far
    assert np.allclose(expected_change(change, previous, measured), 0.1 * change)
    # never more than the change itself; unmeasured nodes do not count in the ratio
    assert np.allclose(expected_change(change, 0.5 * change, measured), change)
    measured[0] = False
    previous = np.array([100.0, 0.2, 0.0, 0.1])
    assert np.allclose(expected_change(change, previous, measured), 0.1 * change)


def test_another_pass_only_confirms_where_too_few_nodes_would_still_move_enough():
    measured = np.ones(100, bool)
    useful = np.full(100, 0.5 * MIN_USEFUL_CHANGE * 20.0)  # clean scans: bound 0.01 voxel
    change = np.full(100, 0.005)
    change[:5] = 0.05  # 5 % of the nodes moved by five times the bound
    stop, changed, bound = only_confirms(1, change, None, useful, 0.0, measured, 0.01)
    assert stop == "" and changed.sum() == 5 and bound == pytest.approx(0.01)
    # the pass before moved them 20 times as far: the next would move them 0.0025
    stop, changed, _ = only_confirms(2, change, 20.0 * change, useful, 0.0, measured, 0.01)
    assert changed.sum() == 5  # the changed nodes (for the next selection) are unchanged
    assert "0.05 times as far as pass 1" in stop and "at that rate no node would move" in stop
    # ... 4 times as far: 0.0125 > 0.01, another pass may still improve them
    assert only_confirms(2, change, 4.0 * change, useful, 0.0, measured, 0.01)[0] == ""
    # too few (under 1 %) moved by enough at all
    change[:5] = 0.005
    stop = only_confirms(1, change, None, useful, 0.0, measured, 0.01)[0]
    assert stop.startswith("no node moved in pass 1")
