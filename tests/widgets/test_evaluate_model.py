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
