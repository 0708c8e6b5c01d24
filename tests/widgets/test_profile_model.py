"""A line profile across a field: linear interpolation between nodes, NaN off the grid."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.widgets import profile_model as P


@pytest.fixture
def field() -> DisplacementField:
    """u = (0.1 z, 0, 0) on nodes at z = 10 + 4 i (voxel size 2: world z = 20 + 8 i)."""
    shape = (6, 5, 5)
    origin, step = (10.0, 10.0, 10.0), (4.0, 4.0, 4.0)
    z = origin[0] + step[0] * np.arange(shape[0])
    u = np.zeros((*shape, 3))
    u[..., 0] = 0.1 * z[:, None, None]
    return DisplacementField(
        origin=origin, step=step, u=u, metadata={"voxel_size": [2.0, 2.0, 2.0]}
    )


def test_a_profile_of_a_linear_field_is_that_line(field):
    start, end = (20.0, 36.0, 36.0), (60.0, 36.0, 36.0)  # world: first to last node along z
    profile = P.line_profile(field, "uncorrected", "uz", start, end, n=11)
    assert profile.source == "uncorrected" and profile.quantity == "uz"
    np.testing.assert_allclose(profile.distance, np.linspace(0.0, 40.0, 11))
    z_voxels = np.linspace(20.0, 60.0, 11) / 2.0  # world / voxel size
    # a displacement is shown in the layers' units: voxels times the voxel size (float32 values)
    np.testing.assert_allclose(profile.values, 0.1 * z_voxels * 2.0, atol=1e-6)


def test_off_the_grid_is_nan_and_a_point_is_no_line(field):
    profile = P.line_profile(field, "f", "|u|", (0.0, 36.0, 36.0), (40.0, 36.0, 36.0), n=5)
    # world z 0 and 10 lie before the first node (20); 20, 30, 40 on the grid
    assert np.isnan(profile.values[:2]).all() and np.isfinite(profile.values[2:]).all()
    np.testing.assert_allclose(profile.values[2:], [2.0, 3.0, 4.0], atol=1e-6)  # 0.1 z, world
    with pytest.raises(ValueError, match="no length"):
        P.line_profile(field, "f", "|u|", (20.0, 36.0, 36.0), (20.0, 36.0, 36.0))


def test_the_cache_serves_the_second_call(field, monkeypatch):
    cache = {}
    first = P.line_profile(field, "f", "uz", (20, 36, 36), (60, 36, 36), n=5, values_cache=cache)
    assert list(cache) == [(id(field), "uz")]
    monkeypatch.setattr(P.L, "quantity_values", lambda *a: pytest.fail("computed again"))
    second = P.line_profile(field, "f", "uz", (20, 36, 36), (60, 36, 36), n=5, values_cache=cache)
    np.testing.assert_array_equal(first.values, second.values)


def test_profiles_pair_a_displacement_with_a_strain(field):
    assert P.strain_quantity("εzz") == "εzz" and P.strain_quantity("|u|") == "εeq"
    displacement, strain = P.profiles({"a": field, "b": field}, "uz", (20, 36, 36), (60, 36, 36))
    assert [p.quantity for p in displacement] == ["uz", "uz"]
    assert [p.source for p in displacement] == ["a", "b"]
    assert [p.quantity for p in strain] == ["εeq", "εeq"]
    # εzz = d(0.1 z)/dz = 0.1 everywhere: εeq of a uniaxial strain is 2/3 of it
    assert np.nanmax(np.abs(strain[0].values - 2 / 3 * 0.1)) < 1e-6  # float32 values
