"""GPU vs CPU IC-GN throughput in voxel-iterations per second (issue 7), ready to run on a GPU.

For each workload (a textured float32 pair with a known homogeneous strain, POIs on a regular
grid, integer initial guesses as the FFT search would give them) the script

1. matches every POI on the GPU (``engine.cuda.match_many_cuda``), for each block size /
   register cap asked for, after a warm-up that compiles the kernel and copies the volumes;
2. matches a subset of the same POIs on the CPU (``engine.correlation.icgn.match_many``, all cores);
3. prints the GPU's name, voxel-iterations per second on both (Σ iterations × subvolume³ / wall
   time of the call, as ``correlate`` counts them), the speed-up, the largest |u_GPU − u_CPU| on
   the common POIs, and the achieved fraction of the GPU's FP32 peak and memory bandwidth from the
   kernel's *modelled* work per voxel-iteration (FLOP_MODEL, BYTE_MODEL below: an arithmetic
   count of the source, not a hardware counter; use Nsight Compute for measured DRAM bytes:
   ``ncu --metrics dram__bytes_read.sum,sm__inst_executed.sum python benchmarks/bench_gpu.py
   --quick``);
4. extrapolates the paper's workload (2000×2000×3000 voxels, 141³ subvolumes, step 10).

It needs only numpy, scipy and numba(-cuda) (not napari): on a machine where the package is not
installed run ``PYTHONPATH=src python benchmarks/bench_gpu.py``. ``--quick`` runs a small case in a
minute; the default runs the "typical" (31³, step 8) and "paper" (141³ subvolumes) workloads for
first-order and the typical one for second-order IC-GN, in a few minutes on an H100.
``--json PATH`` writes every figure for docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

# The engine asks numba for a thread-safe CPU threading layer (TBB or OpenMP) unless told otherwise;
# a GPU machine may have neither, and this script calls the CPU kernels from one thread only.
os.environ.setdefault("NUMBA_THREADING_LAYER", "default")

# Work per voxel-iteration of the hot loop (interior voxels), counted from the kernel source:
# B-spline weights 3 × 14 FLOP, 64 taps as 16 rows of 4 + 4 planes + 1 sum (147 FLOP), warp
# position 3·nb FMA + floor/fraction, per-voxel sums (ΣJ(f−s): 3·nb FMA, Σf, Σf², Σgf, centring).
FLOP_MODEL = {1: 42 + 147 + 24 + 6 + 34, 2: 42 + 147 + 60 + 12 + 6 + 70}
# Compulsory memory traffic per voxel-iteration: G (4 B) and ∇G (12 B) read at every iteration,
# and about one new float32 coefficient of F per voxel (4 B; the other 63 taps hit L1/L2).
BYTE_MODEL = 20
# SASS instructions and loads per interior voxel-iteration (nb = 4), read off ptxas output for
# sm_90 (see docs/performance.md): used for the load-issue ceiling printed below.
LOADS_PER_VOXEL = 68

PAPER_VOXEL_ITERATIONS = 1.7e14

KNOWN_PEAKS = {  # name fragment: (FP32 TFLOP/s, memory TB/s), vendor figures
    "H100 80GB HBM3": (66.9, 3.35),
    "H100 SXM": (66.9, 3.35),
    "H100 NVL": (60.0, 3.9),
    "H100 PCIe": (51.2, 2.0),
    "H200": (66.9, 4.8),
    "A100-SXM4-80GB": (19.5, 2.04),
    "A100-SXM4-40GB": (19.5, 1.56),
    "A100-PCIE-40GB": (19.5, 1.56),
    "RTX 4090": (82.6, 1.01),
    "RTX 5090": (104.8, 1.79),
}


def gpu_info(cuda) -> dict:
    device = cuda.get_current_device()
    name = device.name.decode() if isinstance(device.name, bytes) else str(device.name)
    cc = device.compute_capability
    sms = int(device.MULTIPROCESSOR_COUNT)
    clock_ghz = device.CLOCK_RATE / 1e6
    lanes = 64 if cc in ((6, 0), (7, 0), (7, 5), (8, 0)) else 128
    fp32 = sms * lanes * 2 * clock_ghz / 1e3  # TFLOP/s
    try:
        memory = 2 * device.MEMORY_CLOCK_RATE * 1e3 * device.GLOBAL_MEMORY_BUS_WIDTH / 8 / 1e12
    except Exception:  # noqa: BLE001 - attribute missing in some numba versions
        memory = float("nan")
    source = "from SM count × FP32 lanes × 2 × boost clock and memory clock × bus width"
    for fragment, (known_fp32, known_memory) in KNOWN_PEAKS.items():
        if fragment in name:
            fp32, memory, source = known_fp32, known_memory, f"vendor figures for {fragment}"
    return {
        "name": name,
        "compute_capability": f"{cc[0]}.{cc[1]}",
        "sms": sms,
        "clock_ghz": clock_ghz,
        "fp32_tflops": fp32,
        "memory_tbs": memory,
        "peak_source": source,
        "load_ceiling": sms * 32 * clock_ghz * 1e9 / LOADS_PER_VOXEL,
    }


def make_pair(size: int, seed: int = 0):
    """Textured reference and its image under a homogeneous strain (scipy, fast)."""
    from scipy import ndimage

    from napari_dvc_correct.engine import synthetic

    reference = synthetic.textured_volume((size,) * 3, 2.0, seed=seed) * 1000.0 + 100.0
    gradient = np.array([[0.01, 0.002, -0.003], [0.0, -0.005, 0.004], [0.002, 0.0, 0.008]])
    shift = np.array([0.4, -1.3, 2.2])
    center = np.full(3, size / 2)
    # F(x) = G(X) with x = X + A (X - c) + s  =>  X = (I + A)^-1 (x + A c - s)
    inverse = np.linalg.inv(np.eye(3) + gradient)
    offset = inverse @ (gradient @ center - shift)
    deformed = ndimage.affine_transform(
        reference.astype(np.float64), inverse, offset, order=3, mode="mirror"
    ).astype(np.float32)

    def truth(points):
        return shift + (np.asarray(points, float) - center) @ gradient.T

    return reference.astype(np.float32), deformed, truth


def poi_grid(size: int, subvolume: int, step: int, margin: int = 6) -> np.ndarray:
    half = subvolume // 2
    axis = np.arange(half + margin, size - half - margin, step)
    zz, yy, xx = np.meshgrid(axis, axis, axis, indexing="ij")
    return np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1).astype(np.int64)


def run_matcher(kernel, level, centers, guesses, nb, **options):
    from napari_dvc_correct.engine.correlation import icgn

    n = len(centers)
    params = guesses.copy()
    zncc, status, its = np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64)
    start = time.perf_counter()
    inputs = icgn.MatchInputs(
        reference=level["reference"],
        gradient=level["gradient"],
        coef_deformed=level["coef"],
        mask=np.zeros((1, 1, 1), bool),
        use_mask=False,
        half=level["half"],
        nb=nb,
        max_iterations=50,
        tolerance=1e-3,
        min_std=0.0,
        min_mask_fraction=0.5,
        max_update=float(max(level["half"], 4)),
    )
    kernel(inputs, centers, params, zncc, status, its, **options)
    seconds = time.perf_counter() - start
    return params, status, its, seconds


def workload(args, gpu, name, size, subvolume, step, order, cpu_pois, max_pois):
    from napari_dvc_correct.engine.correlation import icgn, icgn_reference, shape_function
    from napari_dvc_correct.engine.correlation.interpolation import prefilter
    from napari_dvc_correct.engine.cuda import match_many_cuda

    t0 = time.perf_counter()
    reference, deformed, truth = make_pair(size)
    level = {
        "reference": reference,
        "gradient": icgn_reference.gradient_volume(prefilter(reference)),
        "coef": prefilter(deformed),
        "half": subvolume // 2,
    }
    setup = time.perf_counter() - t0
    centers = poi_grid(size, subvolume, step)
    if len(centers) > max_pois:  # a centred block of the grid
        middle = len(centers) // 2 - max_pois // 2
        centers = centers[middle : middle + max_pois]
    nb = shape_function.n_monomials(order)
    guesses = shape_function.displacement_to_params(np.rint(truth(centers)), None, order)
    voxels = subvolume**3
    print(
        f"\n== {name}: {size}³ volume, subvolume {subvolume}³, step {step}, order {order}, "
        f"{len(centers)} POIs (setup {setup:.1f} s)",
        flush=True,
    )
    results = {"workload": name, "size": size, "subvolume": subvolume, "step": step}
    results.update({"order": order, "pois": len(centers), "gpu_runs": []})

    best = None
    for threads in args.threads:
        if order == 2 and threads > 128:
            continue  # shared memory of the order-2 kernel grows with the block size
        for max_registers in args.max_registers:
            options = {"threads_per_block": threads, "max_registers": max_registers or None}
            warm = min(len(centers), 64 if not args.simulator_smoke else 1)
            t0 = time.perf_counter()
            run_matcher(match_many_cuda, level, centers[:warm], guesses[:warm], nb, **options)
            compile_s = time.perf_counter() - t0
            timings = []
            for _ in range(args.repeat):
                params, status, its, seconds = run_matcher(
                    match_many_cuda, level, centers, guesses, nb, **options
                )
                timings.append(seconds)
            seconds = min(timings)
            rate = its.sum() * voxels / seconds
            run = {
                "threads": threads,
                "max_registers": max_registers or None,
                "seconds": seconds,
                "voxel_iterations": int(its.sum() * voxels),
                "rate": rate,
                "mean_iterations": float(its.mean()),
                "converged": float(np.mean(status == 0)),
                "fp32_fraction": rate * FLOP_MODEL[order] / (gpu["fp32_tflops"] * 1e12),
                "memory_fraction": rate * BYTE_MODEL / (gpu["memory_tbs"] * 1e12),
                "warmup_and_compile_s": compile_s,
            }
            run.update(kernel_resources(nb, threads, max_registers or None))
            results["gpu_runs"].append(run)
            print(
                f"GPU  threads {threads:4d} regs cap {str(max_registers or '-'):>4}: "
                f"{rate:.3e} voxel-it/s ({seconds:.3f} s, {its.mean():.1f} it/POI, "
                f"converged {run['converged']:.3f}); FP32 {100 * run['fp32_fraction']:.1f} % "
                f"of peak, memory {100 * run['memory_fraction']:.1f} % of bandwidth (model); "
                f"{run.get('registers', '?')} regs, {run.get('blocks_per_sm', '?')} blocks/SM",
                flush=True,
            )
            if best is None or rate > best[0]["rate"]:
                best = (run, params, its)
    results["best_gpu"] = best[0]

    n_cpu = min(cpu_pois, len(centers))
    pick = np.linspace(0, len(centers) - 1, n_cpu).astype(np.int64)
    try:
        run_matcher(icgn.match_many, level, centers[:2], guesses[:2], nb)  # compile / load cache
        cpu_params, cpu_status, cpu_its, cpu_seconds = run_matcher(
            icgn.match_many, level, centers[pick], guesses[pick], nb
        )
    except Exception as error:  # noqa: BLE001 - keep the GPU figures if the CPU path fails here
        print(f"CPU run failed ({type(error).__name__}: {error}); GPU figures only", flush=True)
        results["cpu_error"] = str(error)
        return results
    cpu_rate = cpu_its.sum() * voxels / cpu_seconds
    gpu_params = best[1][pick].reshape(-1, 3, nb)
    difference = float(np.max(np.abs(gpu_params[:, :, 0] - cpu_params.reshape(-1, 3, nb)[:, :, 0])))
    error = float(np.max(np.abs(best[1].reshape(-1, 3, nb)[:, :, 0] - truth(centers))))
    results.update(
        {
            "cpu_pois": n_cpu,
            "cpu_threads": _cpu_threads(),
            "cpu_rate": cpu_rate,
            "speedup": best[0]["rate"] / cpu_rate,
            "max_gpu_cpu_difference_voxel": difference,
            "max_error_vs_truth_voxel": error,
            "paper_hours_at_best_rate": PAPER_VOXEL_ITERATIONS / best[0]["rate"] / 3600,
        }
    )
    print(
        f"CPU  ({results['cpu_threads']} threads, {n_cpu} of the POIs): {cpu_rate:.3e} "
        f"voxel-it/s; GPU/CPU {results['speedup']:.1f}×; max |u_GPU − u_CPU| {difference:.2e} "
        f"voxel; max |u_GPU − truth| {error:.3f} voxel",
        flush=True,
    )
    print(
        f"paper workload (1.7e14 voxel-iterations) at the best GPU rate: "
        f"{results['paper_hours_at_best_rate']:.2f} h of IC-GN",
        flush=True,
    )
    return results


def kernel_resources(nb, threads, max_registers) -> dict:
    """Registers / local / shared memory of the compiled kernel, when numba exposes them."""
    from napari_dvc_correct.engine.cuda.icgn import build_kernel

    kernel = build_kernel(nb, threads, max_registers)
    out = {}
    for key, getter in (
        ("registers", "get_regs_per_thread"),
        ("local_bytes", "get_local_mem_per_thread"),
        ("shared_bytes", "get_shared_mem_per_block"),
    ):
        try:
            value = getattr(kernel, getter)()
            out[key] = int(next(iter(value.values())) if isinstance(value, dict) else value)
        except Exception:  # noqa: BLE001 - best effort, differs between numba versions
            pass
    if "registers" in out:
        per_block = max(out["registers"], 1) * threads
        by_registers = 65536 // (((per_block + 255) // 256) * 256)
        by_shared = 228 * 1024 // max(out.get("shared_bytes", 1) + 1024, 1)
        out["blocks_per_sm"] = int(min(by_registers, by_shared, 32, 2048 // threads))
    return out


def _cpu_threads() -> int:
    import numba

    return numba.get_num_threads()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one small case (about a minute)")
    parser.add_argument("--threads", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--max-registers", type=int, nargs="+", default=[0, 128])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", help="write the figures to this JSON file")
    parser.add_argument(
        "--simulator-smoke",
        action="store_true",
        help="run a tiny case in numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1) to test this "
        "script without a GPU; its figures mean nothing",
    )
    args = parser.parse_args(argv)

    from napari_dvc_correct.engine.cuda import cuda, simulator_enabled

    if simulator_enabled() and args.simulator_smoke:
        gpu = {"name": "CUDA simulator", "compute_capability": "-", "sms": 1, "clock_ghz": 1.0}
        gpu.update({"fp32_tflops": 1.0, "memory_tbs": 1.0, "peak_source": "made up"})
        gpu["load_ceiling"] = 1.0
    elif simulator_enabled() or not cuda.is_available():
        print("no CUDA GPU visible to numba: nothing to benchmark (see docs/performance.md)")
        return 1
    else:
        gpu = gpu_info(cuda)
    print(
        f"GPU: {gpu['name']} (compute capability {gpu['compute_capability']}, {gpu['sms']} SMs, "
        f"{gpu['clock_ghz']:.2f} GHz); peaks used: FP32 {gpu['fp32_tflops']:.1f} TFLOP/s, "
        f"memory {gpu['memory_tbs']:.2f} TB/s ({gpu['peak_source']}); load-issue ceiling "
        f"~{gpu['load_ceiling']:.2e} voxel-it/s at {LOADS_PER_VOXEL} loads per voxel"
    )
    print(f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    print(f"model: {FLOP_MODEL} FLOP and {BYTE_MODEL} B per voxel-iteration (order: FLOP)")
    # (name, volume edge, subvolume, step, order, POIs matched on the CPU, POI cap)
    if args.simulator_smoke:
        plan = [("smoke", 24, 7, 6, 1, 2, 2)]
        args.threads, args.max_registers, args.repeat = [16], [0], 1
    elif args.quick:
        plan = [("quick", 96, 21, 8, 1, 64, 10**6)]
        args.threads, args.max_registers, args.repeat = [128], [0], 2
    else:
        plan = [
            ("typical", 256, 31, 8, 1, 512, 10**6),
            ("paper", 320, 141, 10, 1, 8, 1056),
            ("typical", 256, 31, 8, 2, 256, 10**6),
        ]
    report = {"gpu": gpu, "cpu_cores": os.cpu_count(), "workloads": []}
    for name, size, subvolume, step, order, cpu_pois, max_pois in plan:
        report["workloads"].append(
            workload(args, gpu, name, size, subvolume, step, order, cpu_pois, max_pois)
        )
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(report, stream, indent=2, default=float)
        print(f"figures written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
