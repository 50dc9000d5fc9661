"""A study's numbers: per config, mean and spread over seeds of every metric, each config's
difference to the baseline with intervals over seeds and held-out episodes
(`evaluation.intervals`), the do-nothing rows, and the targets a config meets (docs/evaluation.md).

Pure functions of the runs' `result.json` contents; `pi0_armfix.study` runs the study,
`pi0_armfix.study.report` writes what this module computes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pi0_armfix.evaluation import intervals
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.evaluation import baselines as baselines_lib
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib

SWITCH_METRICS = ("precision", "recall", "f1")
SWITCH_COUNTS = ("tp", "fp", "fn")
CLOSED_LOOP = "closed_loop/"  # prefix of the closed-loop metrics of a run
CLOSED_LOOP_KINDS = ("navigation", "manipulation", "task")
PHASE_KINDS = CLOSED_LOOP_KINDS[:2]
# Compared with the baseline: episodes whose every phase of a kind succeeded, and the share of
# phases that succeeded (the seed's claim is about phases).
CLOSED_LOOP_COMPARED = (*(f"success/{k}" for k in CLOSED_LOOP_KINDS),
                        *(f"phase_success/{k}" for k in PHASE_KINDS))
CLOSED_LOOP_TOLERANCES = (1.0, 2.0, 4.0)  # the success curve: the world's tolerances times these


def curve_prefix(factor: float) -> str:
    """The prefix of a closed-loop rate measured with the world's tolerances times `factor`
    (`closed_loop/curve/<f>x/<rate>` in a run's metrics, `curve/<f>x/<outcome>` in its
    per-episode outcomes)."""
    return f"curve/{factor:g}x/"


LOOSER_TOLERANCES = tuple(f for f in CLOSED_LOOP_TOLERANCES if f != 1)
# The same rates at the looser tolerances, compared only where every run kept their per-episode
# outcomes (a run measured before they were kept has its rates, not their resamples).
CURVE_COMPARED = tuple(curve_prefix(f) + k for f in LOOSER_TOLERANCES
                       for k in CLOSED_LOOP_COMPARED)
EPISODE_REPLICATES = "episode_replicates"  # result.json: headline numbers per episode resample
CLOSED_LOOP_EPISODES = "closed_loop_episodes"  # result.json: per-episode closed-loop outcomes


@dataclasses.dataclass(frozen=True)
class Targets:
    """The bar for a config that fixes stagnation (reported, never tuned to)."""

    arm_gain: float = 0.5  # each arm's mean held-out motion gain over seeds ...
    ceiling_share: float = 0.7  # ... or this share of the ceiling's gain ...
    ceiling_below: float = 0.7  # ... where the ceiling's gain is below this
    base_skill_drop: float = 0.10  # base skill at most 10 % below the baseline config's
    switch_f1: float = 0.6
    # closed loop: manipulation phases succeeded, at least this many points above the baseline
    # (interval above 0) ...
    manipulation_gain: float = 0.30
    navigation_drop: float = 0.10  # ... navigation phases at most this many points below it ...
    switch_precision: float = 0.6  # ... and the held-out gripper switch precision




def episode_replicates(sums: Mapping[str, np.ndarray], layout: ActionLayout
                       ) -> dict[str, Any]:
    """A run's headline numbers (`COMPARED`) on each of the study's resamples of its held-out
    episodes (`intervals.episode_counts`), from its per-chunk sums (`HeldOutChunks.score`):
    `{"episodes": E, "chunks": the chunks' fingerprint, <name>: [B] values}` for the headline
    numbers and each group's (`group_keys`)."""
    num_episodes = len(np.unique(sums[chunk_sums_lib.EPISODE]))
    replicates = {k: [] for k in (*COMPARED, *group_keys(layout))}
    for metrics in chunk_sums_lib.resampled_metrics(sums, layout):
        for k, v in {**run_summary(metrics, layout), **metrics}.items():
            if k in replicates:
                v = as_number(v)
                replicates[k].append(v if math.isfinite(v) else None)
    return {"episodes": num_episodes, "chunks": chunk_sums_lib.chunks_fingerprint(sums),
            **replicates}


