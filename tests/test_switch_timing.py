"""The gripper-switch timing breakdown (`pi0_armfix.tools.switch_timing`) on hand-built chunks."""

import numpy as np

from pi0_armfix.tools.switch_timing import switch_timing

H = 8


def _gripper(*switches):
    """One chunk `[H, 1]` of a gripper command, -1 (closed) or +1 (open): closed at step 0, the
    command flipping at each step of `switches`."""
    chunk = np.full((H, 1), -1.0)
    for h in switches:
        chunk[h:] *= -1.0
    return chunk


def _timing(predicted, true, **kwargs):
    predicted, true = np.stack(predicted), np.stack(true)
    valid = np.ones(true.shape[:2], bool)
    settings = {"tolerances": (0, 1, 2), "tolerance": 1, "executed": H // 2} | kwargs
    return switch_timing(predicted, true, valid, np.zeros(1), **settings)


def test_a_switch_one_step_late_matches_from_tolerance_one():
    timing = _timing([_gripper(3)], [_gripper(2)])
    assert timing["by_tolerance"][0]["f1"] == 0.0
    assert timing["by_tolerance"][1] == {"precision": 1.0, "recall": 1.0, "f1": 1.0}


def test_recall_splits_the_executed_steps_from_those_ahead():
    # The true switch at step 1 is predicted; the one at step 6 (ahead) is not.
    timing = _timing([_gripper(1), _gripper()], [_gripper(1), _gripper(6)])
    assert timing["recall"]["executed"] == {"true": 1, "recall": 1.0}
    assert timing["recall"]["ahead"] == {"true": 1, "recall": 0.0}
    assert timing["by_tolerance"][1]["recall"] == 0.5


def test_one_predicted_switch_counts_once_across_the_parts():
    # True opens at 3 (executed) and 5 (ahead), a close at 4; one predicted open at 4, within the
    # tolerance of both opens: it matches one switch overall, so the parts share that one.
    timing = _timing([_gripper(4)], [_gripper(3, 4, 5)])
    assert timing["by_tolerance"][1]["recall"] == 1 / 3
    assert timing["recall"]["executed"] == {"true": 1, "recall": 1.0}
    assert timing["recall"]["ahead"] == {"true": 2, "recall": 0.0}
    matched = sum(timing["recall"][p]["true"] * timing["recall"][p]["recall"]
                  for p in ("executed", "ahead"))
    assert matched == 1


def test_recall_splits_opening_from_closing():
    # -1 -> +1 at step 2 opens, +1 -> -1 at step 5 closes; only the opening is predicted.
    timing = _timing([_gripper(2)], [_gripper(2, 5)])
    assert timing["recall"]["opens"] == {"true": 1, "recall": 1.0}
    assert timing["recall"]["closes"] == {"true": 1, "recall": 0.0}


def test_a_switch_of_the_wrong_direction_does_not_match():
    closing = -_gripper(3)  # +1 -> -1 at step 3
    timing = _timing([closing], [_gripper(3)])
    assert timing["by_tolerance"][2]["f1"] == 0.0


def test_switches_predicted_where_none_happens_are_counted():
    timing = _timing([_gripper(2, 4), _gripper(3)], [_gripper(), _gripper(3)])
    assert (timing["predicted"], timing["true"], timing["predicted_without_true"]) == (3, 1, 2)
    assert timing["by_tolerance"][0]["precision"] == 1 / 3


def test_a_chunk_without_any_switch_has_no_recall_to_measure():
    timing = _timing([_gripper()], [_gripper()])
    assert np.isnan(timing["by_tolerance"][0]["recall"])
    assert np.isnan(timing["recall"]["executed"]["recall"])
