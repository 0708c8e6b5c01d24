"""One residual, stated: Self-correct and Evaluate give the same mean gray residual for the same
field and frame (issue 26, item 3)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correction.self_correction import correct
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.evaluation.gray_levels import GrayLevelMap
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume

SHAPE = (40, 40, 40)


@pytest.fixture(scope="module")
def case():
    truth = synthetic.affine(
        np.array([[0.01, 0.0, 0.0], [0.0, -0.005, 0.0], [0.0, 0.0, 0.004]]),
        np.array(SHAPE) / 2.0,
        shift=(1.1, -0.4, 0.7),
    )
    clean = synthetic.two_phase_volume(SHAPE, phase_grays=(90.0, 160.0), texture=4.0, seed=9)
    reference = synthetic.add_noise(clean, 2.0, seed=1)
    # the loaded scan darker and offset: the gray-level map must take it out
    deformed = 0.7 * synthetic.add_noise(synthetic.deform_volume(clean, truth), 2.0, seed=2) + 20
    params = CorrelationParams(subvolume=15, step=6)
    origin, step, grid = grid_for_volume(SHAPE, params.subvolume, params.step)
    field = DisplacementField.zeros(origin, step, grid, params=params.to_dict())
    field.u[:] = synthetic.sample_displacement(truth, field.points).reshape((*grid, 3)) + 0.2
    return reference.astype(np.float32), deformed.astype(np.float32), field


@pytest.mark.parametrize("frame", ["loaded", "reference"])
def test_self_correct_and_evaluate_report_the_same_residual(case, frame):
    reference, deformed, field = case
    corrected = correct(reference, deformed, field, frame=frame, max_passes=1)
    said = corrected.metadata["correction"]["mean_gray_residual_after"]
    gray = GrayLevelMap.from_dict(corrected.metadata["gray_levels"])
    same_map = evaluate_fields(
        reference, deformed, {"c": corrected}, mode=frame, gray_levels=gray, keep_volumes=False
    )
    assert same_map["c"].mean_residual == pytest.approx(said, rel=1e-3)
    # the evaluation's own map of the pair (fitted with the best field) differs a little
    own = evaluate_fields(reference, deformed, {"c": corrected}, mode=frame, keep_volumes=False)
    assert own["c"].mean_residual == pytest.approx(said, rel=0.03)
    assert ("loaded frame" if frame == "loaded" else "reference frame") in own.residual_text


def test_the_self_correct_panel_states_its_frame(case):
    from napari_dvc_correct.widgets.correct_model import summary_message

    reference, deformed, field = case
    marked = field.replace(
        metadata={"correction": {"frame": "loaded"}, "gray_levels": {"contrast": 1.4}}
    )
    assert "|map(F) − G'|, loaded frame, reference gray levels" in summary_message(marked)
