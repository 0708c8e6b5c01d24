"""Device copies kept while the host array lives: one copy per array, dropped with it (the copy
itself is faked here; the kernels' tests copy for real in the CUDA simulator)."""

import gc
from types import SimpleNamespace

import numpy as np

from napari_dvc_correct.engine.cuda import memory


def test_one_device_copy_per_live_host_array(monkeypatch):
    copies = []

    def to_device(host):
        copies.append(host.copy())
        return SimpleNamespace(host=copies[-1])

    monkeypatch.setattr(memory, "cuda", SimpleNamespace(to_device=to_device))
    memory.clear_device_cache()
    volume = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    first = memory.to_device_cached(volume)
    assert memory.to_device_cached(volume) is first and len(copies) == 1  # reused
    flat = memory.to_device_cached(volume, flat=True)
    assert flat is not first and flat.host.shape == (24,)  # a 1-D copy is another entry
    other = memory.to_device_cached(volume.copy())
    assert other is not first and len(copies) == 3
    del volume
    gc.collect()
    assert memory._CACHE == {}  # every host array gone: its copies dropped
    kept = np.ones(3)
    memory.to_device_cached(kept)
    memory.clear_device_cache()
    assert memory._CACHE == {}


def test_threads_per_block_are_fewer_in_the_simulator(monkeypatch):
    monkeypatch.setattr(memory, "simulator_enabled", lambda: False)
    assert memory.default_threads() == 128
    monkeypatch.setattr(memory, "simulator_enabled", lambda: True)
    assert memory.default_threads() == 32
