"""The judge of matched POIs: a flat subvolume is low texture, a match of unrelated texture is
low ZNCC, the others keep their match; the run's noise may be given by the caller."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation import match_judgement as J
from napari_dvc_correct.engine.correlation.correlate import match_iter
from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.engine.progress import run_to_completion

SHAPE = (40, 40, 64)
SHIFT = (0.4, -0.3, 0.6)
PARAMS = CorrelationParams(subvolume=11, step=8, search_radius=3)


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume(SHAPE, feature_size=2.0, seed=7) * 100.0 + 500.0
    deformed = synthetic.deform_volume(reference, synthetic.translation(SHIFT))
    reference = synthetic.add_noise(reference, 1.0, seed=1)
    deformed = synthetic.add_noise(deformed, 1.0, seed=2)
    reference[:, :, 44:] = 500.0  # a flat region: nothing to match
    deformed[:, :, 44:] = 500.0
    return reference, deformed


def test_the_judge_marks_flat_pois_and_keeps_good_matches(pair):
    matched, fine = run_to_completion(match_iter(*pair, PARAMS))
    assert isinstance(matched, J.MatchedGrid)
    # the match measures its own noise-free uncertainty where it says so (sigma_plain); the
    # others wait for the judge
    measured = np.isfinite(matched.sigma).all(axis=1)
    if matched.sigma_plain is not None:
        assert np.array_equal(measured, matched.sigma_plain)
    assert not measured[matched.status != Status.CONVERGED].any()
    estimates = matched.noise_estimates()
    assert 0 < estimates.size < len(matched.centers)  # the textured, matched POIs only
    field, thresholds = run_to_completion(J.judge_iter(matched, fine, PARAMS))
    x = field.axis_coordinates()[2]
    flat = x - PARAMS.subvolume // 2 >= 44  # the whole subvolume in the flat region
    textured = x + PARAMS.subvolume // 2 < 44
    assert flat.any() and textured.any()
    assert np.all(field.status[:, :, flat] == Status.LOW_TEXTURE)
    good = field.status[:, :, textured] == Status.CONVERGED
    assert good.mean() > 0.9
    error = field.u[:, :, textured][good] - SHIFT
    assert np.abs(error).max() < 0.05  # voxels
    assert np.isfinite(field.uncertainty[:, :, textured][good]).all()
    assert thresholds.shape == (field.n_points,) and np.all(thresholds <= 1.0)
    assert field.metadata["noise"]["uncertainty_bound"] > 0


def test_a_noise_given_by_the_caller_is_used_and_the_bound_left_to_it(pair):
    matched, fine = run_to_completion(match_iter(*pair, PARAMS))
    field, thresholds = run_to_completion(
        J.judge_iter(matched, fine, PARAMS, noise_variance=1e6, bound=False)
    )
    # an enormous noise: the perfect ZNCC it allows is low, so are the thresholds
    matched2, fine2 = run_to_completion(match_iter(*pair, PARAMS))
    _, usual = run_to_completion(J.judge_iter(matched2, fine2, PARAMS))
    assert np.nanmedian(thresholds) < np.nanmedian(usual)
    assert "uncertainty_bound" not in field.metadata["noise"]
