"""The record of a correction pass: written to a field's metadata and read back, old files too."""

import math

from napari_dvc_correct.engine.correction.record import (
    CorrectionPass,
    correction_table,
    distinct_values,
)
from napari_dvc_correct.engine.fields.field import DisplacementField


def test_a_record_survives_the_metadata_round_trip():
    entry = CorrectionPass(
        2, 1.5, residual_before=2.0, accepted=True, fraction_changed=0.25, noise_floor=1.0,
        local_residual_before=2.5, local_residual_after=1.8, accepted_nodes=20,
        rejected_nodes=3, improved_nodes=5, mean_change=0.1, max_change=0.4,
        converged_fraction=1.0, seconds=1.0, order=2, subvolume=15, method="the field bends",
    )  # fmt: skip
    stored = entry.to_dict()
    assert stored["pass"] == 2 and "number" not in stored  # the key older readers use
    assert CorrectionPass.from_dict(stored) == entry
    field = DisplacementField.zeros((8, 8, 8), (4, 4, 4), (2, 2, 2))
    assert correction_table(field) == []
    field.metadata["correction_passes"] = [stored, entry]  # as stored, or still a record
    assert correction_table(field) == [entry, entry]


def test_an_older_record_reads_with_defaults():
    old = {"pass": "1", "mean_gray_residual": 3.0, "accepted": True, "fraction_changed": 0.5}
    old |= {"mean_change": 0.1, "max_change": 0.2, "converged_fraction": 1.0, "seconds": 2.0}
    old["field_we_no_longer_keep"] = 7
    entry = CorrectionPass.from_dict(old)
    assert entry.number == "1" and entry.residual_before == 3.0  # before = after when unknown
    assert math.isnan(entry.noise_floor) and entry.accepted_nodes == 0
    assert entry.order == 0 and entry.method == ""  # not recorded


def test_distinct_values_shows_the_digits_that_differ():
    assert distinct_values(2.6147, 2.6152) == ("2.6147", "2.6152")  # 4 digits read 2.615 twice
    assert distinct_values(53.68, 60.36) == ("53.68", "60.36")
    assert distinct_values(1.0, 1.0) == ("1", "1")  # equal: no search for a difference
    assert distinct_values(1.0, 1.0 + 1e-14) == ("1", "1")  # beyond 10 digits: stops there
