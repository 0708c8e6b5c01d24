"""The npe2 reader: TIFF volumes, folders of slices, field files, and files that are not ours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_dvc_correct._reader import napari_get_reader
from napari_dvc_correct.engine.fields.field import DisplacementField, Status
from napari_dvc_correct.io.export import export_volume_tiff
from napari_dvc_correct.io.npz import save_field
from napari_dvc_correct.layers import field_of


@pytest.fixture
def field() -> DisplacementField:
    shape = (3, 4, 5)
    u = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1)
    status = np.zeros(shape, np.uint8)
    status[0, 0, 0] = Status.DIVERGED
    return DisplacementField(
        origin=(7.0, 7.0, 7.0),
        step=(4.0, 4.0, 4.0),
        u=0.1 * u,
        status=status,
        metadata={"voxel_size": [2.0, 1.0, 1.0], "offset": [5.0, 0.0, 0.0]},
    )


def test_field_file_opens_as_the_plugin_layers(field, tmp_path):
    path = tmp_path / "run1.npz"
    save_field(field, path)
    reader = napari_get_reader(str(path))
    assert reader is not None
    layers = reader(str(path))
    names = [kwargs["name"] for _, kwargs, _ in layers]
    assert names == ["|u| (run1)", "displacement (run1)"]  # one quantity at a time, and arrows
    for _data, kwargs, _layer_type in layers:
        assert kwargs["scale"] == (8.0, 4.0, 4.0)
        assert kwargs["translate"] == (19.0, 7.0, 7.0)
        np.testing.assert_array_equal(field_of(kwargs["metadata"]).u, field.u)
    magnitude = next(d for d, k, _ in layers if k["name"] == "|u| (run1)")
    assert np.isnan(magnitude[0, 0, 0])  # the diverged node is not shown as a value
    # |u| in the field's physical units: u = 0.1 * (1, 2, 3) voxels of size (2, 1, 1)
    np.testing.assert_allclose(magnitude[1, 2, 3], 0.1 * np.sqrt(4 + 4 + 9), rtol=1e-6)


@pytest.mark.parametrize("content", ["other arrays", "garbage"])
def test_an_npz_that_is_not_ours_goes_to_napari_s_reader(content, tmp_path):
    from napari_builtins.io import napari_get_reader as builtin

    path = tmp_path / "other.npz"
    if content == "other arrays":
        np.savez(path, volume=np.zeros((4, 4, 4)), format=np.array("something else"))
    else:
        path.write_bytes(b"PK\x03\x04 not really a zip file")
    assert napari_get_reader(str(path)) is builtin(str(path))


def test_tiff_volume_and_placement_round_trip(tmp_path):
    volume = np.random.default_rng(0).random((6, 7, 8)).astype(np.float32)
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, volume)
    ((data, kwargs, layer_type),) = napari_get_reader(str(plain))(str(plain))
    assert layer_type == "image" and kwargs["name"] == "plain"
    np.testing.assert_array_equal(data, volume)
    assert "scale" not in kwargs
    placed = tmp_path / "placed.tif"
    export_volume_tiff(volume, placed, scale=(2.0, 0.5, 0.5), translate=(1.0, 2.0, 3.0))
    ((data, kwargs, _),) = napari_get_reader(str(placed))(str(placed))
    np.testing.assert_array_equal(data, volume)
    assert kwargs["scale"] == [2.0, 0.5, 0.5] and kwargs["translate"] == [1.0, 2.0, 3.0]


def test_folder_of_tiff_slices(tmp_path):
    volume = np.arange(5 * 6 * 7, dtype=np.uint16).reshape(5, 6, 7)
    folder = tmp_path / "scan"
    folder.mkdir()
    for z in range(5):
        tifffile.imwrite(folder / f"slice_{z:03d}.tif", volume[z])
    ((data, kwargs, _),) = napari_get_reader(str(folder))(str(folder))
    np.testing.assert_array_equal(data, volume)
    assert kwargs["name"] == "scan"
    files = sorted(str(p) for p in folder.iterdir())
    ((data, _, _),) = napari_get_reader(files)(files)
    np.testing.assert_array_equal(data, volume)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert napari_get_reader(str(empty)) is None


def test_other_files_are_declined(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    assert napari_get_reader(str(path)) is None
    assert napari_get_reader(str(tmp_path / "missing.tif")) is None


def test_napari_opens_a_field_file_through_the_plugin(field, tmp_path, make_napari_viewer):
    path = tmp_path / "run2.npz"
    save_field(field, path)
    viewer = make_napari_viewer()
    viewer.open(str(path), plugin="napari-dvc-correct")
    assert "displacement (run2)" in viewer.layers
    np.testing.assert_allclose(viewer.layers["|u| (run2)"].scale, (8.0, 4.0, 4.0))


def test_field_files_open_with_our_reader_without_a_dialog(field, tmp_path, make_napari_viewer):
    """With fresh settings, a ``.dvcfield`` opens as our 3-D field layers through File ▸ Open and
    ``viewer.open(plugin=None)``, no reader is asked for, and the settings stay as they were;
    other .npz still open with napari's reader when the user names it."""
    from napari.settings import get_settings

    from napari_dvc_correct.io.npz import FIELD_SUFFIX

    assert FIELD_SUFFIX == ".dvcfield"
    path = tmp_path / "run3.dvcfield"
    save_field(field, path)
    other = tmp_path / "plain.npz"
    np.savez(other, volume=np.arange(27.0).reshape(3, 3, 3))
    viewer = make_napari_viewer()
    settings = get_settings()
    assert dict(settings.plugins.extension2reader) == {}  # fresh settings
    before = settings.model_dump_json() if hasattr(settings, "model_dump_json") else settings.json()
    viewer.window._qt_viewer._qt_open([str(path)], stack=False)  # what File > Open does
    assert [layer.name for layer in viewer.layers] == ["|u| (run3)", "displacement (run3)"]
    assert viewer.layers["|u| (run3)"].data.ndim == 3
    viewer.layers.clear()
    viewer.open(str(path), plugin=None)
    assert [layer.name for layer in viewer.layers] == ["|u| (run3)", "displacement (run3)"]
    viewer.open(str(other), plugin="napari")
    assert viewer.layers[-1].data.shape == (3, 3, 3)
    after = settings.model_dump_json() if hasattr(settings, "model_dump_json") else settings.json()
    assert after == before
    assert dict(settings.plugins.extension2reader) == {}


