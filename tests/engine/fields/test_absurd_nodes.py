"""Diverged matches of an imported field: a few marked failed for cleaning, a mostly absurd field refused."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.absurd_nodes import flag_absurd_nodes
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.pair_checks import (
    check_field_on_volume,
)

SHAPE = (24, 24, 24)


def field_on(shape=SHAPE, u=(0.0, 0.0, 0.0), **metadata) -> DisplacementField:
    origin, step, grid = grid_for_volume(shape, 9, 6)
    field = DisplacementField.zeros(origin, step, grid, metadata=dict(metadata))
    field.u[...] = u
    return field


def test_a_few_absurd_nodes_are_failed_matches_and_most_are_another_field():
    """spam's ldic leaves a few diverged nodes at 10^3-10^6 voxels marked
    converged; they are flagged as failed (for cleaning), only a mostly absurd field is refused."""
    from napari_dvc_correct.engine.fields.field import Status

    field = field_on(shape=(48, 48, 48), u=(0.5, -1.0, 0.3))  # 6x6x6 nodes
    field.gradient = np.zeros((*field.shape, 3, 3))
    blown = [(0, 0, 0), (1, 2, 0), (5, 1, 4)]
    for node, value in zip(blown, (1.49e3, -2e4, 3.1e6)):
        field.u[node] = (0.5, value, 0.3)
    check_field_on_volume(field, (48, 48, 48))  # a few: not refused
    flagged, note = flag_absurd_nodes(field, (48, 48, 48))
    assert "3.1e+06 voxels along y" in note and "at 3 of 216 usable nodes" in note
    for node in blown:
        assert flagged.status[node] == Status.DIVERGED and not flagged.valid[node]
        assert np.all(np.isnan(flagged.u[node])) and np.all(np.isnan(flagged.gradient[node]))
    assert flagged.valid.sum() == 213 and flagged.metadata["absurd_nodes"] == 3
    assert field.valid.all() and field.u[0, 0, 0, 1] == 1.49e3  # the input is not changed
    same, none = flag_absurd_nodes(field_on(), SHAPE)
    assert none is None
    mostly = field_on(u=(0.0, 1e3, 0.0))
    mostly.u[0, 0, 0] = 0.0
    with pytest.raises(ValueError, match="at 7 of 8 usable nodes: it is not a field of this"):
        flag_absurd_nodes(mostly, SHAPE)
    with pytest.raises(ValueError, match="at 7 of 8"):
        check_field_on_volume(mostly, SHAPE)
