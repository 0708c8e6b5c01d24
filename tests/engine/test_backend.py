"""Device selection: auto, cpu, cuda, and a clear fallback to the CPU when there is no GPU."""

import warnings

import pytest

from napari_dvc_correct.engine import backend


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
