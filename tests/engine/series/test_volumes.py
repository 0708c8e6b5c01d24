"""A scan series' volume operations in memory, on states related by known translations."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.progress import run_to_completion
from napari_dvc_correct.engine.series.volumes import InMemorySeries, SeriesVolumes

SHAPE = (32, 32, 32)
GRID = ((4.0, 4.0, 4.0), (6.0, 6.0, 6.0), (5, 5, 5))


@pytest.fixture(scope="module")
def states():
    v0 = synthetic.textured_volume(SHAPE, feature_size=3.0, seed=5) * 100.0
    v1 = synthetic.deform_volume(v0, synthetic.translation((2.0, 0.0, 0.0)))
    return [v0, v1]


def _uniform(u) -> DisplacementField:
    zero = DisplacementField.zeros(*GRID)
    return zero.replace(u=np.broadcast_to(u, zero.u.shape).copy())


def test_the_in_memory_series_is_a_series_back_end(states):
    series = InMemorySeries(states, CorrelationParams(subvolume=11, step=6), GRID)
    assert isinstance(series, SeriesVolumes) and series.n_states == 2


def test_the_mask_is_carried_by_the_total_field(states):
    mask = np.zeros(SHAPE, np.uint8)
    mask[8:24, 8:24, 8:24] = 3  # non-zero = material
    series = InMemorySeries(states, CorrelationParams(subvolume=11, step=6), GRID, mask=mask)
    carried = run_to_completion(series.carry_mask(_uniform((2.0, 0.0, 0.0))))
    expected = np.zeros(SHAPE, bool)
    expected[10:26, 8:24, 8:24] = True
    np.testing.assert_array_equal(carried, expected)
    # a field that sends the material out of the volume leaves no mask
    assert run_to_completion(series.carry_mask(_uniform((100.0, 0.0, 0.0)))) is None


def test_the_mean_residual_of_a_state_is_small_for_its_true_total_field(states):
    series = InMemorySeries(states, CorrelationParams(subvolume=11, step=6), GRID)
    right = run_to_completion(series.mean_residual(1, _uniform((2.0, 0.0, 0.0))))
    wrong = run_to_completion(series.mean_residual(1, _uniform((0.0, 0.0, 0.0))))
    assert right < 0.05 * float(np.std(states[0])) < wrong
