"""How a correcting match becomes the corrected field, on fields whose update is known exactly.

``D(X) = G X`` (affine) corrected by a uniform ``ΔD = d``: summed, ``D + d``; composed in the
loaded frame, ``D(X) + d`` read at ``X + D(X)``; composed in the reference frame,
``d + D(X + d) = D(X) + d + G d``.
"""

import numpy as np
import pytest

from napari_dvc_correct.engine.correction import pass_update as P
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status

GRID = ((10.0, 10.0, 10.0), (5.0, 5.0, 5.0), (4, 5, 6))
G = np.array([[0.01, 0.0, 0.02], [0.0, -0.01, 0.0], [0.005, 0.0, 0.01]])
D = np.array([0.3, -0.2, 0.5])


def _current() -> DisplacementField:
    zero = DisplacementField.zeros(*GRID)
    return zero.replace(u=(zero.points @ G.T).reshape((*GRID[2], 3)))


def _delta() -> DisplacementField:
    zero = P.zero_start(GRID)
    assert zero.gradient.shape == (*GRID[2], 3, 3) and not zero.u.any()
    return zero.replace(u=np.broadcast_to(D, zero.u.shape).copy())


@pytest.mark.parametrize(
    ("frame", "update", "expected"),
    [
        ("loaded", "sum", lambda u: u + D),
        ("loaded", "exact", lambda u: u + D),
        ("reference", "exact", lambda u: u + D + G @ D),
    ],
)
def test_the_update_of_an_affine_field_by_a_uniform_correction(frame, update, expected):
    current = _current()
    updated = P.updated_field(current, _delta(), frame, update)
    np.testing.assert_allclose(updated.u, expected(current.u), atol=1e-9)


def test_each_node_reads_its_correction_where_its_update_reads():
    current = _current()
    np.testing.assert_array_equal(
        P.update_read_points(current, "reference", "exact"), current.points
    )
    np.testing.assert_array_equal(P.update_read_points(current, "loaded", "sum"), current.points)
    displaced = P.update_read_points(current, "loaded", "exact")
    np.testing.assert_allclose(displaced, current.points + current.u.reshape(-1, 3))
    # nearest node of ΔD's grid: a point 2 voxels past node (1, 2, 3) reads that node; far
    # outside, the border node
    points = np.array([[15.0 + 2.0, 20.0, 25.0], [-100.0, 1e3, 12.0], [np.nan, 10.0, 10.0]])
    index = P.nearest_match(_delta(), points, (3,))
    assert [tuple(int(a[k]) for a in index) for k in range(3)] == [(1, 2, 3), (0, 4, 0), (0, 0, 0)]


def test_quality_arrays_come_from_the_correcting_match():
    current, delta = _current(), _delta()
    delta.zncc[:] = 0.97
    delta.status[0, 0, 0] = Status.DIVERGED
    delta.provenance[1, 1, 1] = Provenance.REPLACED  # a failed match, filled by the cleaning
    masked = np.zeros(GRID[2], bool)
    masked[3, 4, 5] = True
    current.status[3, 4, 5] = Status.MASKED
    candidate = P.updated_field(current, delta, "loaded", "sum")
    reads = P.update_read_points(current, "loaded", "sum")
    done = P.finish_pass(candidate, delta, current, masked, reads)
    assert np.all(done.zncc == np.float32(0.97)) and done.status[0, 0, 0] == Status.DIVERGED
    assert done.provenance[1, 1, 1] == Provenance.REPLACED
    assert done.provenance[3, 4, 5] == Provenance.MASKED and done.status[3, 4, 5] == Status.MASKED
    assert int((done.provenance == Provenance.CORRECTED).sum()) == np.prod(GRID[2]) - 2
    good = P.good_nodes(done)  # the diverged and the masked node are not good measurements
    assert not good[0, 0, 0] and not good[3, 4, 5] and good.sum() == np.prod(GRID[2]) - 2


def test_the_correction_s_uncertainty_is_its_nearest_match_s():
    delta = _delta()
    reads = _current().points
    assert np.isnan(P.correction_sigma(delta, reads, GRID[2])).all()  # none measured
    delta.uncertainty = np.broadcast_to([0.03, 0.04, 0.0], (*GRID[2], 3)).copy()
    np.testing.assert_allclose(P.correction_sigma(delta, reads, GRID[2]), 0.05)


def test_a_corrected_node_s_uncertainty_is_its_correcting_match_s_not_a_sum():
    # a correcting match re-measures the node on the same images: its noise replaces the node's
    current, delta = _current(), _delta()
    current.uncertainty = np.full((*GRID[2], 3), 0.2)
    delta.uncertainty = np.full((*GRID[2], 3), 0.03)
    delta.provenance[1, 1, 1] = Provenance.REPLACED
    masked = np.zeros(GRID[2], bool)
    masked[3, 4, 5] = True
    candidate = P.updated_field(current, delta, "loaded", "exact")
    np.testing.assert_allclose(candidate.uncertainty[0, 0, 0], np.hypot(0.2, 0.03))  # composed
    reads = P.update_read_points(current, "loaded", "exact")
    done = P.finish_pass(candidate, delta, current, masked, reads)
    np.testing.assert_allclose(done.uncertainty[0, 0, 0], 0.03)
    assert np.isnan(done.uncertainty[1, 1, 1]).all()  # interpolated: nothing measured
    np.testing.assert_allclose(done.uncertainty[3, 4, 5], 0.2)  # masked: kept
