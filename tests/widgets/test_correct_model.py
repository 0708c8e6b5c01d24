"""The Self-correct panel without Qt: the per-pass rows and the messages, from a field's records."""

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.widgets import correct_model as model


def test_pass_rows_and_the_changed_method(changed_method_field):
    field, method = changed_method_field
    assert model.pass_rows(field) == [
        ("0 (input)", "—", "—", "3.000", "—", "0 %"),
        ("1", "second", "15³", "2.500", "yes", "25 %"),
        ("2", "second", "15³", "2.000", "yes", "25 %"),
    ]
    assert model.method_message(field) == (
        f"Correcting matches changed from your first order, 21³: passes 1–2: {method}."
    )
    field.params = {"order": 2, "subvolume": 15}
    assert model.method_message(field).startswith(
        "Correcting matches as you chose (second order, 15³): "
    )


def test_the_summary_says_before_after_why_it_stopped_and_in_which_frame():
    field = DisplacementField.zeros((8.0, 8.0, 8.0), (4.0, 4.0, 4.0), (2, 2, 2))
    assert model.pass_rows(field) == [] and model.method_message(field) == ""
    field.metadata["correction"] = {
        "mean_gray_residual_before": 4.0, "mean_gray_residual_after": 2.5,
        "passes_applied": 2, "stop_reason": "the residual stopped falling", "frame": "reference",
    }  # fmt: skip
    assert model.summary_message(field) == (
        "Mean gray residual (|F(X + u) − G(X)|, reference frame, raw gray levels) 4.000 → 2.500 "
        "(2 pass(es) applied). Stopped: the residual stopped falling."
    )
    field.metadata["correction"]["frame"] = "loaded"
    field.metadata["gray_levels"] = {"description": "G ≈ 2·F"}
    assert model.summary_message(field).endswith(
        "Gray levels of the loaded scan mapped onto the reference's: G ≈ 2·F; residuals are in "
        "the reference's gray levels."
    )


def test_a_corrected_field_is_named_after_its_source():
    """Correcting an opened field 'aldvc' never replaces another field's '(corrected)' layers
    (user audit, item 2); the corrected ones are not offered again."""
    corrected_source, is_corrected = model.corrected_source, model.is_corrected
    cases = {
        "uncorrected": "corrected",
        "series (total)": "series (total, corrected)",
        "aldvc": "aldvc, corrected",
        "aldvc [1]": "aldvc [1], corrected",
    }
    assert {source: corrected_source(source) for source in cases} == cases
    assert all(is_corrected(name) for name in cases.values())
    assert not any(is_corrected(source) for source in cases)


def test_before_after_pairs_a_field_with_its_own_corrected_one():
    """View ▸ Before ⇄ after toggles the opened field 'aldvc' with 'aldvc, corrected', not only
    the panel's own 'uncorrected' / 'corrected'."""
    sources = ["uncorrected", "aldvc", "corrected", "aldvc, corrected"]
    pair = model.before_after_pair
    assert pair(sources, ["aldvc"]) == ("aldvc", "aldvc, corrected")
    assert pair(sources, ["aldvc, corrected"]) == ("aldvc, corrected", "aldvc")
    assert pair(sources, ["uncorrected"]) == ("uncorrected", "corrected")
    assert pair(sources, ["corrected"]) == ("corrected", "uncorrected")
    assert pair(sources, sources)[1] == "corrected"  # all overlaid: as before
    assert pair(["aldvc", "snow48"], ["aldvc"]) is None  # nothing corrected yet


def test_a_series_says_which_state_each_method_line_is_for(changed_method_field):
    # the dock printed one "Correcting matches ..." sentence per state with no state named
    from types import SimpleNamespace

    changed, _ = changed_method_field
    chosen = changed.copy()
    chosen.params = {"order": 2, "subvolume": 15}
    plain = DisplacementField.zeros((8.0, 8.0, 8.0), (4.0, 4.0, 4.0), (2, 2, 2))
    results = [SimpleNamespace(field=f) for f in (chosen, changed, chosen, plain)]
    text = model.series_method_message(results)
    assert text == (
        f"States 1 and 3: {model.method_message(chosen)} State 2: {model.method_message(changed)}"
    )


def test_every_stage_of_a_series_correction_says_which_state_of_how_many(monkeypatch):
    """The stage line named the state only at its start ("state 2/3: self-correcting"), then
    showed the passes' stages alone; now each of them is led by "state k of n"."""
    from napari_dvc_correct.engine.progress import Progress

    def fake_correction(reference, deformed, field, **options):
        yield Progress("correction pass 1", 1, 2, "IC-GN")
        return model.CorrectionResult(field=field, voxel_size=(1.0,) * 3, offset=(0.0,) * 3)

    monkeypatch.setattr(model, "run_correction", fake_correction)
    fields = [DisplacementField.zeros((8.0,) * 3, (4.0,) * 3, (2, 2, 2)) for _ in range(3)]
    pairs = [(None, None)] * 3
    generator = model.run_series_correction(pairs, fields)
    stages = []
    while True:
        try:
            stages.append(next(generator).stage)
        except StopIteration as stop:
            result = stop.value
            break
    assert stages == [
        f"state {k} of 3{suffix}" for k in (1, 2, 3) for suffix in ("", ": correction pass 1")
    ]
    assert len(result.results) == 3
