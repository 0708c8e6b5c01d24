"""The self-correction passes in words and rows: one wording for every front end."""

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.report import passes


def test_orders_and_subvolumes_in_words():
    assert [passes.order_text(k) for k in (0, 1, 2)] == ["—", "first", "second"]
    assert passes.subvolume_text(15) == "15³" and passes.subvolume_text(0) == "—"


def test_a_field_whose_passes_changed_method(changed_method_field):
    field, method = changed_method_field
    assert passes.first_run_parameters(field) == (1, 21)
    assert passes.changed_parameters(field)
    assert passes.method_lines(field) == [f"passes 1–2: {method}"]
    rows = passes.pass_rows(field)
    assert [row["pass"] for row in rows] == [0, 1, 2]
    assert [(row["order"], row["subvolume"], row["applied"]) for row in rows] == [
        ("—", "—", "—"),
        ("second", "15³", "yes"),
        ("second", "15³", "yes"),
    ]
    assert [row["mean_gray_residual"] for row in rows] == [3.0, 2.5, 2.0]
    assert rows[1]["accepted_nodes"] == 20 and rows[1]["refused_nodes"] == 7


def test_a_field_with_no_pass_says_its_method_once():
    # no pass ran: the fallback words must not repeat the callers' own "correcting matches"
    field = DisplacementField.zeros((8, 8, 8), (4, 4, 4), (2, 2, 2))
    method = "the first run's parameters (first order, 31³)"
    field.metadata["correction"] = {"pass_method": method}
    assert passes.method_lines(field) == [method]


def test_an_uncorrected_field_has_no_words():
    field = DisplacementField.zeros((8, 8, 8), (4, 4, 4), (2, 2, 2))
    assert passes.pass_rows(field) == [] and passes.method_lines(field) == []
    assert not passes.changed_parameters(field)
    assert passes.gray_level_line(field) == "" and passes.flag_line(field) == ""


def test_gray_levels_and_flags_in_words():
    field = DisplacementField.zeros((8, 8, 8), (4, 4, 4), (2, 2, 2))
    field.metadata["gray_levels"] = {"description": "contrast 1.02, offset -3"}
    field.metadata["correction"] = {
        "flagged_after": 5, "discontinuity_nodes": 2, "shielded_nodes": 4,
    }  # fmt: skip
    assert passes.gray_level_line(field).startswith(
        "gray levels of the loaded scan mapped onto the reference's: contrast 1.02, offset -3"
    )
    text = passes.flag_line(field)
    assert "3 nodes whose residual" in text and "2 along a discontinuity" in text
    assert text.endswith("; 4 nodes near it kept their values")


def _corrected(**info) -> DisplacementField:
    field = DisplacementField.zeros((0.0, 0.0, 0.0), (5, 5, 5), (4, 5, 5))
    field.metadata["correction"] = info
    return field


def test_the_flagged_share_is_of_the_measured_nodes():
    # 100 nodes, 40 of them outside the user's mask: 12 flagged of 60 measured is 20 %, not 12 %
    line = passes.flag_line(_corrected(flagged_after=12, discontinuity_nodes=8, measured_nodes=60))
    assert "4 nodes whose residual no small error explains" in line
    assert "8 along a discontinuity" in line
    assert "20.0% of the 60 measured nodes" in line


def test_a_record_without_the_measured_count_says_no_share():
    # fields corrected before the count was recorded still read
    line = passes.flag_line(_corrected(flagged_after=3, discontinuity_nodes=0))
    assert line.startswith("flagged after the passes: 3 nodes") and "measured" not in line
    assert passes.flag_line(DisplacementField.zeros((0.0,) * 3, (5,) * 3, (2, 2, 2))) == ""


def test_the_regularised_nodes_in_words():
    field = DisplacementField.zeros((0.0, 0.0, 0.0), (5.0, 5.0, 5.0), (2, 2, 2))
    assert passes.noise_fit_line(field) == ""
    field.metadata["correction"] = {"noise_fit": None}  # switched off
    assert passes.noise_fit_line(field) == ""
    field.metadata["correction"] = {
        "noise_fit": {
            "neighbourhood_nodes": 3,
            "eligible_nodes": 187,
            "fitted_nodes": 169,
            "median_variance_ratio": 0.14,
            "fitted": [],
        }
    }
    line = passes.noise_fit_line(field)
    assert "169 nodes" in line and "3³" in line and "187 tested" in line and "x0.14" in line
    field.metadata["correction"]["noise_fit"]["not_run"] = "the field carries no uncertainty"
    assert passes.noise_fit_line(field) == "regularised: no node (the field carries no uncertainty)"


def test_the_oriented_step_in_words():
    field = DisplacementField.zeros((8, 8, 8), (4, 4, 4), (2, 2, 2))
    assert passes.oriented_line(field) == ""
    field.metadata["correction"] = {"oriented": {"ran": False, "reason": "no node varies"}}
    assert passes.oriented_line(field) == ""  # the usual case says nothing
    field.metadata["correction"]["oriented"] = {
        "ran": True,
        "planar_nodes": 120,
        "matched_nodes": 118,
        "accepted_nodes": 97,
        "across": 2.5,
        "along": 10.0,
        "subvolume": 31,
    }
    line = passes.oriented_line(field)
    assert "97 of 120 nodes" in line and "std 2.5 voxels across" in line
    assert "10 along" in line and "31³ boxes" in line
    assert "blur" not in line
    field.metadata["correction"]["oriented"]["deblurred_nodes"] = 90
    line = passes.oriented_line(field)
    assert "blur taken out of 90 of them" in line and line.endswith("cubes after the passes")


def test_the_correction_residual_says_its_frame_and_gray_levels():
    field = DisplacementField.zeros((8.0, 8.0, 8.0), (4.0, 4.0, 4.0), (2, 2, 2))
    field.metadata["correction"] = {"frame": "reference"}
    assert passes.residual_frame(field) == "|F(X + u) − G(X)|, reference frame, raw gray levels"
    field.metadata["correction"]["frame"] = "loaded"
    field.metadata["gray_levels"] = {"description": "G ≈ 2·F"}
    assert passes.residual_frame(field) == "|map(F) − G'|, loaded frame, reference gray levels"
