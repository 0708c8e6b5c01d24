"""Device selection: auto, cpu, cuda, and a clear fallback to the CPU when there is no GPU."""

import warnings

import pytest

from napari_dvc_correct.engine import backend
from napari_dvc_correct.io.npz import load_field


def test_cpu_is_always_available():
    device = backend.select_device("cpu")
    assert device.kind == "cpu" and not device.is_cuda
    assert "CPU" in device.description and device.fallback_reason is None


def test_auto_uses_a_gpu_only_when_one_works():
    usable, text = backend.probe_cuda()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # auto never warns
        device = backend.select_device("auto")
    if usable:
        assert device.kind == "cuda" and device.description == text
    else:
        assert device.kind == "cpu"
        assert text in device.description and device.fallback_reason == text


def test_cuda_without_a_gpu_warns_and_falls_back(monkeypatch):
    monkeypatch.setattr(backend, "probe_cuda", lambda: (False, "no CUDA GPU found (test)"))
    with pytest.warns(RuntimeWarning, match="Running on the CPU"):
        device = backend.select_device("cuda")
    assert device.kind == "cpu" and device.requested == "cuda"
    assert "no CUDA GPU found (test)" in device.description


def test_cuda_with_a_gpu_is_used(monkeypatch):
    monkeypatch.setattr(backend, "probe_cuda", lambda: (True, "CUDA GPU 0: Test GPU"))
    device = backend.select_device("CUDA")
    assert device.is_cuda and device.description == "CUDA GPU 0: Test GPU"
    assert backend.select_device(device) is device


def test_unknown_device_is_refused():
    with pytest.raises(ValueError, match="auto, cpu, cuda"):
        backend.select_device("tpu")


def test_command_line_prints_the_device(tmp_path, capsys, monkeypatch):
    import numpy as np

    from napari_dvc_correct import cli
    from napari_dvc_correct.engine import synthetic

    monkeypatch.setattr(backend, "probe_cuda", lambda: (False, "no CUDA GPU found (test)"))
    reference = synthetic.textured_volume((32, 32, 32), 1.5, seed=4)
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.3, -0.5, 0.2)))
    np.save(tmp_path / "ref.npy", reference)
    np.save(tmp_path / "def.npy", deformed)
    out = tmp_path / "field.npz"
    arguments = [str(tmp_path / "ref.npy"), str(tmp_path / "def.npy"), "--out", str(out)]
    arguments += ["--subvolume", "11", "--step", "8", "--quiet", "--device", "cuda"]
    with pytest.warns(RuntimeWarning, match="CUDA was requested"):
        assert cli.main(["correlate", *arguments]) == 0
    printed = capsys.readouterr().out
    assert "device: CPU" in printed and "no CUDA GPU found (test)" in printed
    field = load_field(out)
    assert field.metadata["device"].startswith("CPU")
    assert np.allclose(field.u[field.valid], [0.3, -0.5, 0.2], atol=0.02)


def _no_driver_files(monkeypatch):
    real_exists = backend.os.path.exists
    monkeypatch.setattr(
        backend.os.path, "exists", lambda p: False if p == "/proc/driver/nvidia" else real_exists(p)
    )
    monkeypatch.setattr(backend, "_device_nodes", lambda: [])
    monkeypatch.delenv("NUMBA_CUDA_DRIVER", raising=False)
    backend._nvidia_driver_present.cache_clear()


def test_driver_check_opens_the_library_numba_would_and_starts_no_process(monkeypatch):
    import ctypes
    import subprocess

    _no_driver_files(monkeypatch)
    opened = []

    def fake_cdll(name):
        opened.append(name)
        if name != "libcuda.so":
            raise OSError(f"{name}: cannot open shared object file")
        return object()

    def no_process(*args, **kwargs):
        raise AssertionError("the driver check started a process")

    monkeypatch.setattr(ctypes, "CDLL", fake_cdll)
    monkeypatch.setattr(subprocess, "Popen", no_process)
    try:
        assert backend._nvidia_driver_present()
        assert opened == ["libcuda.so.1", "libcuda.so"]
        backend._nvidia_driver_present.cache_clear()
        opened.clear()
        monkeypatch.setattr(ctypes, "CDLL", lambda name: fake_cdll("absent " + name))
        assert not backend._nvidia_driver_present()
        opened[:] = [name.removeprefix("absent ") for name in opened]
        assert opened == list(backend.DRIVER_LIBRARIES)
        backend._nvidia_driver_present.cache_clear()
        monkeypatch.setenv("NUMBA_CUDA_DRIVER", "/opt/driver/libcuda.so")
        monkeypatch.setattr(ctypes, "CDLL", lambda name: name == "/opt/driver/libcuda.so" or 1 / 0)
        assert backend._nvidia_driver_present()
    finally:
        backend._nvidia_driver_present.cache_clear()


def test_device_nodes_are_numbered_nvidia_files(monkeypatch):
    names = ["nvidia0", "nvidia12", "nvidiactl", "nvidia-uvm", "nvidia", "null"]
    monkeypatch.setattr(backend.os, "listdir", lambda path: names)
    assert backend._device_nodes() == ["nvidia0", "nvidia12"]

    def missing(path):
        raise FileNotFoundError(path)

    monkeypatch.setattr(backend.os, "listdir", missing)
    assert backend._device_nodes() == []
