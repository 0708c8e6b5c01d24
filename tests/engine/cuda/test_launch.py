"""A failing GPU never stops a run: match_many_cuda warns and matches on the CPU."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation import icgn, icgn_reference
from napari_dvc_correct.engine.correlation.interpolation import prefilter
from napari_dvc_correct.engine.cuda import launch as gpu_launch
from napari_dvc_correct.engine.fields.field import Status


def _inputs(nb=4):
    reference = synthetic.textured_volume((24, 24, 24), 1.5, seed=1)
    deformed = synthetic.deform_volume(reference, synthetic.translation((0.4, -0.3, 0.2)))
    inputs = icgn.MatchInputs(
        reference=reference,
        gradient=icgn_reference.gradient_volume(prefilter(reference)),
        coef_deformed=prefilter(deformed),
        mask=np.zeros((1, 1, 1), bool),
        use_mask=False,
        half=4,
        nb=nb,
        max_iterations=30,
        tolerance=1e-3,
        min_std=0.0,
        min_mask_fraction=0.5,
        max_update=4.0,
    )
    return inputs, np.array([[10, 10, 10], [13, 12, 11]], np.int64)


def _outputs(n):
    return np.zeros((n, 12)), np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64)


def test_gpu_failure_falls_back_to_the_cpu_with_a_warning(monkeypatch):
    from numba.cuda.cudadrv.error import CudaSupportError

    def broken(*args, **kwargs):
        args[2][:] = 99.0  # a half-done launch must not leak into the result
        raise CudaSupportError("no driver")

    monkeypatch.setattr(gpu_launch, "_launch", broken)
    inputs = _inputs()
    gpu_out = _outputs(2)
    with pytest.warns(RuntimeWarning, match="GPU failed.*CPU"):
        gpu_launch.match_many_cuda(*inputs, *gpu_out)
    cpu_out = _outputs(2)
    icgn.match_many(*inputs, *cpu_out)
    np.testing.assert_array_equal(gpu_out[0], cpu_out[0])
    assert np.all(gpu_out[2] == Status.CONVERGED)
    np.testing.assert_allclose(gpu_out[0][:, [0, 4, 8]], [[0.4, -0.3, 0.2]] * 2, atol=0.01)


def test_gpu_failure_can_be_raised(monkeypatch):
    from numba.cuda.cudadrv.error import CudaSupportError

    def broken(*args, **kwargs):
        raise CudaSupportError("no driver")

    monkeypatch.setattr(gpu_launch, "_launch", broken)
    with pytest.raises(CudaSupportError):
        gpu_launch.match_many_cuda(*_inputs(), *_outputs(2), cpu_fallback=False)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="nb must be"):
        gpu_launch.match_many_cuda(*_inputs(nb=7), *_outputs(2))
