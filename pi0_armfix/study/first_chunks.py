"""study.md's section on the held-out episodes' first chunks and on the errors in the robot's units.

An episode's first chunk is the one place where a run relative to the previous command has no
command to be relative to (`transforms.EpisodeStart`: the state and its mean offset where the
state map holds the joints as positions, else the training split's mean action), and where
holding the previous action is the true first action. A per-group table that mixes it with
the rest can be ruled by it: on the G1's idle arm, when the first chunk was made relative to the
state vector's own dims whatever they held, those 20 chunks held most of the offset lever's
error. So each
trained config's per-group skill over holding is given with every chunk and without the
episodes' first chunks (from each run's kept per-chunk sums, `chunk_sums_lib.CHUNK_SUMS_FILE`), with the
first chunks' share of the single draw's squared error; and beside it the single draw's error
in the data's own units (`rms_units`, radians or degrees for a joint) and holding's and copying
the state's, so a reader sees whether a negative skill is an arm that jitters by a fraction of a
degree or one that moves.

Intervals: t intervals over seeds at 95 %, uncorrected (each cell its own question); a cell of
fewer than 2 seeds has none. Lever variants are measured on their trained config's chunks and
left out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.evaluation import intervals
from pi0_armfix.study.run import run_folder, saved_config, trained_config

FIRST_CHUNKS_HEADING = "## Episodes' first chunks, in and out; errors in the robot's units"
SAMPLERS = ("policy", chunk_sums_lib.MEAN_OF_DRAWS)  # the single draw, the mean of the draws


def later_chunks(sums: Mapping[str, np.ndarray]) -> np.ndarray:
    """`[N]` bool: the chunks that start past their episode's first frame. Sums kept before
    chunks were named (`chunk_sums_lib.CHUNKS`) hold each chunk's episode in tiling order: an episode's
    first row is its first chunk (`tiled_chunk_starts` starts every episode at its first frame;
    `run_rows` takes them only where no tile was thinned out)."""
    if chunk_sums_lib.CHUNKS in sums:
        return np.asarray(sums[chunk_sums_lib.CHUNKS])[:, 1] > 0
    episode = np.asarray(sums[chunk_sums_lib.EPISODE])
    return np.concatenate([[False], episode[1:] == episode[:-1]])


def skills(sums: Mapping[str, np.ndarray], layout: ActionLayout, rows: np.ndarray
           ) -> dict[str, float]:
    """`{"<sampler>/<group>": skill over holding}` of the chunks `rows` `[N]` bool (NaN where
    holding is exact on them)."""
    out = {}
    for g in layout.group_names:
        held = float(np.sum(sums[f"persistence/sq_err/{g}"][rows]))
        for sampler in SAMPLERS:
            err = float(np.sum(sums[f"{sampler}/sq_err/{g}"][rows]))
            out[f"{sampler}/{g}"] = 1.0 - err / held if held > 0 else math.nan
    return out


def first_share(sums: Mapping[str, np.ndarray], layout: ActionLayout) -> dict[str, float]:
    """`{group: the first chunks' share of the single draw's squared error}`."""
    first = ~later_chunks(sums)
    out = {}
    for g in layout.group_names:
        err = np.asarray(sums[f"policy/sq_err/{g}"])
        out[g] = float(err[first].sum() / err.sum()) if err.sum() > 0 else math.nan
    return out


def run_rows(result: Mapping[str, Any], workdir: Path) -> dict[str, Any] | None:
    """One run's numbers for the section, or None where it kept no per-chunk sums."""
    folder = run_folder(workdir, result["config"], result["seed"])
    path = evaluator_lib.heldout_paths(folder, result["steps"])[1]
    if not path.exists():
        return None
    sums = chunk_sums_lib.load_chunk_sums(path)
    layout = ActionLayout.from_config(result["layout"])
    every = np.ones(len(sums[chunk_sums_lib.EPISODE]), bool)
    if (chunk_sums_lib.CHUNKS not in sums
            and len(every) >= saved_config(folder)["eval"]["max_chunks"]):
        return None  # unnamed chunks, perhaps thinned: an episode's first row may start later
    metrics = result["metrics"]
    return {"all": skills(sums, layout, every), "later": skills(sums, layout, later_chunks(sums)),
            "share": first_share(sums, layout),
            "first_chunks": int((~later_chunks(sums)).sum()), "chunks": len(every),
            "rms": {f"{who}{g}": metrics.get(f"{who}rms_units/{g}")
                    for g in layout.group_names
                    for who in ("", "persistence/", "state_copy/")}}


def _cell(values: Sequence[float | None]) -> str:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return "n/a"
    mean, low, high = intervals.mean_interval(finite)
    if not math.isfinite(low):
        return f"{mean:+.3f}"
    return f"{mean:+.3f} [{low:+.3f}, {high:+.3f}]"


def _units(values: Sequence[float | None]) -> str:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return f"{np.mean(finite):.4g}" if finite else "n/a"


def section(results: Sequence[Mapping[str, Any]], workdir: Path) -> list[str]:
    """The section's lines (none where no run kept its per-chunk sums)."""
    by_config: dict[str, list[dict[str, Any]]] = {}
    layouts: dict[str, ActionLayout] = {}
    for result in results:
        if trained_config(result["config"]) != result["config"]:
            continue
        rows = run_rows(result, workdir)
        if rows is not None:
            by_config.setdefault(result["config"], []).append(rows)
            layouts[result["config"]] = ActionLayout.from_config(result["layout"])
    if not by_config:
        return []
    first = next(iter(by_config.values()))[0]
    lines = ["", FIRST_CHUNKS_HEADING, "",
             f"Skill over holding per group, with every held-out chunk and without the episodes' "
             f"first chunks ({first['first_chunks']} of {first['chunks']}), single draw and mean "
             "of the draws (mean over seeds [95 % t interval over seeds, uncorrected]); the "
             "first chunks' share of the single draw's squared error; the single draw's, "
             "holding's and copying the state's RMS error in the data's own units (n/a: a run "
             "evaluated before they were kept). pi0_armfix/study/first_chunks.py.", "",
             "| config | seeds | group | skill, all | skill, without first | mean of draws, all "
             "| mean of draws, without first | first chunks' share | rms | holding rms "
             "| state copy rms |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for config, runs in by_config.items():
        for g in layouts[config].group_names:
            cells = [_cell([r[part][f"{sampler}/{g}"] for r in runs])
                     for sampler in SAMPLERS for part in ("all", "later")]
            shares = [r["share"][g] for r in runs if math.isfinite(r["share"][g])]
            share = f"{100 * np.mean(shares):.0f} %" if shares else "n/a"
            rms = [_units([r["rms"][f"{who}{g}"] for r in runs])
                   for who in ("", "persistence/", "state_copy/")]
            lines.append(f"| {config} | {len(runs)} | {g} | {' | '.join(cells)} | {share} | "
                         f"{' | '.join(rms)} |")
    return lines
