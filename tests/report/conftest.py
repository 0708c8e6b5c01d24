"""An evaluation of two known fields on a small shear-band pair, shared by the report tests."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    deform_volume,
    sample_displacement,
    shear_band,
    two_phase_volume,
)

SHAPE = (32, 32, 32)


@pytest.fixture(scope="module")
def evaluation():
    clean = two_phase_volume(SHAPE, seed=1)
    truth = shear_band(center=(16.0, 16.0, 16.0), width=4.0, slip=3.0)
    reference = add_noise(clean, 3.0, seed=2)
    deformed = add_noise(deform_volume(clean, truth), 3.0, seed=3)
    origin, step, shape = grid_for_volume(SHAPE, 9, 4)
    base = DisplacementField.zeros(origin, step, shape)
    exact = base.replace(u=sample_displacement(truth, base.points).reshape((*shape, 3)))
    rigid = base.replace(u=np.zeros_like(exact.u))  # ignores the band: a poor field
    return evaluate_fields(reference, deformed, {"exact": exact, "no band": rigid}, n_bins=3)
