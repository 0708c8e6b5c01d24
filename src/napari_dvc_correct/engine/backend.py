"""Choosing where the engine runs: the CPU (numba, always there) or a CUDA GPU (numba.cuda).

``select_device("auto")`` uses a GPU when numba sees one that works and says which it chose;
``select_device("cuda")`` insists, but still falls back to the CPU with a warning when there is no
usable GPU (no driver, no GPU, a failing compiler): a missing GPU never stops a run.
"""

from __future__ import annotations

import functools
import os
import warnings
from dataclasses import dataclass

import numba
import numba.core.config

DEVICE_CHOICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class Device:
    """The device a computation runs on.

    Attributes
    ----------
    kind : {"cpu", "cuda"}
        What the engine dispatches on.
    description : str
        One readable line for users and logs, e.g.
        ``"CUDA GPU 0: NVIDIA H100 80GB HBM3 (compute capability 9.0, 132 SMs, 79.1 GiB)"`` or
        ``"CPU (numba, 8 threads); no CUDA GPU: ..."``.
    requested : str
        What was asked for (``"auto"``, ``"cpu"`` or ``"cuda"``).
    fallback_reason : str or None
        Why a GPU was not used when one was asked for or looked for.
    """

    kind: str
    description: str
    requested: str = "auto"
    fallback_reason: str | None = None

    @property
    def is_cuda(self) -> bool:
        return self.kind == "cuda"


def cpu_description() -> str:
    return f"CPU (numba, {numba.get_num_threads()} threads)"


#: Where numba.cuda looks for the driver library, after ``NUMBA_CUDA_DRIVER``.
DRIVER_LIBRARIES = ("libcuda.so.1", "libcuda.so", "nvcuda.dll")


@functools.cache
def _nvidia_driver_present() -> bool:
    """Cheap check for an NVIDIA driver: its device nodes, its /proc entry, or a driver library
    the dynamic loader opens (as numba.cuda will; ``ctypes.util.find_library`` would start
    ``ldconfig`` and a compiler, about 20 ms of every CPU run)."""
    import ctypes

    if os.path.exists("/proc/driver/nvidia") or _device_nodes():
        return True
    for name in (os.environ.get("NUMBA_CUDA_DRIVER"), *DRIVER_LIBRARIES):
        if not name:
            continue
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


def _device_nodes() -> list[str]:
    """``/dev/nvidia0``, ``/dev/nvidia1``, ... (none where there is no ``/dev``)."""
    try:
        names = os.listdir("/dev")
    except OSError:
        return []
    return [name for name in names if name.startswith("nvidia") and name[6:].isdigit()]


def probe_cuda() -> tuple[bool, str]:
    """Whether a CUDA GPU can run our kernels: ``(True, description)`` or ``(False, reason)``.

    Imports numba.cuda, checks for a driver and a device, then compiles and runs a tiny kernel
    (this catches a missing CUDA compiler, NVVM). Cached for the process.
    """
    if not numba.core.config.ENABLE_CUDASIM and not _nvidia_driver_present():
        # importing numba.cuda costs most of a second: skip it where no driver can exist
        return False, "no CUDA GPU found (no NVIDIA driver on this machine)"
    try:
        from .cuda import cuda, simulator_enabled
    except Exception as error:  # noqa: BLE001 - any import failure means "no GPU backend"
        return False, f"numba.cuda could not be imported ({type(error).__name__}: {error})"
    if simulator_enabled():
        return True, (
            "CUDA simulator (NUMBA_ENABLE_CUDASIM=1): kernels run in Python, for tests only"
        )
    try:
        if not cuda.is_available():
            return False, "no CUDA GPU found (no NVIDIA driver or no device visible to numba)"
        device = cuda.get_current_device()
        name = device.name.decode() if isinstance(device.name, bytes) else str(device.name)
        major, minor = device.compute_capability
        sms = getattr(device, "MULTIPROCESSOR_COUNT", None)
        free, total = cuda.current_context().get_memory_info()
        _smoke_test(cuda)
    except Exception as error:  # noqa: BLE001 - a failing GPU falls back, never crashes
        return False, f"the CUDA GPU failed a test ({type(error).__name__}: {error})"
    parts = [f"compute capability {major}.{minor}"]
    if sms:
        parts.append(f"{sms} SMs")
    parts.append(f"{total / 2**30:.1f} GiB, {free / 2**30:.1f} GiB free")
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    index = f"GPU {device.id}" + (f" (CUDA_VISIBLE_DEVICES={visible})" if visible else "")
    return True, f"CUDA {index}: {name} ({', '.join(parts)})"


def _smoke_test(cuda) -> None:
    import numpy as np

    @cuda.jit
    def add_one(values):
        i = cuda.grid(1)
        if i < values.size:
            values[i] += 1.0

    values = cuda.to_device(np.zeros(32, np.float32))
    add_one[1, 32](values)
    if not np.all(values.copy_to_host() == 1.0):
        raise RuntimeError("a test kernel returned wrong values")


def select_device(requested: str | Device = "auto", *, warn: bool = True) -> Device:
    """Pick the device for a run.

    Parameters
    ----------
    requested : {"auto", "cpu", "cuda"} or Device
        ``"auto"`` uses a working CUDA GPU when there is one (never the CUDA simulator), else the
        CPU. ``"cuda"`` uses the GPU (or the simulator when ``NUMBA_ENABLE_CUDASIM=1``) and falls
        back to the CPU, with a warning, when there is none. A ``Device`` is returned unchanged.
    warn : bool
        Emit a ``RuntimeWarning`` when ``"cuda"`` was requested but the CPU is used.

    Returns
    -------
    Device
        ``description`` says which device was chosen, and why not the GPU when it was not.

    Raises
    ------
    ValueError
        For a name other than auto, cpu or cuda.
    """
    if isinstance(requested, Device):
        return requested
    choice = str(requested).strip().lower()
    if choice not in DEVICE_CHOICES:
        raise ValueError(f"device must be one of {', '.join(DEVICE_CHOICES)}, got {requested!r}")
    if choice == "cpu":
        return Device("cpu", cpu_description(), requested=choice)
    usable, text = probe_cuda()
    if usable and choice == "auto" and numba.core.config.ENABLE_CUDASIM:
        usable, text = False, "the CUDA simulator is enabled, and auto never picks it"
    if usable:
        return Device("cuda", text, requested=choice)
    if choice == "cuda" and warn:
        warnings.warn(
            f"CUDA was requested but cannot be used: {text}. Running on the CPU instead.",
            RuntimeWarning,
            stacklevel=2,
        )
    return Device(
        "cpu", f"{cpu_description()}; not the GPU: {text}", requested=choice, fallback_reason=text
    )
