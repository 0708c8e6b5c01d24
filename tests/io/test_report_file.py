"""A report of values as a file (io/report_file.py): JSON and Markdown with known contents."""

import json

import numpy as np
import pytest

from napari_dvc_correct.io import report_file


def test_report_json_and_markdown(tmp_path):
    report = {
        "title": "accuracy",
        "accuracy index": np.float64(0.93),
        "phases": {"mean gray": [100.0, 170.0]},
    }
    data = json.loads(report_file.export_report(report, tmp_path / "r.json").read_text())
    assert data["accuracy index"] == pytest.approx(0.93)
    text = report_file.export_report(report, tmp_path / "r.md").read_text()
    assert "# accuracy" in text and "| accuracy index | 0.93 |" in text and "## phases" in text
