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
