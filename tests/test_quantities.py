"""The quantities a field layer shows: known values on known fields, physical units."""

from __future__ import annotations

import numpy as np

from napari_dvc_correct import quantities as Q
from napari_dvc_correct.engine.fields.field import DisplacementField


def _uniaxial(shape=(6, 7, 8), e=0.01, voxel_size=(1.0, 1.0, 1.0)):
    """u_z = e * z on a grid of step 4 (voxels): εzz = e, everything else zero."""
    z = (np.arange(shape[0]) * 4.0)[:, None, None]
    u = np.zeros((*shape, 3))
    u[..., 0] = e * z
    return DisplacementField(
        origin=(0, 0, 0), step=(4, 4, 4), u=u, metadata={"voxel_size": list(voxel_size)}
    )


def test_every_quantity_has_its_known_value_on_a_uniaxial_field():
    e = 0.01
    field = _uniaxial(e=e)
    inner = (slice(1, -1),) * 3  # central differences everywhere but the edges
    expected = {
        "εzz": e,
        "εyy": 0.0,
        "εxx": 0.0,
        "εzy": 0.0,
        "ε1": e,
        "ε2": 0.0,
        "ε3": 0.0,
        "εvol": e,
        "γmax": e,
        "εeq": 2 * e / 3,  # octahedral strain of diag(e, 0, 0)
        "ux": 0.0,
    }
    for quantity, value in expected.items():
        values = Q.quantity_values(field, quantity)
        np.testing.assert_allclose(values[inner], value, atol=1e-7, err_msg=quantity)
    np.testing.assert_allclose(Q.quantity_values(field, "uz")[3, 0, 0], e * 12.0, rtol=1e-6)
    assert Q.unit_of("uz", field) == "vx" and Q.unit_of("εeq", field) == "strain, –"
    assert "uncertainty" not in Q.available_quantities(field)
    assert "residual" in Q.available_quantities(field, residual=True)


def test_displacements_and_strains_use_the_physical_voxel_size():
    """Anisotropic voxels: u_z = e z in voxels is e * 2 µm per 2 µm: the strain stays e."""
    e = 0.01
    field = _uniaxial(e=e, voxel_size=(2.0, 1.0, 1.0))
    assert Q.unit_of("|u|", field) == "scale units"  # a voxel size without a unit
    field.metadata["unit"] = "µm"
    np.testing.assert_allclose(Q.quantity_values(field, "uz")[3, 0, 0], 2 * e * 12.0, rtol=1e-6)
    np.testing.assert_allclose(Q.quantity_values(field, "εzz")[2, 2, 2], e, rtol=1e-6)
    assert Q.unit_of("|u|", field) == "µm"


def test_uncertainty_shows_when_the_field_has_one():
    field = _uniaxial()
    field.uncertainty = np.full((*field.shape, 3), 0.1)
    assert "uncertainty" in Q.available_quantities(field)
    values = Q.quantity_values(field, "uncertainty")
    np.testing.assert_allclose(values[0, 0, 0], 0.1 * np.sqrt(3), rtol=1e-6)
