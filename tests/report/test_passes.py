"""The correction's flag line counts the nodes a user asked to measure (not the masked ones)."""

from __future__ import annotations

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.report.passes import flag_line


def _corrected(**info) -> DisplacementField:
    field = DisplacementField.zeros((0.0, 0.0, 0.0), (5, 5, 5), (4, 5, 5))
    field.metadata["correction"] = info
    return field


def test_the_flagged_share_is_of_the_measured_nodes():
    # 100 nodes, 40 of them outside the user's mask: 12 flagged of 60 measured is 20 %, not 12 %
    line = flag_line(_corrected(flagged_after=12, discontinuity_nodes=8, measured_nodes=60))
    assert "4 nodes whose residual no small error explains" in line
    assert "8 along a discontinuity" in line
    assert "20.0% of the 60 measured nodes" in line


def test_a_record_without_the_measured_count_says_no_share():
    # fields corrected before the count was recorded still read
    line = flag_line(_corrected(flagged_after=3, discontinuity_nodes=0))
    assert line.startswith("flagged after the passes: 3 nodes") and "measured" not in line
    assert flag_line(DisplacementField.zeros((0.0,) * 3, (5,) * 3, (2, 2, 2))) == ""
