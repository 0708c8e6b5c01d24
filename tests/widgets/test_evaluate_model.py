"""The Evaluate panel's Qt-free model: histogram, live phases, report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from napari_dvc_correct.widgets import evaluate_model as model


def test_histogram_and_subsampling():
    volume = np.zeros((100, 100, 100), np.float32)
    volume[50:] = 1.0
    sample = model.sample_voxels(volume, max_samples=10_000)
    assert sample.size <= 10_000
    assert 0.4 < sample.mean() < 0.6
    counts, edges = model.gray_histogram(volume, bins=10)
    assert counts.sum() == model.sample_voxels(volume).size
    assert edges[0] == 0.0 and edges[-1] == 1.0


def test_phase_preview_labels_and_means():
    volume = np.array([10.0, 20.0, 30.0, np.nan]).reshape(1, 1, 4)
    preview = model.phase_preview(volume, [15.0, 25.0])
    np.testing.assert_array_equal(preview.labels.ravel(), [1, 2, 3, 0])
    np.testing.assert_allclose(preview.mean_gray, [10.0, 20.0, 30.0])
    assert "phase 3: mean gray 30.0" in preview.text()
    with pytest.raises(ValueError, match="increasing"):
        model.phase_preview(volume, [25.0, 15.0])


def test_automatic_thresholds_split_two_grays():
    rng = np.random.default_rng(0)
    volume = np.where(rng.random((20, 20, 20)) < 0.3, 170.0, 100.0) + rng.normal(0, 3, (20,) * 3)
    (threshold,) = model.automatic_thresholds(volume, 2)
    assert 110 < threshold < 160


def test_report_of_a_real_evaluation():
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
    from napari_dvc_correct.engine.fields.field import DisplacementField
    from napari_dvc_correct.engine.synthetic import two_phase_volume

    volume = two_phase_volume((32, 32, 32), seed=2)
    field = DisplacementField.zeros((8.0, 8.0, 8.0), (8.0, 8.0, 8.0), (3, 3, 3))
    evaluation = evaluate_fields(volume, volume, {"zero": field}, phases=[135.0])
    report = model.evaluation_report(evaluation)
    json.dumps(report)  # JSON-friendly
    item = report["field: zero"]
    assert item["mean gray residual"] == pytest.approx(0.0, abs=1e-3)  # identical volumes
    assert item["accuracy index p"] == pytest.approx(1.0, abs=1e-3)
    assert "zero: mean residual" in model.summary_text(evaluation)


def test_temporary_folders_go_when_nothing_reads_them():
    from napari_dvc_correct.widgets.evaluate_model import TemporaryFolders

    folders = TemporaryFolders()
    first = folders.new(["uncorrected", "corrected"])
    second = folders.new(["corrected"])
    one, two = first["corrected"].parent, second["corrected"].parent
    assert one != two and one.is_dir() and two.is_dir() and one.name.startswith("dvc-evaluate-")
    (one / "residual_1.zarr").mkdir()  # as a run writes it
    folders.release([str(two)])  # a layer still reads the second
    assert not one.exists() and two.is_dir() and folders.folders == [two]
    folders.release([None, str(two)])
    assert two.is_dir()
    folders.remove_all()
    assert not two.exists() and folders.folders == []


def test_the_summary_marks_bounds_and_the_field_carries_the_resolution():
    """A noisy pair evaluated with the exact (zero) field: the residual resolves no error, so
    the median is shown as a bound ("< x", x the median resolution), the lines say what
    "likely" means, and the estimate left on the field carries its resolution."""
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
    from napari_dvc_correct.engine.evaluation.error_estimate import resolution_of
    from napari_dvc_correct.engine.fields.field import DisplacementField
    from napari_dvc_correct.engine.synthetic import add_noise, two_phase_volume

    volume = two_phase_volume((32, 32, 32), seed=2)
    field = DisplacementField.zeros((8.0, 8.0, 8.0), (8.0, 8.0, 8.0), (3, 3, 3))
    evaluation = evaluate_fields(
        add_noise(volume, 3.0, seed=1), add_noise(volume, 3.0, seed=2), {"zero": field}
    )
    item = evaluation["zero"]
    error = item.error
    assert error["below_resolution"] >= 0.5 and error["median_is_bound"]
    (line,) = model.field_lines(item)
    assert f"error estimate median < {error['median_bound']:.3f} voxel" in line
    assert "likely > 0.5 voxel (P ≥ ½)" in line and "possibly (P ≥ 16 %" in line
    assert f"resolution {error['resolution']:.3f} voxel (median)" in line
    report = model.evaluation_report(evaluation)["field: zero"]
    assert report["residual's resolution, median (voxels)"] == pytest.approx(error["resolution"])
    model.attach_estimate(field, item, evaluation)
    np.testing.assert_allclose(resolution_of(field), item.error_resolution, atol=1e-6)


def test_every_stage_of_a_series_evaluation_says_which_pair_of_how_many(monkeypatch):
    from napari_dvc_correct.engine.progress import Progress, run_to_completion
    from napari_dvc_correct.widgets import evaluate_model

    def fake_evaluation(reference, deformed, fields, *args, **options):
        yield Progress("residual", 1, 1)
        return "evaluation"

    monkeypatch.setattr(evaluate_model, "run_evaluation", fake_evaluation)
    groups = [(f"state {k}", None, None, {}) for k in (1, 2)]
    stages = []

    def collect():
        for progress in evaluate_model.run_groups(groups, None):
            stages.append(progress.stage)
            yield progress

    run_to_completion(collect())
    assert stages == [
        "state 1 (1 of 2)", "state 1 (1 of 2): residual",
        "state 2 (2 of 2)", "state 2 (2 of 2): residual",
    ]  # fmt: skip
