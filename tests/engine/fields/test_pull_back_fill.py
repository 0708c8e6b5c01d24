"""The one-pass pull-back (engine/fields/pull_back_fill.py) against sampling the field spline's positions."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
from napari_dvc_correct.engine.fields import warp
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.field_spline import FieldSpline
from napari_dvc_correct.engine.fields.pull_back_fill import pull_back_box


@pytest.fixture(scope="module")
def volume_and_spline():
    volume = synthetic.textured_volume((36, 40, 44), 2.0, seed=3).astype(np.float32)
    field = DisplacementField.zeros((4.0, 6.0, 5.0), (6.0, 6.0, 7.0), (6, 6, 6))
    rng = np.random.default_rng(1)
    # large random displacements: many positions land outside F and near its borders
    field.u[:] = rng.normal(0.0, 3.0, field.u.shape)
    return volume, FieldSpline.from_field(field)


@pytest.mark.parametrize("outside", ["extrapolate", "nan"])
def test_one_pass_pull_back_equals_sampling_the_lattice_positions(volume_and_spline, outside):
    volume, spline = volume_and_spline
    coefficients = prefilter(volume)
    box = (slice(2, 33), slice(0, 40), slice(7, 41))  # not at the origin, not the whole volume
    fused = pull_back_box(coefficients, spline, box, outside)
    axes = warp.box_axes(box)
    points = warp.box_lattice(box) + spline.lattice(*axes, outside=outside).reshape(-1, 3)
    expected = sample(coefficients, points, cval=np.nan).reshape(fused.shape)
    assert fused.dtype == np.float32 and fused.shape == (31, 40, 34)
    nan = np.isnan(expected)
    assert 0.05 < nan.mean() < 0.9  # both outside F and (with "nan") outside the hull
    assert np.array_equal(np.isnan(fused), nan)
    scale = float(np.abs(volume).max())
    assert np.max(np.abs(fused[~nan] - expected[~nan])) < 1e-5 * scale  # float32 rounding


def test_pull_back_block_takes_the_one_pass_path_for_in_memory_volumes(volume_and_spline):
    volume, spline = volume_and_spline
    coefficients = prefilter(volume)
    box = warp.whole_box(volume.shape)
    in_memory = warp.pull_back_block(warp.SplineSampler(coefficients), spline, box, "nan")
    generic = warp.pull_back_block(lambda p: sample(coefficients, p), spline, box, "nan")
    np.testing.assert_allclose(in_memory, generic, rtol=0, atol=1e-5 * float(volume.max()))


def test_one_pass_pull_back_refuses_a_field_of_other_components(volume_and_spline):
    volume, _ = volume_and_spline
    scalar = FieldSpline((0.0, 0.0, 0.0), (8.0, 8.0, 8.0), np.zeros((4, 4, 4, 1)))
    with pytest.raises(ValueError, match="3 components"):
        pull_back_box(prefilter(volume), scalar, warp.whole_box(volume.shape))
