"""Fixtures shared by the engine's warp and residual tests."""

import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume


@pytest.fixture(scope="module")
def sheared_pair():
    """A 40³ textured pair deformed by a known shear band, and the true field on a 9/3 grid."""
    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=3)
    band = synthetic.shear_band((20.0, 20.0, 20.0), width=7.0, slip=6.0, shift=(1.5, -2.0, 2.5))
    deformed = synthetic.deform_volume(reference, band)
    origin, step, shape = grid_for_volume(reference.shape, 9, 3)
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(*shape, 3))
    return reference, deformed, field
