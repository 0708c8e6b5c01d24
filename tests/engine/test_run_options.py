"""How a run is carried out: the checked RunOptions record (engine/run_options.py)."""

import pytest

from napari_dvc_correct.engine.run_options import MAX_MEMORY_BYTES, RunOptions


def test_the_defaults_run_in_memory_and_choose_the_device():
    options = RunOptions()
    assert not options.out_of_core
    assert options.device == "auto"
    assert options.tiled_keywords() == {
        "batch_shape": None,
        "max_memory": None,
        "workers": None,
        "scheduler": None,
        "device": "auto",
    }


@pytest.mark.parametrize(
    "changes",
    [
        {"tiled": True},
        {"max_memory": 2**30},
        {"workers": 2},
        {"scheduler": "tcp://10.0.0.5:8786"},
        {"batch_shape": (4, 4, 4)},
        {"block_shape": (64, 64, 64)},
    ],
)
def test_any_out_of_core_option_asks_for_out_of_core(changes):
    assert RunOptions(**changes).out_of_core


def test_a_temp_dir_asks_for_out_of_core(tmp_path):
    options = RunOptions(temp_dir=str(tmp_path))
    assert options.out_of_core and options.temp_dir == str(tmp_path)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"tiled": "cpu"}, "tiled must be True or False"),
        ({"device": "gpu"}, "device must be one of"),
        ({"max_memory": 0}, "max_memory must be > 0"),
        ({"max_memory": MAX_MEMORY_BYTES}, "max_memory must be > 0"),
        ({"max_memory": "lots"}, "max_memory must be > 0"),
        ({"workers": 0}, "workers must be a whole number >= 1"),
        ({"workers": 1.5}, "workers must be a whole number >= 1"),
        ({"batch_shape": (4, 4)}, "batch_shape must be 3 whole numbers"),
        ({"block_shape": (0, 8, 8)}, "block_shape must be 3 whole numbers"),
        ({"temp_dir": "/no/such/folder/here"}, "is not an existing folder"),
    ],
)
def test_a_bad_option_is_refused_with_what_to_change(changes, message):
    with pytest.raises(ValueError, match=message):
        RunOptions(**changes)


def test_a_blank_scheduler_is_none_and_the_record_round_trips(tmp_path):
    assert RunOptions(scheduler="  ").scheduler is None
    options = RunOptions(max_memory=1.5e9, batch_shape=[2, 3, 4], temp_dir=str(tmp_path))
    assert options.max_memory == 1_500_000_000 and options.batch_shape == (2, 3, 4)
    assert RunOptions.from_dict(options.as_dict()) == options
