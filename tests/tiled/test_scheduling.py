"""Running delayed tasks: which schedulers are local, results by index, threads, errors, a cluster."""

import threading

import dask
import pytest

from napari_dvc_correct.tiled import scheduling
from napari_dvc_correct.tiled.scheduling import (
    cluster_resources,
    connect,
    is_local,
    run,
    run_local,
    running,
)


def _square(i):
    return i * i


def _tasks(n=6):
    return [dask.delayed(_square)(i) for i in range(n)]


@pytest.mark.parametrize("scheduler", [None, "threads", "threading", "sync", "synchronous"])
def test_local_schedulers(scheduler):
    assert is_local(scheduler)


@pytest.mark.parametrize("scheduler", ["tcp://10.0.0.5:8786", "processes", "", object(), 3])
def test_other_schedulers_are_not_local(scheduler):
    assert not is_local(scheduler)


@pytest.mark.parametrize("workers", [1, 2])
def test_run_local_gives_every_result_under_its_index(workers):
    pairs = list(run_local(_tasks(), workers=workers))
    assert sorted(index for index, _ in pairs) == list(range(6))  # each task exactly once
    assert dict(pairs) == {i: i * i for i in range(6)}


@pytest.mark.parametrize(("workers", "synchronous"), [(1, False), (4, True)])
def test_one_worker_or_synchronous_runs_one_task_at_a_time(workers, synchronous):
    lock = threading.Lock()
    running, most = [0], [0]

    def track(i):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        threading.Event().wait(0.01)
        with lock:
            running[0] -= 1
        return i

    tasks = [dask.delayed(track)(i) for i in range(6)]
    assert dict(run_local(tasks, workers=workers, synchronous=synchronous)) == {
        i: i for i in range(6)
    }
    assert most[0] == 1


def test_two_workers_run_two_tasks_at_once():
    # each task waits for the other at a barrier: only two concurrent threads get through
    barrier = threading.Barrier(2, timeout=10)

    def meet(i):
        barrier.wait()
        return i

    tasks = [dask.delayed(meet)(i) for i in range(2)]
    assert dict(run_local(tasks, workers=2)) == {0: 0, 1: 1}


def test_results_are_yielded_as_tasks_finish():
    # the second task finishes only after the caller has received the first result
    first_seen = threading.Event()

    def fast():
        return "fast"

    def slow():
        return "slow" if first_seen.wait(timeout=10) else "timed out"

    generator = run_local([dask.delayed(fast)(), dask.delayed(slow)()], workers=2)
    assert next(generator) == (0, "fast")
    first_seen.set()
    assert list(generator) == [(1, "slow")]


def test_errors_of_a_task_are_raised_in_the_caller():
    def fail(i):
        if i == 2:
            raise ZeroDivisionError(f"task {i} failed")
        return i

    tasks = [dask.delayed(fail)(i) for i in range(4)]
    with pytest.raises(ZeroDivisionError, match="task 2 failed"):
        list(run_local(tasks, workers=2))


class _Recorder:
    """Tasks that record when they start and finish (20 ms each)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.started, self.active = [], 0

    def task(self, i):
        with self.lock:
            self.started.append(i)
            self.active += 1
        threading.Event().wait(0.02)
        with self.lock:
            self.active -= 1
        return i

    def tasks(self, n=8):
        return [dask.delayed(self.task)(i) for i in range(n)]


def test_closing_the_generator_stops_the_run():
    recorder = _Recorder()
    generator = run_local(recorder.tasks(), workers=1)
    next(generator)
    generator.close()
    # returns once the background thread has ended: nothing runs any more, and at most the task
    # that was running when the run was closed started after the first result
    assert recorder.active == 0
    assert len(recorder.started) <= 2
    threading.Event().wait(0.1)
    assert len(recorder.started) <= 2  # no task starts later either


def test_leaving_running_early_stops_the_run():
    recorder = _Recorder()
    with pytest.raises(KeyError, match="the caller failed"):
        with running(recorder.tasks(), workers=1) as results:
            next(results)
            raise KeyError("the caller failed")
    assert recorder.active == 0
    assert len(recorder.started) <= 2
    # run to the end, the context gives every result
    recorder = _Recorder()
    with running(recorder.tasks(4), workers=2) as results:
        assert dict(results) == {i: i for i in range(4)}
    assert sorted(recorder.started) == [0, 1, 2, 3]


def test_run_dispatches_locally_by_default(monkeypatch):
    calls = []
    real = scheduling.run_local

    def spy(tasks, workers=1, synchronous=False):
        calls.append((workers, synchronous))
        return real(tasks, workers, synchronous)

    monkeypatch.setattr(scheduling, "run_local", spy)
    assert dict(run(_tasks())) == {i: i * i for i in range(6)}
    assert dict(run(_tasks(3), scheduler="sync")) == {0: 0, 1: 1, 2: 4}
    assert dict(run(_tasks(3), scheduler="threads", workers=2)) == {0: 0, 1: 1, 2: 4}
    assert calls == [(1, False), (1, True), (2, False)]


def test_connect_refuses_what_is_not_a_scheduler():
    with pytest.raises(ValueError, match="scheduler must be None, 'threads', 'sync', a scheduler"):
        connect(42)


class _FakeClient:
    def __init__(self, workers):
        self.workers = workers

    def scheduler_info(self, n_workers=-1):
        return {"workers": self.workers}


def test_cluster_resources():
    client = _FakeClient(
        {
            "a": {"nthreads": 4, "memory_limit": 8 * 2**30},
            "b": {"nthreads": 2, "memory_limit": 4 * 2**30},
            "c": {"nthreads": 1, "memory_limit": 0},  # no limit
        }
    )
    assert cluster_resources(client) == (7, 4, 4 * 2**30)
    assert cluster_resources(_FakeClient({"a": {"nthreads": 2}})) == (2, 2, 0)
    with pytest.raises(ConnectionError, match="the dask cluster has no workers"):
        cluster_resources(_FakeClient({}))


def test_run_sends_the_tasks_to_a_cluster_when_given_a_client():
    import distributed  # a test dependency (imported here: it is slow to import)

    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster, set_as_default=False) as client,
    ):
        assert connect(client) == (client, False)  # a Client is used, not owned
        assert cluster_resources(client)[:2] == (2, 2)
        pairs = list(run(_tasks(), client=client))
    assert sorted(index for index, _ in pairs) == list(range(6))
    assert dict(pairs) == {i: i * i for i in range(6)}
