"""study.md's section on the held-out episodes' first chunks and the errors in the robot's units
(`pi0_armfix.study.first_chunks`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.study import first_chunks
from pi0_armfix.study.run import run_folder

LAYOUT = ActionLayout({"arm": (0, 2), "hand": (2, 3)}, real_dim=3, action_dim=4)


def kept_sums(named: bool = True) -> dict[str, np.ndarray]:
    """Two episodes of three chunks; the policy errs 9 on each episode's first chunk and 1
    elsewhere on the arm, holding 2 everywhere; the hand is exact for both."""
    first = np.array([True, False, False, True, False, False])
    sums = {chunk_sums_lib.EPISODE: np.array([0, 0, 0, 1, 1, 1])}
    if named:
        sums[chunk_sums_lib.CHUNKS] = np.array([[5, 0, 8], [5, 7, 8], [5, 14, 8],
                                             [9, 0, 8], [9, 7, 8], [9, 14, 8]])
    for who, arm in (("policy", np.where(first, 9.0, 1.0)),
                     (chunk_sums_lib.MEAN_OF_DRAWS, np.where(first, 3.0, 0.5)),
                     ("persistence", np.full(6, 2.0))):
        sums[f"{who}/sq_err/arm"] = arm
        sums[f"{who}/sq_err/hand"] = np.zeros(6)
    return sums


@pytest.mark.parametrize("named", [True, False])
def test_the_first_chunks_are_those_starting_at_their_episodes_first_frame(named):
    assert first_chunks.later_chunks(kept_sums(named)).tolist() == [False, True, True] * 2


def test_skill_without_the_first_chunks_leaves_their_error_out():
    sums = kept_sums()
    every = np.ones(6, bool)
    with_first = first_chunks.skills(sums, LAYOUT, every)
    without = first_chunks.skills(sums, LAYOUT, first_chunks.later_chunks(sums))
    assert with_first["policy/arm"] == pytest.approx(1 - 22 / 12)
    assert without["policy/arm"] == pytest.approx(1 - 4 / 8)
    assert without[f"{chunk_sums_lib.MEAN_OF_DRAWS}/arm"] == pytest.approx(1 - 2 / 8)
    assert np.isnan(without["policy/hand"])  # holding is exact: no skill to score
    assert first_chunks.first_share(sums, LAYOUT)["arm"] == pytest.approx(18 / 22)


def test_the_study_report_gives_each_group_with_and_without_first_chunks(tmp_path):
    results = []
    for seed in range(2):
        result = {"config": "uniform", "seed": seed, "steps": 10,
                  "layout": {"groups": LAYOUT.groups, "real_dim": 3, "action_dim": 4},
                  "metrics": {"rms_units/arm": 0.01 * (seed + 1),
                              "persistence/rms_units/arm": 0.02}}
        folder = run_folder(tmp_path, "uniform", seed)
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps({"eval": {"max_chunks": 512}}))
        chunk_sums_lib.save_chunk_sums(evaluator_lib.heldout_paths(folder, 10)[1], kept_sums())
        results.append(result)
    lines = first_chunks.section(results, tmp_path)
    assert first_chunks.FIRST_CHUNKS_HEADING in lines
    row = next(line for line in lines if line.startswith("| uniform | 2 | arm |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # both seeds alike: a zero-width interval
    assert cells[3] == "-0.833 [-0.833, -0.833]" and cells[4] == "+0.500 [+0.500, +0.500]"
    assert cells[7] == "82 %"
    assert cells[8:11] == ["0.015", "0.02", "n/a"]  # rms: mean over seeds; state copy unkept


def test_unnamed_chunks_that_may_have_been_thinned_are_left_out(tmp_path):
    folder = run_folder(tmp_path, "uniform", 0)
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"eval": {"max_chunks": 6}}))
    chunk_sums_lib.save_chunk_sums(evaluator_lib.heldout_paths(folder, 10)[1], kept_sums(False))
    result = {"config": "uniform", "seed": 0, "steps": 10, "metrics": {},
              "layout": {"groups": LAYOUT.groups, "real_dim": 3, "action_dim": 4}}
    assert first_chunks.run_rows(result, tmp_path) is None
