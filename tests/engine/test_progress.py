"""Progress records and driving an engine generator to its end."""

from napari_dvc_correct.engine.progress import Progress, run_to_completion


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
