"""Shared fixtures of the widget tests: a small soil-like pair and helpers to run a panel."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from napari_dvc_correct._sample_data import soil_pair

#: Small enough for CI (2 cores): 48³ voxels, subvolume 15, step 8 -> 125 POIs. A physical voxel
#: size and an offset, so the tests see that both are respected.
SMALL = SimpleNamespace(
    shape=(48, 48, 48),
    subvolume=15,
    step=8,
    voxel_size=(2.0, 1.5, 1.5),
    offset=(10.0, -4.0, 0.0),
)


@pytest.fixture
def small():
    return SMALL


@pytest.fixture(scope="session")
def pair48():
    """Reference, deformed and the known shear band (keyword arguments of ``shear_band``)."""
    return soil_pair(SMALL.shape, slip=3.0, compression=0.01)


@pytest.fixture
def viewer_pair(make_napari_viewer, pair48):
    """A viewer holding the pair as "reference" and "deformed", placed with a voxel size."""
    reference, deformed, _ = pair48
    viewer = make_napari_viewer()
    for name, data in (("reference", reference), ("deformed", deformed)):
        viewer.add_image(data, name=name, scale=SMALL.voxel_size, translate=SMALL.offset)
    return viewer


@pytest.fixture
def lazy_viewer(make_napari_viewer, pair48):
    """A viewer holding the pair as Dask arrays ("reference", "deformed"): lazily backed scans."""
    import dask.array as da

    reference, deformed, _ = pair48
    viewer = make_napari_viewer()
    for name, data in (("reference", reference), ("deformed", deformed)):
        viewer.add_image(da.from_array(data, chunks=24), name=name)
    return viewer


@pytest.fixture
def lazy_panel(lazy_viewer):
    """A docked Correlate panel over :func:`lazy_viewer`'s scans, with the small subvolume/step."""
    from napari_dvc_correct.widgets import CorrelateWidget

    widget = CorrelateWidget(lazy_viewer)
    lazy_viewer.window.add_dock_widget(widget)
    widget.subvolume.setValue(SMALL.subvolume)
    widget.step.setValue(SMALL.step)
    return widget


@pytest.fixture
def run_panel(qtbot):
    """``run_panel(widget)``: run a panel and wait for its worker and for its result on view
    (the layers are added one per turn of the event loop after the worker ends; no sleeping);
    the worker."""

    def run(widget, timeout: int = 300_000):
        worker = widget.run(start=False)
        assert worker is not None, widget.message.text()
        with qtbot.waitSignal(worker.finished, timeout=timeout):
            worker.start()
        qtbot.waitUntil(lambda: not widget.running, timeout=30_000)
        return worker

    return run


@pytest.fixture
def correlated(viewer_pair, run_panel):
    """A docked Correlate panel that has run on the small pair (first-order, 125 POIs)."""
    from napari_dvc_correct.widgets import CorrelateWidget

    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(SMALL.subvolume)
    widget.step.setValue(SMALL.step)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    return widget


@pytest.fixture
def point_voxels():
    """Points of interest in voxels (z, y, x) of the small pair, fractional ones included."""
    return np.array(
        [[12.0, 14.0, 20.0], [24.0, 24.0, 24.0], [30.4, 20.0, 33.6], [20.0, 33.0, 14.0]]
    )


@pytest.fixture
def points_panel(viewer_pair, point_voxels):
    """A docked Correlate panel set to correlate at the points of the Points layer "my points"
    (added in world coordinates over the small pair)."""
    from napari_dvc_correct.widgets import CorrelateWidget

    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(SMALL.subvolume)
    widget.step.setValue(SMALL.step)
    world = point_voxels * np.asarray(SMALL.voxel_size) + np.asarray(SMALL.offset)
    viewer_pair.add_points(world, name="my points")
    widget.placement.setCurrentIndex(widget.placement.findData("points"))
    return widget


@pytest.fixture
def strain_calls(monkeypatch):
    """A list that gets, for each strain tensor computed (``quantities.physical_strain``), True
    when it was computed on the main thread."""
    import threading

    from napari_dvc_correct import quantities

    calls = []
    original = quantities.physical_strain

    def recording(field):
        calls.append(threading.current_thread() is threading.main_thread())
        return original(field)

    monkeypatch.setattr(quantities, "physical_strain", recording)
    return calls


def expected_placement(field):
    """``(scale, translate)`` a grid layer of ``field`` must have over the small pair."""
    vs, off = np.asarray(SMALL.voxel_size), np.asarray(SMALL.offset)
    return np.asarray(field.step) * vs, off + np.asarray(field.origin) * vs


@pytest.fixture
def placement():
    return expected_placement
