"""Fixtures shared by the tests of several front ends (panel, command line, report)."""

from __future__ import annotations

import pytest


@pytest.fixture
def changed_method_field():
    """A corrected field whose passes matched second order on 15³ while the user chose first
    order on 21³ (what the engine does on a curved field), without running the engine."""
    from napari_dvc_correct.engine.correction.record import CorrectionPass
    from napari_dvc_correct.engine.fields.field import DisplacementField

    field = DisplacementField.zeros((40, 40, 40), (8, 8, 8), (3, 3, 3))
    field.params = {"order": 1, "subvolume": 21}
    method = "second order on 15³ instead of first order on 21³: the field bends"
    common = dict(noise_floor=1.0, local_residual_before=2.0, local_residual_after=1.5)
    common |= dict(accepted_nodes=20, rejected_nodes=7, improved_nodes=5, mean_change=0.1)
    common |= dict(max_change=0.4, converged_fraction=1.0, seconds=1.0)
    field.metadata["correction_passes"] = [
        CorrectionPass(
            0, 3.0, residual_before=3.0, accepted=False, fraction_changed=0.0, **common
        ).to_dict(),
        *(
            CorrectionPass(
                k,
                3.0 - k / 2,
                residual_before=3.0,
                accepted=True,
                fraction_changed=0.25,
                order=2,
                subvolume=15,
                method=method,
                **common,
            ).to_dict()
            for k in (1, 2)
        ),
    ]
    field.metadata["correction"] = {
        "mean_gray_residual_before": 3.0,
        "mean_gray_residual_after": 2.0,
        "passes_applied": 2,
        "stop_reason": "max_passes (2) reached",
        "pass_method": method,
        "flagged_after": 14,
        "discontinuity_nodes": 11,
        "shielded_nodes": 6,
    }
    field.metadata["gray_levels"] = {"description": "G ≈ 2.3·F − 23 (local, 32-voxel cells)"}
    return field, method
