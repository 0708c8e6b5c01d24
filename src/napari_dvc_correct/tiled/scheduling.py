"""Running lists of ``dask.delayed`` tasks locally or on a ``dask.distributed`` cluster.

Used by :mod:`.correlate` (correlation batches) and :mod:`.volumes` (output chunks). A run is a
generator of ``(index, result)`` pairs in completion order, so the engine can report progress as
tasks finish:

- ``scheduler=None`` (or ``"threads"``): dask's local threaded scheduler, nothing to start;
- ``"sync"``: one task at a time, in dask's order (not the list's; debugging);
- any other string: the address of a ``dask.distributed`` scheduler (``distributed`` is imported
  only then); or a ``distributed.Client``.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from concurrent.futures import ThreadPoolExecutor

LOCAL_SCHEDULERS = (None, "threads", "threading", "sync", "synchronous")


def is_local(scheduler) -> bool:
    """True for dask's local schedulers (no cluster involved)."""
    return isinstance(scheduler, (str, type(None))) and scheduler in LOCAL_SCHEDULERS


def run_local(tasks, workers: int = 1, synchronous: bool = False):
    """Compute delayed ``tasks`` on dask's local scheduler; yield ``(index, result)`` as they finish.

    The computation runs in a background thread; its exceptions are re-raised here, once the
    tasks still running have ended. Closing the generator early (a cancelled run) stops the
    computation: no task starts after that, the tasks already running finish, and the call
    returns once they and the background thread have ended.
    """
    import dask

    keys = {task.key: i for i, task in enumerate(tasks)}
    finished: queue.Queue = queue.Queue()
    cancelled = threading.Event()

    def pretask(key, dsk, state):
        if cancelled.is_set():
            raise _Cancelled()

    def posttask(key, result, dsk, state, worker_id):
        if key in keys:
            finished.put((keys[key], result))

    outcome: dict = {}
    # our own pool, so that a failed or cancelled run returns only once the tasks already running
    # have ended (dask's scheduler returns at the first error): none writes after the caller
    # has cleaned up (an unfinished output, a temporary array)
    pool = None if synchronous else ThreadPoolExecutor(max(1, int(workers)))

    def compute():
        try:
            dask.compute(
                *tasks,
                scheduler="sync" if synchronous else "threads",
                num_workers=max(1, int(workers)),
                **({} if pool is None else {"pool": pool}),
                # (start, start_state, pretask, posttask, finish), local to this computation
                callbacks=[(None, None, pretask, posttask, None)],
            )
        except BaseException as error:  # re-raised in the caller's thread
            outcome["error"] = error
            cancelled.set()  # the tasks not started yet need not run
        finally:
            if pool is not None:
                pool.shutdown(wait=True)
            finished.put(None)

    thread = threading.Thread(target=compute, name="dvc-dask-local", daemon=True)
    thread.start()
    try:
        while True:
            item = finished.get()
            if item is None:
                break
            yield item
    finally:
        cancelled.set()  # a no-op once every task has run
        thread.join()
    if "error" in outcome and not isinstance(outcome["error"], _Cancelled):
        raise outcome["error"]


class _Cancelled(Exception):
    """Raised inside dask's local scheduler to stop a run whose results nobody waits for."""


def connect(scheduler):
    """``(client, owned)``: a ``distributed.Client`` for an address (``owned``: close it after)."""
    try:
        import distributed
    except ImportError as error:  # pragma: no cover - distributed is a test dependency
        raise ImportError(
            "sending work to a cluster needs dask.distributed: pip install distributed"
        ) from error
    if isinstance(scheduler, distributed.Client):
        return scheduler, False
    if not isinstance(scheduler, str):
        raise ValueError(
            "scheduler must be None, 'threads', 'sync', a scheduler address (e.g. "
            f"'tcp://10.0.0.5:8786') or a distributed.Client, got {scheduler!r}"
        )
    try:
        return distributed.Client(scheduler, set_as_default=False, timeout="20s"), True
    except (OSError, TimeoutError) as error:
        raise ConnectionError(
            f"could not reach the dask scheduler at {scheduler!r} ({error}); start one with "
            "`dask scheduler` and workers with `dask worker ADDRESS`, or leave the scheduler out "
            "to run on this machine"
        ) from error


def cluster_resources(client) -> tuple[int, int, int]:
    """Total threads, the most threads of one worker, and the smallest worker memory limit (0 = none)."""
    workers = client.scheduler_info(n_workers=-1)["workers"]
    if not workers:
        raise ConnectionError(
            "the dask cluster has no workers: start some with `dask worker ADDRESS`"
        )
    threads = [int(w.get("nthreads", 1)) for w in workers.values()]
    limits = [int(w.get("memory_limit") or 0) for w in workers.values()]
    positive = [v for v in limits if v > 0]
    return sum(threads), max(threads), (min(positive) if positive else 0)


def run_distributed(tasks, client):
    """Compute delayed ``tasks`` on a cluster; yield ``(index, result)`` as they finish."""
    from distributed import as_completed

    futures = client.compute(tasks)
    index = {future.key: i for i, future in enumerate(futures)}
    try:
        for future in as_completed(futures, loop=client.loop):
            yield index[future.key], future.result()
    finally:
        client.cancel(futures)


def run(tasks, scheduler=None, workers: int = 1, client=None):
    """Dispatch to :func:`run_local` or :func:`run_distributed` (when ``client`` is given)."""
    if client is not None:
        return run_distributed(tasks, client)
    return run_local(tasks, workers, scheduler in ("sync", "synchronous"))


@contextlib.contextmanager
def running(tasks, scheduler=None, workers: int = 1, client=None):
    """:func:`run` as a context: leaving the ``with`` block early (an error, a cancelled caller)
    stops the run at once, local or on a cluster, instead of when the generator is collected."""
    results = run(tasks, scheduler, workers, client)
    try:
        yield results
    finally:
        results.close()