def test_opening_every_panel_leaves_the_reader_preferences_alone(make_napari_viewer, tmp_path):
    """Panels never write the user's persistent reader preferences (``*.tif`` → us would take
    over every unrelated TIFF)."""
    from napari.settings import get_settings

    viewer = make_napari_viewer()
    settings = get_settings()
    settings.plugins.extension2reader = {"*.png": "napari"}  # a choice the user made
    for name in ("Correlate", "View", "Self-correct", "Evaluate", "Export"):
        viewer.window.add_plugin_dock_widget("napari-dvc-correct", name)
    assert dict(settings.plugins.extension2reader) == {"*.png": "napari"}


def test_a_dvcfield_that_is_not_a_field_is_declined(tmp_path):
    path = tmp_path / "broken.dvcfield"
    path.write_bytes(b"PK\x03\x04 not a zip")
    assert napari_get_reader(str(path)) is None


@pytest.mark.parametrize("content", [b"", b"not a tiff at all", "truncated"])
def test_unreadable_tiff_is_not_claimed(tmp_path, content):
    """A .tif that tifffile cannot open is not ours: None, so napari tries other readers."""
    path = tmp_path / "broken.tif"
    if content == "truncated":
        tifffile.imwrite(path, np.zeros((4, 16, 16), np.uint8), photometric="minisblack")
        path.write_bytes(path.read_bytes()[:12])
    else:
        path.write_bytes(content)
    assert napari_get_reader(str(path)) is None


@pytest.mark.parametrize(
    "case", ["empty.mat", "header.tsv", "header.disp", "truncated.tif", "lying.npz", "bomb.npz"]
)
def test_files_the_reader_cannot_read_are_declined(tmp_path, case):
    """Issue 27 item 7: an empty .mat, a header-only table, a TIFF truncated after an intact
    header, a field .npz whose headers promise arrays it does not hold: None, never a raise."""
    import io
    import os
    import zipfile

    path = tmp_path / case
    if case == "empty.mat":
        path.write_bytes(b"")
    elif case == "header.tsv":
        path.write_text("NodeNumber\tZpos\tYpos\tXpos\tZdisp\tYdisp\tXdisp\treturnStatus\n")
    elif case == "header.disp":
        path.write_text("n\tx\ty\tz\tstatus\tobjmin\tu\tv\tw\n")
    elif case == "truncated.tif":
        tifffile.imwrite(path, np.zeros((40, 64, 64), np.uint16), photometric="minisblack")
        os.truncate(path, path.stat().st_size // 2)  # the first page's header is intact
    else:
        save_field(DisplacementField.zeros((4.0,) * 3, (4.0,) * 3, (2, 2, 2)), path)
        with zipfile.ZipFile(path) as archive:
            kept = {n: archive.read(n) for n in archive.namelist() if n != "u.npy"}
        header = io.BytesIO()
        shape = (2, 2, 2, 3) if case == "bomb.npz" else (10**5, 10**5, 10**5, 3)
        np.lib.format.write_array_header_2_0(
            header, {"descr": "<f8", "fortran_order": False, "shape": shape}
        )
        with zipfile.ZipFile(path, "w") as archive:
            for name, data in kept.items():
                archive.writestr(name, data)
            archive.writestr("u.npy", header.getvalue() + (b"" if case == "bomb.npz" else b"0"))
    assert napari_get_reader(str(path)) is None


def test_an_npz_of_several_volumes_opens_as_one_layer_each(tmp_path):
    """The real-rock crops hold reference, deformed and box_zyx: napari's own reader gave one
    layer under the file's name holding the deformed scan (user audit, item 5); ours gives
    each volume, named as the command line names it."""
    path = tmp_path / "rock.npz"
    reference = np.arange(4 * 5 * 6, dtype=np.uint8).reshape(4, 5, 6)
    np.savez(path, reference=reference, deformed=reference + 1, box_zyx=np.arange(6))
    reader = napari_get_reader(str(path))
    layers = reader(str(path))
    assert [(k["name"], t) for _, k, t in layers] == [
        ("rock:reference", "image"),
        ("rock:deformed", "image"),
    ]
    np.testing.assert_array_equal(layers[0][0], reference)
    np.testing.assert_array_equal(layers[1][0], reference + 1)
    # the real file (../shared, absent from a bare clone): the same reader claims it
    shared = (
        Path(__file__).resolve().parents[2] / "shared" / "data" / "real-rock" / "rock_upper.npz"
    )
    if shared.exists():
        assert napari_get_reader(str(shared)) is reader
