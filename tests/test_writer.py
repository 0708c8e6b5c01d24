"""The npe2 writer: field files from the layers the plugin made."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct._writer import write_fields
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.io.npz import load_field
from napari_dvc_correct.layers import field_layers
from napari_dvc_correct.viewer_layers import show_layers


def _field(value: float) -> DisplacementField:
    field = DisplacementField.zeros((7, 7, 7), (4, 4, 4), (2, 3, 4))
    field.u[...] = value
    field.u[..., 2] = np.arange(4) * value
    return field


def test_writes_the_field_behind_a_layer_not_the_display_data(tmp_path):
    field = _field(0.5)
    vectors = next(t for t in field_layers(field) if t[2] == "vectors")
    data, kwargs, layer_type = vectors
    written = write_fields(str(tmp_path / "out"), [(data, kwargs, layer_type)])
    assert written == [str(tmp_path / "out.dvcfield")]  # the kind napari opens with our reader
    loaded = load_field(written[0])
    np.testing.assert_array_equal(loaded.u, field.u)
    assert loaded.shape == (2, 3, 4)


def test_layers_of_two_fields_give_two_files(tmp_path):
    layers = field_layers(_field(0.5), "uncorrected") + field_layers(_field(0.25), "corrected")
    written = write_fields(str(tmp_path / "both.npz"), layers)
    assert sorted(written) == sorted(
        [str(tmp_path / "both_uncorrected.npz"), str(tmp_path / "both_corrected.npz")]
    )
    np.testing.assert_allclose(load_field(tmp_path / "both_corrected.npz").u[0, 0, 1], 0.25)


def test_layers_not_made_by_the_plugin_are_refused(tmp_path):
    with pytest.raises(ValueError, match="none of the selected layers"):
        write_fields(str(tmp_path / "x.npz"), [(np.zeros((3, 3)), {"name": "mine"}, "image")])
    assert list(tmp_path.iterdir()) == []


def test_napari_saves_a_plugin_layer_through_the_writer(tmp_path, make_napari_viewer):
    viewer = make_napari_viewer()
    field = _field(1.5)
    (layer,) = show_layers(viewer, [t for t in field_layers(field) if t[2] == "vectors"])
    viewer.layers.selection = {layer}
    written = viewer.layers.save(
        str(tmp_path / "saved.npz"), selected=True, plugin="napari-dvc-correct"
    )
    assert written == [str(tmp_path / "saved.npz")]
    np.testing.assert_array_equal(load_field(tmp_path / "saved.npz").u, field.u)


def test_an_npz_that_is_not_a_field_file_is_never_replaced(tmp_path):
    # File > Save Selected Layers onto the scans' rock.npz (opened in the viewer) replaced the
    # scans with the field; an earlier field file may still be saved over
    scans = tmp_path / "rock.npz"
    np.savez(scans, reference=np.zeros((4, 4, 4), np.uint8))
    before = scans.read_bytes()
    layers = field_layers(_field(0.5), "uncorrected")
    with pytest.raises(ValueError, match="rock.npz is not a field file"):
        write_fields(str(scans), layers)
    assert scans.read_bytes() == before
    assert write_fields(str(tmp_path / "f.npz"), layers) == [str(tmp_path / "f.npz")]
    assert write_fields(str(tmp_path / "f.npz"), field_layers(_field(0.25), "x"))  # over a field
    np.testing.assert_allclose(load_field(tmp_path / "f.npz").u[0, 0, 1], 0.25)


def test_a_series_layer_writes_every_state(tmp_path):
    # Save Selected Layers on a 4-D series layer wrote its last state alone, under the plain name
    states = [_field(0.0), _field(0.5), _field(1.0), _field(1.5)]
    layers = field_layers(states, "series (total)")
    written = write_fields(str(tmp_path / "run.dvcfield"), layers[:1])
    assert sorted(written) == [str(tmp_path / f"run_state_{k}_total.dvcfield") for k in (1, 2, 3)]
    for k, name in enumerate(sorted(written), start=1):
        np.testing.assert_allclose(load_field(name).u, states[k].u)