def check_same_chunks(results: Sequence[Mapping[str, Any]]) -> None:
    """Refuses runs scored on different held-out chunks (another horizon, `eval.max_chunks` or
    held-out split): their differences and the do-nothing rows (the first run's) would compare
    other chunks. Runs kept before their chunks had a fingerprint are not checked.

    Raises:
      ValueError naming the runs of each set of chunks.
    """
    groups: dict[str, list[str]] = {}
    for r in results:
        fingerprint = (r.get(EPISODE_REPLICATES) or {}).get("chunks")
        if fingerprint:
            groups.setdefault(fingerprint, []).append(f"{r['config']} seed {r['seed']}")
    if len(groups) > 1:
        sets = "; ".join(f"chunks {k}: {', '.join(v)}" for k, v in groups.items())
        raise ValueError(f"the runs were scored on different held-out chunks ({sets}): compare "
                         "runs with the same model.action_horizon, eval.max_chunks and held-out "
                         "episodes (eval.episodes, data.root), or study them apart")



def closed_loop_outcomes(detail: Sequence[Mapping[str, Any]]) -> dict[str, list[int]]:
    """Per closed-loop episode (`closed_loop.json`'s `episodes_detail`), what the study resamples:
    `success/<kind>` 0/1, and per phase kind the phases and the phases that succeeded."""
    out = {f"success/{k}": [int(bool(e[k])) for e in detail] for k in CLOSED_LOOP_KINDS}
    for kind in PHASE_KINDS:
        out[f"phases/{kind}"] = [sum(p["kind"] == kind for p in e["phases"]) for e in detail]
        out[f"phase_successes/{kind}"] = [sum(p["kind"] == kind and bool(p["success"])
                                              for p in e["phases"]) for e in detail]
    return out


