"""What an evaluation returns: which nodes count as measured, and the records' derived values."""

import math

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation import results as R
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status


def _field(failed: int = 0) -> DisplacementField:
    """2 x 2 x 2 nodes; the first ``failed`` of them not measured, each for another reason."""
    field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (2, 2, 2))
    flat = (field.status.reshape(-1), field.provenance.reshape(-1), field.u.reshape(-1, 3))
    status, provenance, u = flat
    reasons = [
        lambda k: status.__setitem__(k, Status.DIVERGED),  # a failed match
        lambda k: provenance.__setitem__(k, Provenance.REPLACED),  # inpainted by the cleaning
        lambda k: u.__setitem__(k, np.nan),  # no value
        lambda k: status.__setitem__(k, Status.MASKED),
        lambda k: provenance.__setitem__(k, Provenance.INTERPOLATED),  # from scattered points
    ]
    for k in range(failed):
        reasons[k](k)
    provenance[7] = Provenance.CORRECTED  # a corrected node is a measurement
    return field


def _evaluation_of(field: DisplacementField, **values) -> R.FieldEvaluation:
    values = dict(mean_residual=5.0, background_used=2.0, accuracy=0.9) | values
    return R.FieldEvaluation(
        name="f", field=field, equivalent_strain=np.zeros(field.shape), voxels=100,
        background=None, bins=None, bin_accuracy=np.zeros(3), **values,
    )  # fmt: skip


def test_measured_nodes_are_good_matches_measured_or_corrected():
    np.testing.assert_array_equal(R.measured_mask(_field()), np.ones((2, 2, 2), bool))
    mask = R.measured_mask(_field(failed=5)).reshape(-1)
    assert mask.tolist() == [False] * 5 + [True] * 3


@pytest.mark.parametrize(("failed", "fraction", "meaningful"), [(0, 1.0, True), (4, 0.5, True),
                                                                (5, 0.375, False)])  # fmt: skip
def test_an_evaluation_of_mostly_inpainted_nodes_is_not_meaningful(failed, fraction, meaningful):
    item = _evaluation_of(_field(failed))
    assert item.measured_nodes == round(8 * fraction)
    assert item.measured_fraction == fraction and item.meaningful is meaningful
    assert R.MIN_MEASURED_FRACTION == 0.5


def test_corrected_residual_and_the_error_summary():
    item = _evaluation_of(_field())
    assert item.mean_corrected_residual == 3.0  # mean(r) - r0
    numbers = [v for v in item.error.values() if not isinstance(v, bool)]
    assert all(math.isnan(v) for v in numbers)  # no estimate: nothing known
    assert not item.error["median_is_bound"] and not item.error["p95_is_bound"]
    item.error_estimate = np.array([0.1, 0.2, 0.3, np.nan]).reshape(2, 2, 1)
    assert item.error["median"] == pytest.approx(0.25)  # NaN counts as the worst


def test_the_evaluation_finds_its_fields_and_says_what_its_residual_is():
    evaluation = R.Evaluation(
        mode="reference", thresholds_reference=np.array([100.0]),
        thresholds_deformed=np.array([100.0]), phases_reference=[], phases_deformed=[],
        contrast=50.0, phase_pair=(0, 1), edges=np.linspace(0, 1, 4), options={},
        fields=[_evaluation_of(_field())],
    )  # fmt: skip
    assert evaluation["f"].name == "f"
    with pytest.raises(KeyError, match="no field named 'g'"):
        evaluation["g"]
    assert evaluation.gray_levels.is_identity  # no pair statistics: raw gray levels
    assert evaluation.residual_text == "|F(X + u) − G(X)|, reference frame, raw gray levels"
    evaluation.mode = "loaded"
    assert evaluation.residual_text == "|F − G'|, loaded frame, raw gray levels"
