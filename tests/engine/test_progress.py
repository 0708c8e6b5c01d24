"""Progress records and driving an engine generator to its end."""

from napari_dvc_correct.engine.progress import (
    Progress,
    forward_progress,
    run_to_completion,
    state_of,
)


def test_fraction_is_done_over_total_clipped():
    assert Progress("IC-GN", 25, 100).fraction == 0.25
    assert Progress("IC-GN", 120, 100).fraction == 1.0
    assert Progress("plan", 0, 0).fraction == 1.0  # nothing planned: done
    assert Progress("warp", 1, 4, "block 1 of 4").message == "block 1 of 4"


def test_run_to_completion_returns_the_generator_s_value():
    seen = []

    def work():
        for k in range(3):
            seen.append(k)
            yield Progress("work", k + 1, 3)
        return "result"

    assert run_to_completion(work()) == "result"
    assert seen == [0, 1, 2]  # every step ran


def test_forward_progress_prefixes_the_stages_and_returns_the_value():
    def inner():
        yield Progress("IC-GN", 1, 2, "half")
        yield Progress("IC-GN", 2, 2, "all")
        return 42

    def outer():
        value = yield from forward_progress(inner(), "pass 1")
        return value + 1

    reports = []
    generator = outer()
    while True:
        try:
            reports.append(next(generator))
        except StopIteration as stop:
            result = stop.value
            break
    assert [p.stage for p in reports] == ["pass 1: IC-GN", "pass 1: IC-GN"]
    assert [(p.done, p.total, p.message) for p in reports] == [(1, 2, "half"), (2, 2, "all")]
    assert result == 43


def test_a_closed_forwarder_closes_the_inner_generator():
    closed = []

    def inner():
        try:
            yield Progress("work", 0, 1)
            yield Progress("work", 1, 1)
        finally:
            closed.append(True)

    generator = forward_progress(inner(), "outer")
    next(generator)
    generator.close()  # a cancelled caller
    assert closed == [True]


def test_a_series_stage_says_which_state_of_how_many_and_other_values_pass():
    def inner():
        yield Progress("IC-GN", 1, 2)
        yield "a partial result"  # not a Progress: forwarded as it is
        return 7

    generator = forward_progress(inner(), state_of(2, 3))
    assert next(generator).stage == "state 2 of 3: IC-GN"
    assert next(generator) == "a partial result"
    assert run_to_completion(generator) == 7
