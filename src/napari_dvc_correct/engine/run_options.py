"""How a run is carried out (not what it computes): in memory or out of core, where, how wide.

Plain Python, so that the command line can build its parsers and print its defaults without
loading numba, scipy or dask. The command line and the panels build one :class:`RunOptions`;
the tiled functions take its :meth:`RunOptions.tiled_keywords`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass

#: Where IC-GN runs (:func:`.backend.select_device`).
DEVICES = ("auto", "cpu", "cuda")

#: The largest memory size accepted (bytes): larger ones are typing mistakes (``1e400GB``).
MAX_MEMORY_BYTES = 2**62


def _shape(value, name: str) -> tuple[int, int, int] | None:
    if value is None:
        return None
    try:
        values = tuple(int(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 whole numbers (z, y, x), got {value!r}") from None
    if len(values) != 3 or min(values) < 1:
        raise ValueError(f"{name} must be 3 whole numbers >= 1 (z, y, x), got {value!r}")
    return values


@dataclass(frozen=True)
class RunOptions:
    """How and where a run is carried out; every default and every check of these lives here.

    Attributes
    ----------
    tiled : bool
        Work out of core: volumes read lazily, region by region, on Dask. Any of
        ``max_memory``, ``workers``, ``scheduler``, ``batch_shape``, ``block_shape`` or
        ``temp_dir`` also asks for it (:attr:`out_of_core`).
    device : {"auto", "cpu", "cuda"}
        Where IC-GN runs: ``"auto"`` takes a CUDA GPU numba sees working, else the CPU.
    max_memory : int, optional
        Peak memory (bytes) an out-of-core run may use; picks the batch size. None: what the
        machine (or each cluster worker) has.
    workers : int, optional
        Batches or blocks worked on at once on this machine (>= 1). None: up to 4.
    scheduler : str, optional
        Address of a ``dask.distributed`` scheduler (e.g. ``tcp://10.0.0.5:8786``). None: Dask's
        local threads.
    batch_shape : (int, int, int), optional
        POIs per batch of a tiled correlation. None: the largest that fits ``max_memory``.
    block_shape : (int, int, int), optional
        Voxels per block of a tiled evaluation. None: the largest cube up to 128 that fits.
    temp_dir : str, optional
        Existing folder for the temporary warped volumes of an out-of-core correction or
        series. None: the system's temporary folder.
    """

    tiled: bool = False
    device: str = "auto"
    max_memory: int | None = None
    workers: int | None = None
    scheduler: str | None = None
    batch_shape: tuple[int, int, int] | None = None
    block_shape: tuple[int, int, int] | None = None
    temp_dir: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.tiled, bool):
            raise ValueError(f"tiled must be True or False, got {self.tiled!r}")
        if self.device not in DEVICES:
            raise ValueError(f"device must be one of {DEVICES}, got {self.device!r}")
        if self.max_memory is not None:
            try:
                size = float(self.max_memory)
            except (TypeError, ValueError):
                size = math.nan
            if not 0 < size < MAX_MEMORY_BYTES:
                raise ValueError(
                    "max_memory must be > 0 bytes and a size a machine can have, got "
                    f"{self.max_memory!r}"
                )
            object.__setattr__(self, "max_memory", int(size))
        if self.workers is not None and (
            isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1
        ):
            raise ValueError(f"workers must be a whole number >= 1, got {self.workers!r}")
        object.__setattr__(self, "batch_shape", _shape(self.batch_shape, "batch_shape"))
        object.__setattr__(self, "block_shape", _shape(self.block_shape, "block_shape"))
        if self.scheduler is not None and not str(self.scheduler).strip():
            object.__setattr__(self, "scheduler", None)
        if self.temp_dir is not None and not os.path.isdir(self.temp_dir):
            raise ValueError(
                f"temp_dir {str(self.temp_dir)!r} is not an existing folder: create it first "
                "(nothing is made for you)"
            )

    @property
    def out_of_core(self) -> bool:
        """True when the run goes out of core: ``tiled``, or any option that only it uses."""
        return bool(
            self.tiled
            or self.scheduler
            or self.max_memory
            or self.workers
            or self.batch_shape
            or self.block_shape
            or self.temp_dir
        )

    def tiled_keywords(self) -> dict:
        """The keywords every tiled correlation, correction and series takes from this run."""
        return dict(
            batch_shape=self.batch_shape,
            max_memory=self.max_memory,
            workers=self.workers,
            scheduler=self.scheduler,
            device=self.device,  # chosen by each batch's worker ("auto": its GPU)
        )

    def replace(self, **changes) -> RunOptions:
        """A copy with ``changes`` (checked like a new one)."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """Plain JSON-ready values (sessions, provenance)."""
        values = dataclasses.asdict(self)
        for key in ("batch_shape", "block_shape"):
            if values[key] is not None:
                values[key] = list(values[key])
        return values

    @classmethod
    def from_dict(cls, values: dict) -> RunOptions:
        """The record of :meth:`as_dict` (unknown keys ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})
