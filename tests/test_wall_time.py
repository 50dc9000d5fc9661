"""A command's wall time by part (`pi0_armfix.wall_time`): what the walltime benchmark reads."""

import time

import pytest

from pi0_armfix import wall_time


def test_a_part_that_runs_again_adds_up_in_the_order_parts_first_ran():
    clock = wall_time.WallTime()
    clock.add("compile", 2.0)
    clock.add("steps", 5.0)
    clock.add("compile", 1.5)
    assert list(clock.parts) == ["compile", "steps"]
    assert clock.parts["compile"] == 3.5


def test_a_part_that_raises_is_still_counted():
    clock = wall_time.WallTime()
    with pytest.raises(KeyError), clock.part("lookup"):
        time.sleep(0.01)
        raise KeyError("x")
    assert clock.parts["lookup"] >= 0.01


def test_the_record_round_trips_through_its_file_and_its_total_holds_every_part(tmp_path):
    clock = wall_time.WallTime()
    with clock.part("sleep"):
        time.sleep(0.01)
    clock.save(tmp_path / wall_time.FILE)
    record = wall_time.load(tmp_path / wall_time.FILE)
    assert list(record["parts"]) == ["sleep"]
    assert record["total"] >= record["parts"]["sleep"] >= 0.01
    assert clock.summary().startswith("wall time by part (s): sleep 0.0")
