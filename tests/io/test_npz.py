import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status
from napari_dvc_correct.io.npz import FORMAT_VERSION, load_field, save_field


def _field(shape=(2, 3, 4), seed=0):
    rng = np.random.default_rng(seed)
    status = rng.integers(0, len(Status), shape).astype(np.uint8)
    return DisplacementField(
        origin=(5, 6, 7),
        step=(4, 4, 2),
        u=rng.normal(size=(*shape, 3)),
        zncc=rng.random(shape),
        status=status,
        iterations=rng.integers(0, 9, shape),
        provenance=np.full(shape, Provenance.REPLACED, np.uint8),
        gradient=rng.normal(size=(*shape, 3, 3)),
        params={"subvolume": 21},
        metadata={"a": [1, 2]},
    )


@settings(max_examples=25, deadline=None)
@given(nz=st.integers(1, 4), ny=st.integers(1, 4), nx=st.integers(1, 4), seed=st.integers(0, 99))
def test_round_trip(tmp_path_factory, nz, ny, nx, seed):
    path = tmp_path_factory.mktemp("npz") / "field.npz"
    field = _field((nz, ny, nx), seed)
    save_field(field, path)
    back = load_field(path)
    assert back.same_grid(field)
    for name in ("u", "zncc", "status", "iterations", "provenance", "gradient"):
        assert np.array_equal(getattr(back, name), getattr(field, name))
    assert back.params == field.params and back.metadata == field.metadata


def test_flat_arrays_readable_without_the_package(tmp_path):
    field = _field()
    save_field(field, tmp_path / "f.npz")
    with np.load(tmp_path / "f.npz") as data:
        points, displacement = data["points"], data["displacement"]
    assert points.shape == (24, 3) and displacement.shape == (24, 3)
    assert np.allclose(points[1], [5, 6, 9])  # x varies fastest, step 2
    # measurements only: nodes whose status is not good (LOW_ZNCC, replaced...) are NaN
    good = np.isin(field.status.reshape(-1), [Status.CONVERGED, Status.MAX_ITERATIONS])
    assert good.any() and (~good).any()
    assert np.allclose(displacement[good], field.u.reshape(-1, 3)[good])
    assert np.all(np.isnan(displacement[~good]))


def test_uncertainty_round_trip_and_older_files_without_it(tmp_path):
    field = _field()
    field.uncertainty = np.abs(np.random.default_rng(3).normal(size=(*field.shape, 3)))
    field.uncertainty[0, 0, 0] = np.nan
    save_field(field, tmp_path / "f.npz")
    back = load_field(tmp_path / "f.npz")
    np.testing.assert_array_equal(back.uncertainty, field.uncertainty)
    assert np.all(np.isfinite(back.u))  # the grid keeps every value
    with np.load(tmp_path / "f.npz") as data:
        old = {k: data[k] for k in data.files if k != "uncertainty"}
    np.savez(tmp_path / "old.npz", **old)
    assert load_field(tmp_path / "old.npz").uncertainty is None


def test_newer_format_is_refused(tmp_path):
    path = tmp_path / "future.npz"
    np.savez(
        path,
        format=np.array("napari-dvc-correct field"),
        format_version=np.array(FORMAT_VERSION + 1),
        origin=np.zeros(3),
        step=np.ones(3),
        u=np.zeros((1, 1, 1, 3)),
    )
    with pytest.raises(ValueError, match="newer"):
        load_field(path)


@pytest.mark.parametrize("content", [b"not a zip at all", b"PK\x03\x04broken"])
def test_broken_files_are_refused(tmp_path, content):
    path = tmp_path / "broken.npz"
    path.write_bytes(content)
    with pytest.raises(ValueError):
        load_field(path)


def test_foreign_npz_is_refused(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, volume=np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="not a napari-dvc-correct field"):
        load_field(path)


def test_failed_write_leaves_earlier_file_intact(tmp_path, monkeypatch):
    path = tmp_path / "f.npz"
    save_field(_field(seed=1), path)
    before = path.read_bytes()

    def explode(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(np, "savez_compressed", explode)
    with pytest.raises(RuntimeError):
        save_field(_field(seed=2), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["f.npz"]


def test_metadata_with_numpy_values_is_serialised(tmp_path):
    field = _field()
    field.metadata["shift"] = np.array([1, 2, 3])
    field.metadata["value"] = np.float32(2.5)
    save_field(field, tmp_path / "f.npz")
    assert load_field(tmp_path / "f.npz").metadata["shift"] == [1, 2, 3]
    json.dumps(load_field(tmp_path / "f.npz").metadata)


def test_non_numeric_format_version_names_the_file(tmp_path):
    path = tmp_path / "odd.npz"
    np.savez(
        path,
        format=np.array("napari-dvc-correct field"),
        format_version=np.array("one"),
        origin=np.zeros(3),
        step=np.ones(3),
        u=np.zeros((1, 1, 1, 3)),
    )
    with pytest.raises(ValueError, match=r"odd\.npz has a non-numeric field format version 'one'"):
        load_field(path)