def closed_loop_replicates(outcomes: Mapping[str, Sequence[int]], key: str) -> np.ndarray:
    """`[B]`: a run's closed-loop rate `key` (one of `CLOSED_LOOP_COMPARED`, or of
    `CURVE_COMPARED` from the outcomes at that factor) on each of the study's resamples of its
    episodes (`intervals.episode_counts`, the same for every run of that many episodes)."""
    at, name, kind = _rate_parts(key)
    counts = intervals.episode_counts(len(outcomes[f"{at}success/{kind}"]))  # [B, E]
    if name == "success":
        return counts @ np.asarray(outcomes[key], np.float64) / counts.sum(axis=1)
    phases = counts @ np.asarray(outcomes[f"{at}phases/{kind}"], np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(phases > 0, counts @ np.asarray(outcomes[f"{at}phase_successes/{kind}"],
                                                        np.float64) / phases, np.nan)


def has_outcomes(run: Mapping[str, Any], key: str) -> bool:
    """Whether a run kept the per-episode outcomes behind its closed-loop rate `key`."""
    at, _, kind = _rate_parts(key)
    return f"{at}success/{kind}" in run.get(CLOSED_LOOP_EPISODES, {})


def _rate_parts(key: str) -> tuple[str, str, str]:
    """`("curve/2x/", "phase_success", "navigation")` of a closed-loop rate's key (the prefix
    empty at the world's own tolerances)."""
    *prefix, name, kind = key.split("/")
    return "".join(f"{p}/" for p in prefix), name, kind


def arm_groups(layout: ActionLayout) -> tuple[str, ...]:
    return layout.groups_with_role("arm")


def group_keys(layout: ActionLayout) -> tuple[str, ...]:
    """The per-group numbers compared with the baseline beside the headline: each group's skill
    over persistence, the single draw's and the mean of the draws'."""
    return tuple(f"{prefix}skill/{g}" for prefix in ("", f"{chunk_sums_lib.MEAN_OF_DRAWS}/")
                 for g in layout.group_names)


def run_summary(metrics: Mapping[str, Any], layout: ActionLayout, prefix: str = ""
                ) -> dict[str, float]:
    """The headline numbers of one run (or, with `prefix` "persistence/" or "state_copy/", of a
    do-nothing predictor scored beside it): the arms' mean skill over persistence (the single
    draw's, the mean of the draws', the energy score's) and motion gain, the base's skill and
    error, gripper switch F1. A point prediction's mean of draws is itself."""
    arms = arm_groups(layout)
    base = layout.groups_with_role("base")

    def get(key):
        return as_number(metrics.get(prefix + key))

    def arms_mean(name):
        return float(np.mean([get(f"{name}/{g}") for g in arms])) if arms else math.nan

    mean_of_draws = arms_mean(f"{chunk_sums_lib.MEAN_OF_DRAWS}/skill")
    return {"arm_skill": arms_mean("skill"),
            "arm_skill_mean_of_draws": arms_mean("skill") if prefix else mean_of_draws,
            "arm_energy_skill": arms_mean("energy_skill"), "arm_gain": arms_mean("motion_gain"),
            "base_skill": get(f"skill/{base[0]}") if base else math.nan,
            "base_err": get(f"err/{base[0]}") if base else math.nan,
            "switch_f1": get("gripper_switch/f1")}


def as_number(value: Any) -> float:
    return math.nan if value is None else float(value)


# vs the baseline config, with study.md's headings
COMPARED = ("arm_skill", "arm_skill_mean_of_draws", "arm_energy_skill", "arm_gain", "base_skill",
            "switch_f1")
COMPARED_HEADINGS = ("arms' skill (single draw)", "arms' skill (mean of draws)",
                     "arms' energy skill", "arms' gain", "base skill (single draw)", "switch F1")


def aggregate(results: Sequence[Mapping[str, Any]], targets: Targets = Targets(),
              primary: str | None = None, ceiling: Mapping[str, float] | None = None
              ) -> dict[str, Any]:
    """Mean and std over seeds of every metric per config, the headline numbers with their
    per-seed values, each config's difference to the first config (the baseline) with Welch t
    intervals, the do-nothing rows, and the targets each config meets. `ceiling`: metrics of a
    perfect sampler on the same chunks (`evaluation.ceiling`), where known.

    The `primary` comparison at 95 % (a lever variant too); two families of the others, each
    Bonferroni-corrected over its members per compared quantity: the other trained configs with
    >= 2 seeds against the baseline (secondary), and the other lever variants (each against its
    trained config, paired, and against the baseline). A 1-seed config has no interval, so it is
    in no family. Each group against holding (`group_intervals`) is an uncorrected 95 % per
    cell. Each config's level is its `confidence`."""
    check_same_chunks(results)
    configs = list(dict.fromkeys(r["config"] for r in results))
    layout = ActionLayout.from_config(results[0]["layout"])
    baseline = configs[0]
    if primary is None:
        primary = configs[1] if len(configs) > 1 else baseline
    if primary not in configs:
        raise ValueError(f"--primary={primary!r} is not one of the study's configs {configs}")
    # The primary comparison holds at 95 % whatever it is (a lever variant too); each family
    # of the others is Bonferroni-corrected over its members, per compared quantity (column).
    levers = [c for c in configs if c != primary
              and any(r.get("trained") for r in results if r["config"] == c)]
    secondary = [c for c in configs if c not in (baseline, primary, *levers)
                 and sum(r["config"] == c for r in results) >= 2]
    lever_confidence = intervals.comparison_confidence(False, len(levers))
    resampled = _episode_resamples(results)
    episodes = resampled["episodes"] if resampled else 0

    def replicates(config: str, key: str) -> np.ndarray | None:
        """`[n, B]` the config's runs' `key` on the resamples; None where a run lacks them (a
        result kept before its per-group resamples)."""
        runs = [r for r in results if r["config"] == config]
        if not resampled or any(key not in r[EPISODE_REPLICATES] for r in runs):
            return None
        return np.asarray([[math.nan if v is None else v for v in r[EPISODE_REPLICATES][key]]
                           for r in runs], np.float64)

    def versus_baseline(config: str, key: str, values, base_values, confidence: float):
        mine, theirs = replicates(config, key), replicates(baseline, key)
        with_episodes = mine is not None and theirs is not None and config != baseline
        return intervals.welch_interval(
            values, base_values, confidence, episodes=episodes if with_episodes else 0,
            episode_variance=(intervals.episode_variance(mine, episodes, theirs)
                              if with_episodes else 0.0))

    per_config: dict[str, Any] = {}
    for config in configs:
        runs = [r for r in results if r["config"] == config]
        names = sorted({k for r in runs for k in r["metrics"]
                        if isinstance(r["metrics"][k], (int, float)) or r["metrics"][k] is None})
        values = {k: np.asarray([as_number(r["metrics"].get(k)) for r in runs]) for k in names}
        summary = [run_summary(r["metrics"], layout) for r in runs]
        headline = {k: np.asarray([s[k] for s in summary]) for k in summary[0]}
        per_config[config] = {
            "seeds": [r["seed"] for r in runs],
            # how its policy was executed (`Sampling.summary`); runs kept before it: unrecorded
            "execution": "; ".join(sorted({r.get("execution") or "not recorded" for r in runs})),
            "mean": {k: nanmean(v) for k, v in {**values, **headline}.items()},
            "std": {k: nanstd(v) for k, v in {**values, **headline}.items()},
            "headline": {k: v.tolist() for k, v in headline.items()},
            "arm_skill_interval": intervals.mean_interval(
                headline["arm_skill"], episodes=episodes, episode_variance=(
                    intervals.episode_variance(replicates(config, "arm_skill"), episodes)
                    if resampled else 0.0)),
        }
    base_values = per_config[baseline]["headline"]
    base_runs = [r for r in results if r["config"] == baseline]
    for config in configs:
        entry = per_config[config]
        if config in levers:
            confidence, entry["comparison"] = lever_confidence, "lever"
        elif config not in (baseline, primary, *secondary):
            confidence, entry["comparison"] = intervals.CONFIDENCE, "anecdote (1 seed)"
        else:
            confidence = intervals.comparison_confidence(config in (primary, baseline),
                                                         len(secondary))
            entry["comparison"] = ("baseline" if config == baseline else
                                   "primary" if config == primary else "secondary")
        entry["confidence"] = confidence
        entry["vs_baseline"] = {k: versus_baseline(config, k, entry["headline"][k],
                                                   base_values[k], confidence)
                                for k in COMPARED}
        runs = [r for r in results if r["config"] == config]
        groups_of = lambda rs, k: [as_number(r["metrics"].get(k)) for r in rs]  # noqa: E731
        entry["vs_baseline_groups"] = {
            k: versus_baseline(config, k, groups_of(runs, k), groups_of(base_runs, k),
                               confidence) for k in group_keys(layout)}
        entry["group_intervals"] = {  # each group against holding, uncorrected 95 % per cell
            k: intervals.mean_interval(groups_of(runs, k), intervals.CONFIDENCE,
                                       episodes=episodes, episode_variance=(
                intervals.episode_variance(replicates(config, k), episodes)
                if replicates(config, k) is not None else 0.0)) for k in group_keys(layout)}
        entry["groups_resampled"] = all(replicates(c, k) is not None for c in (config, baseline)
                                        for k in group_keys(layout))
        entry["vs_baseline"].update(closed_loop_comparisons(runs, base_runs, confidence))
        entry["targets"] = meets_targets(entry, per_config[baseline], layout, targets, ceiling)
        trained = next((r["trained"] for r in runs if r.get("trained")), None)
        if trained in per_config:
            entry["trained"] = trained
            entry["vs_trained"] = lever_comparisons(
                runs, [r for r in results if r["config"] == trained], layout, confidence)
    reference = results[0]["metrics"]
    do_nothing = {name: {k[len(name) + 1:]: v for k, v in reference.items()
                         if k.startswith(name + "/")} for name in baselines_lib.BASELINES}
    seeds = min(len(c["seeds"]) for c in per_config.values())
    return {"baseline": baseline, "primary": primary, "configs": per_config,
            "groups": list(layout.group_names), "arm_groups": list(arm_groups(layout)),
            "do_nothing": {name: {**m, **run_summary(m, layout)} for name, m in do_nothing.items()
                           if m},
            "ceiling": dict(ceiling) if ceiling else None,
            "min_seeds": seeds, "anecdotal": seeds < intervals.MIN_SEEDS,
            "episode_resampling": resampled, "targets": dataclasses.asdict(targets)}


def closed_loop_comparisons(runs: Sequence[Mapping[str, Any]],
                            base_runs: Sequence[Mapping[str, Any]], confidence: float
                            ) -> dict[str, tuple[float, float, float]]:
    """A config's closed-loop rates minus the baseline's (Welch t interval over seeds), widened
    by the world episodes' sampling error where every run kept its per-episode outcomes on the
    same number of episodes (the episodes are a sample too, the same for every run)."""
    out = {}
    both = list(runs) + list(base_runs)
    found = [r.get(CLOSED_LOOP_EPISODES) for r in both]
    episodes = (len(found[0]["success/task"])
                if all(found) and len({len(f["success/task"]) for f in found}) == 1 else 0)
    for key in (*CLOSED_LOOP_COMPARED, *CURVE_COMPARED):
        if not all(CLOSED_LOOP + key in r["metrics"] for r in both):
            continue
        if key in CURVE_COMPARED and not all(has_outcomes(r, key) for r in both):
            continue
        variance = 0.0
        if episodes:
            variance = intervals.episode_variance(
                [closed_loop_replicates(r[CLOSED_LOOP_EPISODES], key) for r in runs], episodes,
                [closed_loop_replicates(r[CLOSED_LOOP_EPISODES], key) for r in base_runs])
        out[CLOSED_LOOP + key] = intervals.welch_interval(
            [r["metrics"][CLOSED_LOOP + key] for r in runs],
            [r["metrics"][CLOSED_LOOP + key] for r in base_runs], confidence,
            episodes=episodes, episode_variance=variance)
    return out


def lever_comparisons(runs: Sequence[Mapping[str, Any]],
                      trained_runs: Sequence[Mapping[str, Any]], layout: ActionLayout,
                      confidence: float = intervals.CONFIDENCE
                      ) -> dict[str, tuple[float, float, float]]:
    """A lever variant minus its trained config, paired seed for seed (the same checkpoints,
    sampled two ways): the t interval of the mean per-seed difference of each headline number
    (`COMPARED`) and closed-loop rate (`CLOSED_LOOP_COMPARED`), widened by the held-out (world)
    episodes' sampling error of that difference where both sides kept their per-episode
    numbers (the same resamples on both sides, so what the two share cancels)."""
    by_seed = {r["seed"]: r for r in trained_runs}
    pairs = [(r, by_seed[r["seed"]]) for r in runs if r["seed"] in by_seed]
    summaries = {id(r): run_summary(r["metrics"], layout) for pair in pairs for r in pair}
    out = {}
    for key in COMPARED:
        out[key] = _paired(pairs, lambda r: summaries[id(r)][key],
                           lambda r: _held_out_replicates(r, key), confidence)
    for key in (*CLOSED_LOOP_COMPARED, *CURVE_COMPARED):
        if key in CURVE_COMPARED and not all(has_outcomes(r, key) for p in pairs for r in p):
            continue
        if all(CLOSED_LOOP + key in r["metrics"] for pair in pairs for r in pair):
            out[CLOSED_LOOP + key] = _paired(
                pairs, lambda r: as_number(r["metrics"][CLOSED_LOOP + key]),
                lambda r: _world_replicates(r, key), confidence)
    return out


def _held_out_replicates(run: Mapping[str, Any], key: str) -> tuple[np.ndarray, int] | None:
    """`([B] values, episodes)`: a run's headline number `key` on the held-out resamples."""
    kept = run.get(EPISODE_REPLICATES)
    if not kept:
        return None
    return np.asarray([as_number(v) for v in kept[key]]), int(kept["episodes"])


def _world_replicates(run: Mapping[str, Any], key: str) -> tuple[np.ndarray, int] | None:
    """`([B] values, episodes)`: a run's closed-loop rate `key` on the world's resamples."""
    kept = run.get(CLOSED_LOOP_EPISODES)
    if not kept:
        return None
    return closed_loop_replicates(kept, key), len(kept["success/task"])


def _paired(pairs, value, replicates, confidence: float) -> tuple[float, float, float]:
    """The interval of the mean per-seed difference `value(a) - value(b)` over `pairs`, widened
    by the episodes' sampling variance of the difference when every run has `replicates`
    on the same number of episodes."""
    diffs = [value(a) - value(b) for a, b in pairs]
    kept = [(replicates(a), replicates(b)) for a, b in pairs]
    if not kept or any(a is None or b is None or a[1] != b[1] or a[1] != kept[0][0][1]
                       for a, b in kept):
        return intervals.mean_interval(diffs, confidence)
    episodes = kept[0][0][1]
    variance = intervals.episode_variance([a[0] - b[0] for a, b in kept], episodes)
    return intervals.mean_interval(diffs, confidence, episodes=episodes,
                                   episode_variance=variance)


def _episode_resamples(results: Sequence[Mapping[str, Any]]) -> dict[str, int] | None:
    """`{"episodes", "replicates"}` when every run has its `episode_replicates` on the same
    number of held-out episodes (the same resamples), else None."""
    found = [r.get(EPISODE_REPLICATES) for r in results]
    if not all(found) or len({f["episodes"] for f in found}) != 1:
        return None
    return {"episodes": found[0]["episodes"], "replicates": len(found[0][COMPARED[0]])}


def meets_targets(entry: Mapping[str, Any], baseline: Mapping[str, Any], layout: ActionLayout,
                  targets: Targets, ceiling: Mapping[str, float] | None
                  ) -> dict[str, bool | None]:
    """Which of `Targets` a config meets (means over seeds; the arm skill by its interval);
    None for a target of a group the layout does not have."""
    mean = entry["mean"]
    _, low, _ = entry["arm_skill_interval"]
    gains = []
    for g in arm_groups(layout):
        bar = targets.arm_gain
        top = (ceiling or {}).get(f"motion_gain/{g}")
        if top is not None and top < targets.ceiling_below:
            bar = targets.ceiling_share * top
        gains.append(mean.get(f"motion_gain/{g}") is not None
                     and mean[f"motion_gain/{g}"] >= bar)
    base, own = baseline["mean"].get("base_skill"), mean.get("base_skill")
    # A target of a group the robot does not have (a G1: no base, hands for grippers) is None.
    met = {
        "arm_skill": bool(np.isfinite(low) and low > 0),
        "arm_gain": bool(gains) and all(gains),
        "base_skill": (bool(base is not None and own is not None
                            and own >= base - targets.base_skill_drop * abs(base))
                       if layout.groups_with_role("base") else None),
        "switch_f1": (bool(mean.get("switch_f1") is not None
                           and mean["switch_f1"] >= targets.switch_f1)
                      if layout.groups_with_role("gripper") else None),
    }
    manipulation = entry["vs_baseline"].get(f"{CLOSED_LOOP}phase_success/manipulation")
    navigation = entry["vs_baseline"].get(f"{CLOSED_LOOP}phase_success/navigation")
    if manipulation is not None and navigation is not None:
        precision = mean.get("gripper_switch/precision")
        met |= {
            "closed_loop_manipulation": bool(manipulation[0] >= targets.manipulation_gain
                                             and np.isfinite(manipulation[1])
                                             and manipulation[1] > 0),
            "closed_loop_navigation": bool(navigation[0] >= -targets.navigation_drop),
            "switch_precision": bool(precision is not None
                                     and precision >= targets.switch_precision),
        }
    return met


def nanmean(v: np.ndarray) -> float | None:
    """The mean of `[N]` values' finite entries; None when none is finite."""
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else None


def nanstd(v: np.ndarray) -> float | None:
    """The sample std (ddof 1) of `[N]` values' finite entries, as every study table gives it; 0
    for one finite value, None for none."""
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if len(v) > 1 else (0.0 if len(v) else None)
