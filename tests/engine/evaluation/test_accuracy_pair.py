"""The scan pair's gray-level map and r0, measured once with the best field (issue 26)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
from napari_dvc_correct.engine.fields.field import (
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)
from napari_dvc_correct.engine.synthetic import (
    add_noise,
    affine,
    deform_volume,
    sample_displacement,
    two_phase_volume,
)

SHAPE = (48, 48, 48)


@pytest.fixture(scope="module")
def pair():
    clean = two_phase_volume(SHAPE, phase_grays=(100.0, 170.0), texture=4.0, seed=4)
    gradient = np.array([[-0.01, 0.004, 0.0], [0.0, 0.006, 0.003], [0.002, 0.0, 0.008]])
    truth = affine(gradient, center=np.array(SHAPE) / 2.0, shift=(1.2, -0.6, 2.1))
    reference = add_noise(clean, 3.0, seed=1)
    deformed = add_noise(deform_volume(clean, truth), 3.0, seed=2)
    origin, step, shape = grid_for_volume(SHAPE, 11, 6)
    base = DisplacementField.zeros(origin, step, shape, params={"subvolume": 11})
    exact = base.replace(u=sample_displacement(truth, base.points).reshape((*shape, 3)))
    return reference, deformed, exact


def test_r0_and_p_do_not_depend_on_which_fields_are_evaluated(pair):
    reference, deformed, exact = pair
    off = exact.replace(u=exact.u + np.array([0.4, -0.3, 0.2]))
    known = {"exact": exact, "off": off}
    alone = evaluate_fields(reference, deformed, {"off": off}, background_fields=known)
    both = evaluate_fields(reference, deformed, known, background_fields=known)
    assert alone.pair.measured_with == both.pair.measured_with == "exact"
    assert alone["off"].background_used == pytest.approx(both["off"].background_used, rel=1e-9)
    assert alone["off"].accuracy == pytest.approx(both["off"].accuracy, abs=1e-12)
    # without the better field known, the noise is over-estimated (the old dependence)
    own = evaluate_fields(reference, deformed, {"off": off})
    assert own.pair.background.mean > 1.05 * both.pair.background.mean


def test_a_change_of_gray_levels_is_mapped_out(pair):
    """The loaded scan 0.6 x darker and shifted: with the map, the residual, r0 and p are those
    of the unchanged pair; the raw residual measures the brightness change."""
    reference, deformed, exact = pair
    plain = evaluate_fields(reference, deformed, {"exact": exact}, keep_volumes=False)
    changed = (0.6 * deformed + 25.0).astype(np.float32)
    mapped = evaluate_fields(reference, changed, {"exact": exact}, keep_volumes=False)
    raw = evaluate_fields(reference, changed, {"exact": exact}, gray_levels=False)
    assert mapped.gray_levels.contrast == pytest.approx(1 / 0.6, rel=0.03)
    assert mapped["exact"].mean_residual == pytest.approx(plain["exact"].mean_residual, rel=0.03)
    assert mapped.pair.background.mean == pytest.approx(plain.pair.background.mean, rel=0.03)
    assert mapped["exact"].accuracy == pytest.approx(plain["exact"].accuracy, abs=0.005)
    assert raw["exact"].mean_residual > 3 * mapped["exact"].mean_residual
    assert "map(F)" in mapped.residual_text and "reference frame" in mapped.residual_text
    assert "raw gray levels" in raw.residual_text


def test_a_mostly_inpainted_field_is_not_certified(pair):
    """24 of 27 nodes replaced: 3 measured nodes, p flagged as not meaningful (item 5)."""
    reference, deformed, exact = pair
    shape = (3, 3, 3)
    coarse = DisplacementField.zeros((10.0,) * 3, (14.0,) * 3, shape, params={"subvolume": 15})
    field = coarse.replace(u=np.zeros((*shape, 3)) + np.array([1.2, -0.6, 2.1]))
    field.status[...] = int(Status.OUTLIER_REPLACED)
    field.provenance[...] = int(Provenance.REPLACED)
    field.status.flat[:3] = int(Status.CONVERGED)
    field.provenance.flat[:3] = int(Provenance.MEASURED)
    result = evaluate_fields(reference, deformed, {"flat": field}, keep_volumes=False)
    item = result["flat"]
    assert item.measured_nodes == 3 and not item.meaningful
    from napari_dvc_correct.report.markdown import render_markdown
    from napari_dvc_correct.report.tables import summary_rows

    assert summary_rows(result)[0]["valid_nodes"] == 3
    assert summary_rows(result)[0]["accuracy_meaningful"] == "no"
    first = render_markdown(result).split("\n\n")[1]
    assert "Warning" in first and "only 3 of 27 nodes were measured" in first


def test_a_specimen_region_keeps_the_air_out_of_phases_r0_and_residuals():
    """A concrete cylinder in air: without a region the two phases are air and concrete; with
    the cylinder they are matrix and aggregates, and no air voxel enters any number."""
    from napari_dvc_correct.engine.correlation.placement import Cylinder
    from napari_dvc_correct.engine.evaluation.accuracy import specimen_mask
    from napari_dvc_correct.engine.synthetic import (
        concrete_ct_volume,
        ct_noise_sigma,
        make_pair,
        translation,
    )

    shape = (40, 48, 48)
    truth = translation((0.6, -1.2, 0.9))
    reference, deformed = make_pair(lambda s: concrete_ct_volume(s, seed=2), shape, truth, 8)
    sigma = ct_noise_sigma(reference, 0.02)
    reference, deformed = add_noise(reference, sigma, seed=3), add_noise(deformed, sigma, seed=4)
    origin, step, grid = grid_for_volume(shape, 11, 6)
    base = DisplacementField.zeros(origin, step, grid, params={"subvolume": 11})
    field = base.replace(u=sample_displacement(truth, base.points).reshape((*grid, 3)))
    cylinder = Cylinder((23.5, 23.5), 0.46 * 48 - 3.0)
    region = specimen_mask(shape, cylinder)
    assert 0.4 < region.mean() < 0.7
    whole = evaluate_fields(reference, deformed, {"f": field}, keep_volumes=True)
    inside = evaluate_fields(reference, deformed, {"f": field}, region=region)
    # without the region, phase 0 is the air (gray ~0.1); inside, both phases are concrete
    assert whole.phases_reference[0].mean_gray < 0.2
    assert min(s.mean_gray for s in inside.phases_reference) > 0.5
    assert sum(s.voxels for s in inside.phases_reference) == int(region.sum())
    assert np.all(np.isnan(inside["f"].residual[~region]))
    assert inside["f"].voxels <= int(region.sum())
    assert inside.contrast < 0.2 * whole.contrast  # aggregates are 5 % brighter, not air


# --- the pieces of the pair's measurement ------------------------------------------------------
def test_background_sums_give_eq_1_per_phase_and_over_all():
    from napari_dvc_correct.engine.evaluation import accuracy_pair

    background = accuracy_pair.background_from_sums(
        np.array([10.0, 0.0, 30.0]), np.array([5, 0, 10]), 2
    )
    assert background.mean == pytest.approx(40.0 / 15) and background.voxels == 15
    assert background.per_phase[0] == (0, 2.0, 5) and background.per_phase[2] == (2, 3.0, 10)
    assert np.isnan(background.per_phase[1][1])  # a phase never on both sides
    empty = accuracy_pair.background_from_sums(np.zeros(2), np.zeros(2, int), 1)
    assert empty.mean == np.inf and empty.voxels == 0


def test_the_best_candidate_is_the_one_of_smallest_r0():
    from napari_dvc_correct.engine.evaluation import accuracy_pair
    from napari_dvc_correct.engine.evaluation.gray_levels import GrayLevelMap

    identity = GrayLevelMap.identity()

    def r0(value, voxels=10):
        return accuracy_pair.background_from_sums(np.array([value * voxels]), np.array([voxels]), 0)

    best = accuracy_pair.choose_best(
        {"plain": (identity, r0(3.0)), "corrected": (identity, r0(2.0))}
    )
    assert best.measured_with == "corrected" and best.background.mean == pytest.approx(2.0)
    assert best.candidates == {"plain": pytest.approx(3.0), "corrected": pytest.approx(2.0)}
    assert best.to_dict()["background_residual"] == pytest.approx(2.0)
    empty = accuracy_pair.background_from_sums(np.zeros(1), np.zeros(1, int), 0)
    with pytest.raises(ValueError, match="background residual is undefined"):
        accuracy_pair.choose_best({"only": (identity, empty)})
    volume = np.arange(64**3, dtype=np.float32).reshape(64, 64, 64)
    sample = accuracy_pair.lattice(volume)
    assert sample.ndim == 1 and sample[0] == 0.0 and sample.size <= volume.size


def test_the_pairs_map_keeps_the_full_contrast_under_noise(pair):
    """Least squares of G on the noisy moved scan reads a smaller contrast; the pair's map
    takes the loaded scan's measured noise out (errors in variables)."""
    reference, deformed, exact = pair
    louder = add_noise(deformed, 12.0, seed=5)  # the loaded scan far noisier than the reference
    result = evaluate_fields(reference, louder, {"exact": exact}, keep_volumes=False)
    gray = result.pair.gray_levels
    assert gray.fit == "errors in variables"
    assert gray.contrast == pytest.approx(1.0, abs=0.03)  # least squares: 0.88
    assert result.pair.to_dict()["gray_levels"]["fit"] == "errors in variables"


def test_the_pair_s_noise_in_words_is_empty_where_not_measured():
    from dataclasses import replace

    from napari_dvc_correct.engine.evaluation.accuracy_pair import PairStatistics
    from napari_dvc_correct.engine.evaluation.noise_correlation import NoiseCorrelation

    pair = PairStatistics(None, None, "field", {})
    assert pair.noise_text() == ""
    white = replace(pair, noise_correlation=NoiseCorrelation.white())
    assert white.noise_text() == NoiseCorrelation.white().describe()
