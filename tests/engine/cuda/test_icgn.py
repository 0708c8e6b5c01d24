"""The GPU kernels, run in numba's CUDA simulator, against the CPU engine on tiny known cases.

The simulator runs every CUDA thread as a Python thread, so the cases are tiny (24³ volumes,
7³ subvolumes, a few POIs) and all run in one subprocess with ``NUMBA_ENABLE_CUDASIM=1`` (the
variable must be set before numba is imported, and must not leak into the other tests). The CPU
reference results are computed here, in the test process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation import icgn, icgn_reference, shape_function
from napari_dvc_correct.engine.correlation.interpolation import prefilter, sample
from napari_dvc_correct.engine.fields.field import Status

pytestmark = pytest.mark.slow

SHAPE = (24, 24, 24)
CENTER = np.array(SHAPE) / 2
HALF = 3
SCRIPT = Path(__file__).with_name("_simulate.py")
GRADIENT = np.array([[0.02, -0.01, 0.005], [0.01, 0.015, 0.0], [-0.005, 0.01, -0.02]])


def _quadratic(points):
    r = (np.asarray(points, float) - CENTER) / 8.0
    return np.stack(
        [0.5 + 0.3 * r[:, 1] ** 2, -0.4 + 0.2 * r[:, 0] * r[:, 2], 0.3 - 0.25 * r[:, 2] ** 2],
        axis=1,
    )


def _icgn_case(reference, deformed, centers, truth, order, mask=None):
    reference = np.ascontiguousarray(reference, np.float32)
    return {
        "kind": np.array("icgn"),
        "reference": reference,
        "gradient": icgn_reference.gradient_volume(prefilter(reference)),
        "coef_deformed": prefilter(deformed),
        "mask": np.zeros((1, 1, 1), bool) if mask is None else mask,
        "use_mask": np.array(mask is not None),
        "centers": np.asarray(centers, np.int64),
        "half": np.array(HALF),
        "nb": np.array(shape_function.n_monomials(order)),
        "params": shape_function.displacement_to_params(
            np.rint(truth(np.asarray(centers, float))), None, order
        ),
        "max_iterations": np.array(30),
        "tolerance": np.array(1e-3),
        "min_std": np.array(0.05 * float(reference.std())),
        "min_mask_fraction": np.array(0.5),
        "max_update": np.array(4.0),
        "truth": truth(np.asarray(centers, float)),
    }


def _inputs(case):
    return icgn.MatchInputs(
        reference=case["reference"],
        gradient=case["gradient"],
        coef_deformed=case["coef_deformed"],
        mask=case["mask"],
        use_mask=bool(case["use_mask"]),
        half=int(case["half"]),
        nb=int(case["nb"]),
        max_iterations=int(case["max_iterations"]),
        tolerance=float(case["tolerance"]),
        min_std=float(case["min_std"]),
        min_mask_fraction=float(case["min_mask_fraction"]),
        max_update=float(case["max_update"]),
        noise_fraction=float(case["noise_fraction"]) if "noise_fraction" in case else 0.0,
    )


def _cpu(case):
    n = len(case["centers"])
    params = case["params"].copy()
    zncc, status, iterations = np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64)
    icgn.match_many(_inputs(case), case["centers"], params, zncc, status, iterations)
    return {"params": params, "zncc": zncc, "status": status, "iterations": iterations}


def _build_cases():
    texture = synthetic.textured_volume(SHAPE, 1.5, seed=3)
    # 16-bit-like gray values with a large offset: the GPU sums around the mean in float32
    reference = 4000.0 * texture + 20000.0
    reference[1:9, 15:24, 15:24] = 22000.0  # a flat patch: no texture
    affine = synthetic.affine(GRADIENT, CENTER, shift=(-0.6, 0.4, -0.3))
    deformed = synthetic.deform_volume(reference, affine)
    cases = {
        # two ordinary POIs, one whose warped subvolume leaves the volume (z < 0), one flat
        "affine": _icgn_case(
            reference, deformed, [[12, 12, 12], [9, 14, 11], [3, 10, 10], [5, 19, 19]], affine, 1
        ),
        "quadratic": _icgn_case(
            4000.0 * texture,
            synthetic.deform_volume(4000.0 * texture, _quadratic),
            [[11, 13, 12]],
            _quadratic,
            2,
        ),
    }
    # noisy scans: the noise stop ends the iterations (same rule on both devices)
    rng_noise = np.random.default_rng(11)
    noisy_ref = 4000.0 * texture + rng_noise.normal(0.0, 500.0, SHAPE)
    noisy_def = synthetic.deform_volume(4000.0 * texture, affine) + rng_noise.normal(
        0.0, 500.0, SHAPE
    )
    cases["noisy"] = _icgn_case(
        noisy_ref, noisy_def, [[12, 12, 12], [9, 14, 11], [14, 9, 13]], affine, 1
    )
    cases["noisy"]["noise_fraction"] = np.array(0.1)
    # a deformed scan unrelated to the reference: the steps wander without shrinking and the
    # stall rule stops them as DIVERGED (measured on the CPU: after 11, 9 and 9 iterations)
    unrelated = 4000.0 * synthetic.textured_volume(SHAPE, 1.5, seed=11) + 20000.0
    cases["unrelated"] = _icgn_case(
        4000.0 * texture + 20000.0,
        unrelated,
        [[10, 14, 14], [14, 12, 10], [14, 14, 10]],
        synthetic.translation((0.0, 0.0, 0.0)),
        1,
    )
    mask = np.zeros(SHAPE, bool)
    mask[:13] = True  # POI at z = 11 keeps 5 of its 7 planes, the one at z = 17 none
    cases["masked"] = _icgn_case(reference, deformed, [[11, 12, 12], [17, 12, 12]], affine, 1, mask)
    rng = np.random.default_rng(5)
    points = np.concatenate(
        [rng.uniform(-0.5, 23.5, (120, 3)), [[0, 0, 0], [23, 23, 23], [0.0, 11.5, 23.0]]]
    )
    coefficients = prefilter(texture)
    cases["sampling"] = {
        "kind": np.array("sample"),
        "coefficients": coefficients,
        "points": points,
        "expected": sample(coefficients, points),
    }
    shifted = synthetic.deform_volume(texture, synthetic.translation((0.6, -0.4, 1.3)))
    cases["pipeline"] = {
        "kind": np.array("correlate"),
        "reference": texture,
        "deformed": shifted,
        "subvolume": np.array(7),
        "search_radius": np.array(2),
        "origin": np.array([9.0, 9.0, 9.0]),
        "step": np.array([6.0, 6.0, 6.0]),
        "grid_shape": np.array([2, 1, 1]),
    }
    return cases


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cuda_sim")
    cases = _build_cases()
    flat = {
        f"{name}/{key}": value
        for name, case in cases.items()
        for key, value in case.items()
        if key not in ("truth", "expected")
    }
    np.savez(folder / "cases.npz", **flat)
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    completed = subprocess.run(
        [sys.executable, str(SCRIPT), str(folder / "cases.npz"), str(folder / "results.npz")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert completed.returncode == 0, completed.stderr[-4000:]
    gpu = dict(np.load(folder / "results.npz"))
    return cases, gpu


def _gpu(gpu, name):
    return {key.split("/", 1)[1]: value for key, value in gpu.items() if key.startswith(name + "/")}


def _compare(case, gpu_result):
    cpu = _cpu(case)
    nb = int(case["nb"])
    np.testing.assert_array_equal(gpu_result["status"], cpu["status"])
    assert np.all(np.abs(gpu_result["iterations"] - cpu["iterations"]) <= 1)
    matched = np.isin(cpu["status"], [int(Status.CONVERGED), int(Status.MAX_ITERATIONS)])
    u_gpu = gpu_result["params"].reshape(-1, 3, nb)
    u_cpu = cpu["params"].reshape(-1, 3, nb)
    # the criterion: the same answer within 1e-3 voxel
    assert np.max(np.abs(u_gpu[:, :, 0] - u_cpu[:, :, 0])) < 1e-3
    assert np.max(np.abs(u_gpu[:, :, 1:4] - u_cpu[:, :, 1:4])) < 1e-4
    np.testing.assert_allclose(gpu_result["zncc"][matched], cpu["zncc"][matched], atol=1e-5)
    assert np.all(np.isnan(gpu_result["zncc"][~matched]) == np.isnan(cpu["zncc"][~matched]))
    return cpu, matched


def test_first_order_matches_the_cpu_and_the_truth(results):
    cases, gpu = results
    case, result = cases["affine"], _gpu(gpu, "affine")
    cpu, matched = _compare(case, result)
    assert list(cpu["status"][:2]) == [Status.CONVERGED, Status.CONVERGED]
    u = result["params"].reshape(-1, 3, 4)
    assert np.max(np.abs(u[:2, :, 0] - case["truth"][:2])) < 0.01
    assert np.max(np.abs(u[:2, :, 1:4] - GRADIENT)) < 0.01
    assert np.all(result["zncc"][:2] > 0.999)


def test_subvolume_leaving_the_volume_is_matched_on_the_cpu(results):
    cases, gpu = results
    result = _gpu(gpu, "affine")
    from napari_dvc_correct.engine.cuda import FALLBACK

    # the kernel flagged it, and the final answer is exactly the CPU's (same code ran it)
    assert result["raw_status"][2] == FALLBACK
    assert FALLBACK not in result["status"]
    cpu = _cpu(cases["affine"])
    np.testing.assert_array_equal(result["params"][2], cpu["params"][2])
    assert result["status"][2] == cpu["status"][2]


def test_flat_subvolume_is_low_texture(results):
    _, gpu = results
    result = _gpu(gpu, "affine")
    assert result["status"][3] == Status.LOW_TEXTURE
    assert result["iterations"][3] == 0 and np.isnan(result["zncc"][3])


def test_second_order_matches_the_cpu(results):
    cases, gpu = results
    case, result = cases["quadratic"], _gpu(gpu, "quadratic")
    cpu, matched = _compare(case, result)
    assert matched.all()
    u = result["params"].reshape(-1, 3, 10)
    assert np.max(np.abs(u[:, :, 0] - case["truth"])) < 0.02


def test_noise_stop_matches_the_cpu(results):
    cases, gpu = results
    case, result = cases["noisy"], _gpu(gpu, "noisy")
    cpu, matched = _compare(case, result)
    assert matched.all()
    without = dict(case, noise_fraction=np.array(0.0))
    assert cpu["iterations"].sum() < _cpu(without)["iterations"].sum()


def test_stall_rule_matches_the_cpu(results):
    cases, gpu = results
    case, result = cases["unrelated"], _gpu(gpu, "unrelated")
    cpu = _cpu(case)
    assert np.all(cpu["status"] == Status.DIVERGED)
    assert np.all(cpu["iterations"] < int(case["max_iterations"]))
    np.testing.assert_array_equal(result["status"], cpu["status"])
    assert np.all(np.abs(result["iterations"] - cpu["iterations"]) <= 1)


def test_mask_is_honoured(results):
    cases, gpu = results
    case, result = cases["masked"], _gpu(gpu, "masked")
    cpu, matched = _compare(case, result)
    assert result["status"][0] == Status.CONVERGED
    assert result["status"][1] == Status.MASKED
    u = result["params"].reshape(-1, 3, 4)
    assert np.max(np.abs(u[0, :, 0] - case["truth"][0])) < 0.05  # 5 of 7 planes only


def test_sampling_matches_the_cpu(results):
    cases, gpu = results
    expected = cases["sampling"]["expected"]
    values = gpu["sampling/values"]
    assert np.array_equal(np.isnan(values), np.isnan(expected))
    assert np.isnan(expected).any() and np.isfinite(expected).sum() > 50
    np.testing.assert_allclose(
        values[np.isfinite(values)], expected[np.isfinite(expected)], atol=1e-5
    )


def test_device_selection_in_the_simulator(results):
    _, gpu = results
    assert str(gpu["device_cuda"]) == "cuda"
    assert "simulator" in str(gpu["device_cuda_description"]).lower()
    assert str(gpu["device_auto"]) == "cpu"  # auto never picks the simulator


def test_correlate_with_device_cuda_gives_the_cpu_field(results):
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    cases, gpu = results
    case = cases["pipeline"]
    grid = (tuple(case["origin"]), tuple(case["step"]), tuple(case["grid_shape"]))
    params = CorrelationParams(subvolume=7, search_radius=2)
    field = correlate(case["reference"], case["deformed"], params, grid=grid, device="cpu")
    assert "simulator" in str(gpu["pipeline/device"]).lower()
    np.testing.assert_array_equal(gpu["pipeline/status"], field.status)
    assert np.all(field.status == Status.CONVERGED)
    assert np.max(np.abs(gpu["pipeline/u"] - field.u)) < 1e-3
    np.testing.assert_allclose(field.u.reshape(-1, 3), [[0.6, -0.4, 1.3]] * 2, atol=0.05)
