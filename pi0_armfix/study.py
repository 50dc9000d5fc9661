"""Every config x every seed -> tables with intervals over seeds, every number beside doing
nothing: which lever fixes the arms, and by how much? (docs/evaluation.md)

    python -m pi0_armfix.study --configs=uniform,arm_focused,arm_delta [--seeds=5] \
        [--primary=arm_focused] [--steps=1500] [--workdir=runs/study] [--parallel=1] \
        [--override=data.root=/data/b1k] [--closed_loop_episodes=50]

Each (config, seed) trains in its own run folder `<workdir>/<config>/seed_<s>` through
`python -m pi0_armfix.train` (`--config.seed=s`, `--config.train.total_steps=steps`, one
held-out evaluation at the end), its console output in `train.log` there. A run whose
`result.json` exists is finished and skipped; an interrupted one resumes from its checkpoints, so
rerunning the same command finishes a study (seed-major: an interrupted study has every config's
first seeds). The results of all finished runs are gathered into:

  study.md    per group: skill over persistence, motion gain and ratio, error, each with the
              do-nothing rows (and the ceiling on the demo); gripper switch precision / recall /
              F1 with the event counts; each config's difference to the first config (the
              baseline) with a Welch t interval over seeds widened by the held-out episodes'
              sampling error (`study_stats`), and the targets.
  study.json  every run's metrics, the per-seed headline values and every aggregate.
  study.png   per-group skill and motion gain, mean with the seeds' spread as error bars, the
              do-nothing predictors as markers.

Closed loop (`--closed_loop_episodes=N`, default 50; 0 = off): every run's final checkpoint also
drives the demo world (`python -m pi0_armfix.evaluate --closed_loop --episodes=N`, the same N
episodes for every run), and study.md / study.png add the success of navigation, manipulation and
the whole task (episodes whose every phase of that kind succeeded), mean ± std over seeds, with
the difference to the baseline. A finished run without them gets them on the next call.

A config is a file name of `configs/` (`arm_focused`, optionally `arm_focused:b1k`); every
`--override` is passed to every run as `--config.<key>=<value>`. Metrics are those of
`pi0_armfix.evaluate` (evaluation units: absolute actions over the training split's std, so
configs with other normalizations or delta actions compare).

The held-out episodes' sampling error: every run's evaluation keeps its per-chunk sums
(`eval/step_<N>/chunk_sums.npz`); the study recomputes the run's headline numbers on resamples of
the held-out episodes (the same resamples for every run) and keeps them in `result.json`
(`episode_replicates`). A finished run without the sums is evaluated again from its checkpoint
(`pi0_armfix.evaluate`); one kept without either leaves the intervals to the seeds alone, and
study.md says so.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import json
import math
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from absl import app, flags  # noqa: E402
from tqdm import tqdm  # noqa: E402

from pi0_armfix import console, evaluate, inference, study_stats  # noqa: E402
from pi0_armfix.action_space import ActionLayout  # noqa: E402
from pi0_armfix.evaluation import baselines as baselines_lib  # noqa: E402
from pi0_armfix.evaluation import heldout as heldout_lib  # noqa: E402
from pi0_armfix.evaluation import metrics as eval_metrics  # noqa: E402
from pi0_armfix.data import stats as stats_lib  # noqa: E402
from pi0_armfix.sim.world import FAILURE_REASONS  # noqa: E402
from pi0_armfix.training import metrics as metrics_lib  # noqa: E402

RESULT_FILE = "result.json"
SWITCH_METRICS = ("precision", "recall", "f1")
SWITCH_COUNTS = ("tp", "fp", "fn")
CLOSED_LOOP = "closed_loop/"  # prefix of the closed-loop metrics of a run
CLOSED_LOOP_KINDS = ("navigation", "manipulation", "task")
EPISODE_REPLICATES = "episode_replicates"  # result.json: headline numbers per episode resample


@dataclasses.dataclass(frozen=True)
class Targets:
    """The bar for a config that fixes stagnation (reported, never tuned to)."""

    arm_gain: float = 0.5  # each arm's mean held-out motion gain over seeds ...
    ceiling_share: float = 0.7  # ... or this share of the ceiling's gain ...
    ceiling_below: float = 0.7  # ... where the ceiling's gain is below this
    base_skill_drop: float = 0.10  # base skill at most 10 % below the baseline config's
    switch_f1: float = 0.6


# ---------------------------------------------------------------------- running


def run_folder(workdir: Path, config: str, seed: int) -> Path:
    return workdir / config.replace(":", "_") / f"seed_{seed}"


def train_command(config: str, seed: int, steps: int, folder: Path,
                  overrides: Sequence[str]) -> list[str]:
    """The `pi0_armfix.train` command line of one run."""
    name, colon, arg = config.partition(":")
    return [sys.executable, "-m", "pi0_armfix.train", f"--config=configs/{name}.py{colon}{arg}",
            f"--workdir={folder}", f"--config.seed={seed}",
            f"--config.train.total_steps={steps}", f"--config.eval.every={steps}",
            *[f"--config.{o}" for o in overrides]]


def final_evaluation(folder: Path) -> dict[str, float]:
    """The last held-out evaluation record of a run's `metrics.jsonl`."""
    records = [r for r in metrics_lib.read_metrics(folder / metrics_lib.METRICS_FILE)
               if any(k.startswith("motion_gain/") for k in r)]
    if not records:
        raise ValueError(f"{folder} has no held-out evaluation in {metrics_lib.METRICS_FILE}; "
                         f"see {folder / 'train.log'}")
    return records[-1]


class StudyInterrupted(Exception):
    """The study was asked to stop (SIGINT or SIGTERM)."""


class Children:
    """The study's child processes (training, evaluation), each in its own process group so that
    a Ctrl-C reaches the study alone, which then stops them (SIGTERM: a training run saves a
    checkpoint and exits) and starts no other: nothing is left running, nothing is lost."""

    def __init__(self):
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self.stopping = threading.Event()

    def run(self, command: list[str], log) -> int:
        with self._lock:
            if self.stopping.is_set():
                raise StudyInterrupted()
            child = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                     env=os.environ, start_new_session=True)
            self._running.add(child)
        try:
            code = child.wait()
        finally:
            with self._lock:
                self._running.discard(child)
        if self.stopping.is_set():
            raise StudyInterrupted()
        return code

    def stop(self, *_) -> None:
        """Starts no more children and sends SIGTERM to the running ones' process groups."""
        with self._lock:
            self.stopping.set()
            for child in self._running:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(child.pid, signal.SIGTERM)


CHILDREN = Children()


def _logged(command: list[str], folder: Path, what: str) -> None:
    """Runs `command`, its output appended to the run's `train.log`; raises on failure
    (`StudyInterrupted` when the study is stopping)."""
    with open(folder / "train.log", "a") as log:
        returncode = CHILDREN.run(command, log)
    if returncode:
        tail = (folder / "train.log").read_text().splitlines()[-5:]
        raise RuntimeError(f"{what} failed (exit {done.returncode}); the end of "
                           f"{folder / 'train.log'}:\n" + "\n".join(tail))


def closed_loop_metrics(folder: Path, steps: int, episodes: int) -> dict[str, float]:
    """Runs the closed-loop evaluation of a run's step `steps` (`pi0_armfix.evaluate
    --closed_loop`) and returns its rates as `closed_loop/<name>` metrics."""
    _logged([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={folder}",
             f"--step={steps}", "--closed_loop", f"--episodes={episodes}"], folder,
            f"the closed-loop evaluation of {folder}")
    path, _ = evaluate.closed_loop_paths(folder, steps, episodes=episodes)
    saved = json.loads(path.read_text())
    return {CLOSED_LOOP + k: v for k, v in saved.items()
            if k.startswith(("success/", "phase_success/", "progress/", "failure/",
                             "gripper_switches/", "seconds_to"))
            or k == "episodes"}


def episode_replicates(sums: Mapping[str, np.ndarray], layout: ActionLayout
                       ) -> dict[str, Any]:
    """A run's headline numbers (`COMPARED`) on each of the study's resamples of its held-out
    episodes (`study_stats.episode_counts`), from its per-chunk sums (`HeldOutChunks.score`):
    `{"episodes": E, <name>: [B] values}`."""
    _, episode = np.unique(sums[heldout_lib.EPISODE], return_inverse=True)
    num_episodes = int(episode.max()) + 1
    onehot = np.zeros((len(episode), num_episodes))
    onehot[np.arange(len(episode)), episode] = 1.0
    counts = study_stats.episode_counts(num_episodes)
    totals = {k: counts @ (np.asarray(v, np.float64) @ onehot) for k, v in sums.items()
              if k != heldout_lib.EPISODE}  # [B] each

    def part(prefix, b):
        return {k[len(prefix):]: v[b] for k, v in totals.items() if k.startswith(prefix)}

    replicates = {k: [] for k in COMPARED}
    for b in range(len(counts)):
        metrics = eval_metrics.metrics_from_sums(part("policy/", b), layout)
        persistence = eval_metrics.metrics_from_sums(part("persistence/", b), layout)
        metrics.update(eval_metrics.skill_scores(metrics, persistence, layout))
        for k, v in run_summary(metrics, layout).items():
            if k in replicates:
                replicates[k].append(v if math.isfinite(v) else None)
    return {"episodes": num_episodes, **replicates}


def add_episode_replicates(result: dict[str, Any], folder: Path, evaluate_missing: bool
                           ) -> dict[str, Any]:
    """The result with its `episode_replicates` (`result.json` rewritten), from the run's
    per-chunk sums; a run without them is evaluated again from its checkpoint when
    `evaluate_missing`, else (or without a checkpoint) returned as it is."""
    if EPISODE_REPLICATES in result:
        return result
    path = folder / "eval" / f"step_{result['steps']}" / heldout_lib.CHUNK_SUMS_FILE
    if not path.exists():
        if not evaluate_missing or not (folder / "checkpoints").is_dir():
            return result
        _logged([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={folder}",
                 f"--step={result['steps']}"], folder, f"the held-out evaluation of {folder}")
    layout = ActionLayout.from_config(result["layout"])
    result = {**result, EPISODE_REPLICATES: episode_replicates(
        heldout_lib.load_chunk_sums(path), layout)}
    stats_lib.write_json_atomic(folder / RESULT_FILE, result)
    return result


def run_one(config: str, seed: int, steps: int, workdir: Path, overrides: Sequence[str],
            closed_loop_episodes: int = 0) -> dict[str, Any]:
    """Trains (or resumes) one run, evaluates it in closed loop when asked, and writes its
    `result.json`; returns the result."""
    folder = run_folder(workdir, config, seed)
    folder.mkdir(parents=True, exist_ok=True)
    _logged(train_command(config, seed, steps, folder, overrides), folder,
            f"{config} seed {seed}")
    evaluation = final_evaluation(folder)
    if evaluation["step"] != steps:
        raise RuntimeError(f"{folder}: the last evaluation is of step {evaluation['step']}, "
                           f"not {steps}")
    layout = json.loads((folder / "config.json").read_text())["layout"]
    result = {"config": config, "seed": seed, "steps": steps, "layout": layout,
              "metrics": {k: v for k, v in evaluation.items() if k != "step"}}
    stats_lib.write_json_atomic(folder / RESULT_FILE, result)
    result = add_episode_replicates(result, folder, evaluate_missing=True)
    return add_closed_loop(result, folder, closed_loop_episodes)


def add_closed_loop(result: dict[str, Any], folder: Path, episodes: int) -> dict[str, Any]:
    """The result with the closed-loop metrics of `episodes` episodes (measured now when it has
    none of that many; `result.json` rewritten)."""
    if episodes <= 0 or result["metrics"].get(CLOSED_LOOP + "episodes") == episodes:
        return result
    result = {**result, "metrics": {
        **{k: v for k, v in result["metrics"].items() if not k.startswith(CLOSED_LOOP)},
        **closed_loop_metrics(folder, result["steps"], episodes)}}
    stats_lib.write_json_atomic(folder / RESULT_FILE, result)
    return result


def load_result(folder: Path) -> dict[str, Any] | None:
    path = folder / RESULT_FILE
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not JSON ({e}): delete it and rerun the study to evaluate "
                         "that run again") from None


def run_study(configs: Sequence[str], seeds: Sequence[int], steps: int, workdir: Path,
              overrides: Sequence[str] = (), parallel: int = 1, closed_loop_episodes: int = 0,
              train: bool = True) -> list[dict[str, Any]]:
    """Every (config, seed) run, the finished ones read back (and evaluated in closed loop when
    they were not), the others trained; with `train=False`, only the finished ones (a partial
    study's tables, labelled by their seed counts)."""
    results, todo = {}, []
    for seed in seeds:  # seed-major: an interrupted study has every config's first seeds
        for config in configs:
            result = load_result(run_folder(workdir, config, seed))
            if result is not None and result["steps"] == steps:
                folder = run_folder(workdir, config, seed)
                result = add_episode_replicates(result, folder, evaluate_missing=train)
                results[config, seed] = add_closed_loop(result, folder,
                                                        closed_loop_episodes if train else 0)
            elif result is not None:
                raise ValueError(f"{run_folder(workdir, config, seed)} finished {result['steps']} "
                                 f"steps, not --steps={steps}: use another --workdir")
            else:
                todo.append((config, seed))
    if not train:
        if not results:
            raise ValueError(f"{workdir} has no finished run of {list(configs)}")
        print(f"study: reporting the {len(results)} finished runs of {len(results) + len(todo)}",
              flush=True)
        return [results[c, s] for c in configs for s in seeds if (c, s) in results]
    if todo:
        print(f"study: {len(results)} of {len(results) + len(todo)} runs finished; training "
              f"{len(todo)} ({parallel} at a time), logs in {workdir}/<config>/seed_<s>/train.log",
              flush=True)
    with concurrent.futures.ThreadPoolExecutor(max_workers=parallel) as pool:
        futures = {pool.submit(run_one, c, s, steps, workdir, overrides, closed_loop_episodes):
                   (c, s) for c, s in todo}
        try:
            for future in tqdm(concurrent.futures.as_completed(futures), total=len(futures),
                               desc="study runs", unit="run"):
                results[futures[future]] = future.result()
        except StudyInterrupted:
            pool.shutdown(wait=True, cancel_futures=True)
            finished = sum(load_result(run_folder(workdir, c, s)) is not None
                           for c in configs for s in seeds)
            raise StudyInterrupted(f"{finished} of {len(configs) * len(seeds)} runs finished"
                                   ) from None
    return [results[c, s] for c in configs for s in seeds]


# ---------------------------------------------------------------------- aggregation


def arm_groups(layout: ActionLayout) -> tuple[str, ...]:
    return layout.groups_with_role("arm")


def run_summary(metrics: Mapping[str, Any], layout: ActionLayout, prefix: str = ""
                ) -> dict[str, float]:
    """The headline numbers of one run (or, with `prefix` "persistence/" or "state_copy/", of a
    do-nothing predictor scored beside it): the arms' mean skill over persistence and motion
    gain, the base's skill and error, gripper switch F1."""
    arms = arm_groups(layout)
    base = layout.groups_with_role("base")

    def get(key):
        return _number(metrics.get(prefix + key))

    def arms_mean(name):
        return float(np.mean([get(f"{name}/{g}") for g in arms])) if arms else math.nan

    return {"arm_skill": arms_mean("skill"), "arm_gain": arms_mean("motion_gain"),
            "base_skill": get(f"skill/{base[0]}") if base else math.nan,
            "base_err": get(f"err/{base[0]}") if base else math.nan,
            "switch_f1": get("gripper_switch/f1")}


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


COMPARED = ("arm_skill", "arm_gain", "base_skill", "switch_f1")  # vs the baseline config
GROUP_TABLES = (  # study.md's per-group tables: (metric, heading, digits)
    ("skill", "Skill over persistence (1 - err / persistence err; > 0: better than holding the "
     "previous action, 1: perfect)", 3),
    ("motion_gain", "Motion gain (1 = moves like the data, 0 = still, or moving in unrelated "
     "directions)", 3),
    ("motion_ratio", "Motion ratio (magnitude only: 1 = moves as much as the data, in any "
     "direction)", 3),
    ("err", "Error (MSE of the sampled chunk)", 4),
)


def aggregate(results: Sequence[Mapping[str, Any]], targets: Targets = Targets(),
              primary: str | None = None, ceiling: Mapping[str, float] | None = None
              ) -> dict[str, Any]:
    """Mean and std over seeds of every metric per config, the headline numbers with their
    per-seed values, each config's difference to the first config (the baseline) with Welch t
    intervals (95 % for the `primary` config, Bonferroni-corrected for the others), the
    do-nothing rows, and the targets each config meets. `ceiling`: metrics of a perfect sampler
    on the same chunks (`evaluation.ceiling`), where known."""
    configs = list(dict.fromkeys(r["config"] for r in results))
    layout = ActionLayout.from_config(results[0]["layout"])
    baseline = configs[0]
    if primary is None:
        primary = configs[1] if len(configs) > 1 else baseline
    if primary not in configs:
        raise ValueError(f"--primary={primary!r} is not one of the study's configs {configs}")
    secondary = [c for c in configs if c not in (baseline, primary)]
    resampled = _episode_resamples(results)
    episodes = resampled["episodes"] if resampled else 0

    def replicates(config: str, key: str) -> np.ndarray | None:
        if not resampled:
            return None
        return np.asarray([[math.nan if v is None else v
                            for v in r[EPISODE_REPLICATES][key]]
                           for r in results if r["config"] == config], np.float64)

    per_config: dict[str, Any] = {}
    for config in configs:
        runs = [r for r in results if r["config"] == config]
        names = sorted({k for r in runs for k in r["metrics"]
                        if isinstance(r["metrics"][k], (int, float)) or r["metrics"][k] is None})
        values = {k: np.asarray([_number(r["metrics"].get(k)) for r in runs]) for k in names}
        summary = [run_summary(r["metrics"], layout) for r in runs]
        headline = {k: np.asarray([s[k] for s in summary]) for k in summary[0]}
        per_config[config] = {
            "seeds": [r["seed"] for r in runs],
            "mean": {k: _nanmean(v) for k, v in {**values, **headline}.items()},
            "std": {k: _nanstd(v) for k, v in {**values, **headline}.items()},
            "headline": {k: v.tolist() for k, v in headline.items()},
            "arm_skill_interval": study_stats.mean_interval(
                headline["arm_skill"], episodes=episodes, episode_variance=(
                    study_stats.episode_variance(replicates(config, "arm_skill"), episodes)
                    if resampled else 0.0)),
        }
    base_values = per_config[baseline]["headline"]
    base_runs = [r for r in results if r["config"] == baseline]
    for config in configs:
        entry = per_config[config]
        confidence = study_stats.comparison_confidence(config in (primary, baseline),
                                                       len(secondary))
        entry["comparison"] = ("baseline" if config == baseline else
                               "primary" if config == primary else "secondary")
        entry["confidence"] = confidence
        entry["vs_baseline"] = {k: study_stats.welch_interval(
            entry["headline"][k], base_values[k], confidence, episodes=episodes,
            episode_variance=(study_stats.episode_variance(
                replicates(config, k), episodes, replicates(baseline, k))
                if resampled and config != baseline else 0.0))
            for k in COMPARED}
        runs = [r for r in results if r["config"] == config]
        for kind in CLOSED_LOOP_KINDS:
            key = f"{CLOSED_LOOP}success/{kind}"
            if all(key in r["metrics"] for r in runs + base_runs):
                entry["vs_baseline"][key] = study_stats.welch_interval(
                    [r["metrics"][key] for r in runs], [r["metrics"][key] for r in base_runs],
                    confidence)
        entry["targets"] = meets_targets(entry, per_config[baseline], layout, targets, ceiling)
    reference = results[0]["metrics"]
    do_nothing = {name: {k[len(name) + 1:]: v for k, v in reference.items()
                         if k.startswith(name + "/")} for name in baselines_lib.BASELINES}
    seeds = min(len(c["seeds"]) for c in per_config.values())
    return {"baseline": baseline, "primary": primary, "configs": per_config,
            "groups": list(layout.group_names), "arm_groups": list(arm_groups(layout)),
            "do_nothing": {name: {**m, **run_summary(m, layout)} for name, m in do_nothing.items()
                           if m},
            "ceiling": dict(ceiling) if ceiling else None,
            "min_seeds": seeds, "anecdotal": seeds < study_stats.MIN_SEEDS,
            "episode_resampling": resampled, "targets": dataclasses.asdict(targets)}


def _episode_resamples(results: Sequence[Mapping[str, Any]]) -> dict[str, int] | None:
    """`{"episodes", "replicates"}` when every run has its `episode_replicates` on the same
    number of held-out episodes (the same resamples), else None."""
    found = [r.get(EPISODE_REPLICATES) for r in results]
    if not all(found) or len({f["episodes"] for f in found}) != 1:
        return None
    return {"episodes": found[0]["episodes"], "replicates": len(found[0][COMPARED[0]])}


def meets_targets(entry: Mapping[str, Any], baseline: Mapping[str, Any], layout: ActionLayout,
                  targets: Targets, ceiling: Mapping[str, float] | None) -> dict[str, bool]:
    """Which of `Targets` a config meets (means over seeds; the arm skill by its interval)."""
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
    return {
        "arm_skill": bool(np.isfinite(low) and low > 0),
        "arm_gain": bool(gains) and all(gains),
        "base_skill": bool(base is not None and own is not None
                           and own >= base - targets.base_skill_drop * abs(base)),
        "switch_f1": bool(mean.get("switch_f1") is not None
                          and mean["switch_f1"] >= targets.switch_f1),
    }


def _nanmean(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else None


def _nanstd(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if len(v) > 1 else (0.0 if len(v) else None)


# ---------------------------------------------------------------------- reports


def _cell(summary: Mapping[str, Any], key: str, digits: int = 3) -> str:
    mean, std = summary["mean"].get(key), summary["std"].get(key)
    if mean is None:
        return "n/a"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def _value(metrics: Mapping[str, Any] | None, key: str, digits: int = 3) -> str:
    value = None if metrics is None else metrics.get(key)
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _interval(d: Sequence[float]) -> str:
    """`+0.123 [+0.010, +0.200]`."""
    if not np.isfinite(d[0]):
        return "n/a"
    if not np.isfinite(d[1]):
        return f"{d[0]:+.3f} [n/a: 1 seed]"
    return f"{d[0]:+.3f} [{d[1]:+.3f}, {d[2]:+.3f}]"


def _reference_rows(study: Mapping[str, Any], key_of_group, digits: int = 3) -> list[str]:
    """The do-nothing rows (and the ceiling, where known) of a per-group table, in italics."""
    rows = []
    named = [(f"*{name.replace('_', ' ')} (do nothing)*", m)
             for name, m in study["do_nothing"].items()]
    if study.get("ceiling"):
        named.append(("*ceiling: the expert re-run (perfect sampler)*", study["ceiling"]))
    for label, m in named:
        cells = [_value(m, key_of_group(g), digits) for g in study["groups"]]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return rows


def markdown(study: Mapping[str, Any], *, steps: int, command: str) -> str:
    """`study.md`: the tables of `aggregate`, every one with the do-nothing rows."""
    groups, configs = study["groups"], study["configs"]
    seeds = study["min_seeds"]
    targets = study["targets"]
    header = "| config | " + " | ".join(groups) + " |"
    rule = "|---" * (len(groups) + 1) + "|"
    lines = [f"# Study: {len(configs)} configs x {seeds} seeds, {steps} steps", "",
             f"`{command}`", ""]
    if study["anecdotal"]:
        lines += [f"**{seeds} seed(s) per config, fewer than {study_stats.MIN_SEEDS}: the "
                  "intervals below are anecdotes, not results.**", ""]
    lines += ["Held-out chunks sampled by the policy, mean ± std over seeds, every seed on the "
              "same chunks (evaluation units: absolute actions over each dim's training std). "
              "Rows in italics are the do-nothing predictors on the same chunks: *persistence* "
              "holds the previous action, *state copy* repeats the current state where it maps "
              "to the actions (see docs/evaluation.md).", ""]
    for metric, title, digits in GROUP_TABLES:
        lines += [f"## {title}", "", header, rule]
        lines += [f"| {name} | " + " | ".join(_cell(c, f"{metric}/{g}", digits) for g in groups)
                  + " |" for name, c in configs.items()]
        lines += _reference_rows(study, lambda g, m=metric: f"{m}/{g}", digits) + [""]
    lines = lines[:-1]
    lines += ["", "## Gripper switches (each event of the held-out timeline once, matched within "
              "the tolerance)", "",
              "| config | precision | recall | F1 | TP / FP / FN (mean over seeds) |",
              "|---|---|---|---|---|"]
    for name, c in configs.items():
        counts = " / ".join(_value(c["mean"], f"gripper_switch/{k}", 1) for k in SWITCH_COUNTS)
        lines.append(f"| {name} | " + " | ".join(_cell(c, f"gripper_switch/{k}")
                                                 for k in SWITCH_METRICS) + f" | {counts} |")
    for label, m in [(f"*{n.replace('_', ' ')} (do nothing)*", m)
                     for n, m in study["do_nothing"].items()]:
        counts = " / ".join(_value(m, f"gripper_switch/{k}", 0) for k in SWITCH_COUNTS)
        lines.append(f"| {label} | " + " | ".join(_value(m, f"gripper_switch/{k}")
                                                 for k in SWITCH_METRICS) + f" | {counts} |")
    resampled = study.get("episode_resampling")
    sampling = (f"the seeds' spread and the held-out episodes' sampling error ({resampled['episodes']}"
                f" episodes, {resampled['replicates']} bootstrap resamples shared by every run)"
                if resampled else "the seeds' spread only: some runs lack their per-chunk sums, "
                "so the interval speaks for these held-out episodes alone")
    lines += ["", f"## Against `{study['baseline']}` (difference of means over seeds, Welch t "
              "interval)", "",
              f"Primary comparison: `{study['primary']}` (95 % interval); the others are "
              "secondary, their intervals Bonferroni-corrected so that together they hold at "
              f"95 %. The intervals hold {sampling}. An interval that excludes 0 is a "
              "difference these seeds and episodes can tell.", "",
              "| config | comparison | arms' skill | arms' gain | base skill | switch F1 |",
              "|---|---|---|---|---|---|"]
    for name, c in configs.items():
        if c["comparison"] == "baseline":
            lines.append(f"| {name} | the baseline | " + " | ".join("—" for _ in COMPARED) + " |")
            continue
        vs = c["vs_baseline"]
        level = f"{c['comparison']} ({c['confidence']:.1%})"
        lines.append(f"| {name} | {level} | " + " | ".join(_interval(vs[k]) for k in COMPARED)
                     + " |")
    lines += ["", "## Targets", "",
              f"Arms' skill over persistence > 0 with its 95 % interval above 0; each arm's "
              f"motion gain >= {targets['arm_gain']} (or >= {targets['ceiling_share']:.0%} of the "
              f"ceiling where that is below {targets['ceiling_below']}); base skill at most "
              f"{targets['base_skill_drop']:.0%} below `{study['baseline']}`'s; gripper switch "
              f"F1 >= {targets['switch_f1']}.", "",
              "| config | arms' skill [95 %] | arm skill | arm gain | base skill | switch F1 |",
              "|---|---|---|---|---|---|"]
    for name, c in configs.items():
        met = c["targets"]
        lines.append(f"| {name} | {_interval(c['arm_skill_interval'])} | "
                     + " | ".join("met" if met[k] else "missed" for k in
                                  ("arm_skill", "arm_gain", "base_skill", "switch_f1")) + " |")
    if has_closed_loop(configs):
        lines += closed_loop_table(study)
    return "\n".join(lines) + "\n"


def has_closed_loop(configs: Mapping[str, Any]) -> bool:
    """Whether any config of an aggregate has closed-loop metrics."""
    return any(f"{CLOSED_LOOP}success/task" in c["mean"] for c in configs.values())


def closed_loop_table(study: Mapping[str, Any]) -> list[str]:
    """study.md's closed-loop section: success per kind, mean ± std over seeds, vs the baseline."""
    configs = study["configs"]
    episodes = {c["mean"].get(CLOSED_LOOP + "episodes") for c in configs.values()}
    lines = ["", "## Closed loop in the demo world (`pi0_armfix.sim`)", "",
             f"{', '.join(str(int(e)) for e in sorted(e for e in episodes if e))} episodes per "
             "seed (world seed 1000, never trained on); an episode succeeds at navigation "
             "(manipulation) when every navigation (manipulation) phase of its task does. Success "
             "rate, mean ± std over seeds; then the difference to the baseline [Welch t "
             "interval, as above]. "
             "Progress: how far a phase got, 1 - closest approach / start distance (base to "
             "target, hand to its target offset), mean over phases.", "",
             "| config | navigation | manipulation | task | navigation progress | manipulation "
             "progress | vs baseline: navigation | manipulation | task |", "|---" * 9 + "|"]
    for name, c in configs.items():
        vs = c["vs_baseline"]
        diffs = [_interval(vs[f"{CLOSED_LOOP}success/{k}"]) if f"{CLOSED_LOOP}success/{k}" in vs
                 else "n/a" for k in CLOSED_LOOP_KINDS]
        lines.append(f"| {name} | " + " | ".join(
            _cell(c, f"{CLOSED_LOOP}success/{k}") for k in CLOSED_LOOP_KINDS)
            + " | " + " | ".join(_cell(c, f"{CLOSED_LOOP}progress/{k}")
                                 for k in CLOSED_LOOP_KINDS[:2])
            + " | " + " | ".join(diffs) + " |")
    return lines + failure_table(configs)


def failure_table(configs: Mapping[str, Any]) -> list[str]:
    """Why the phases failed: per config, the fraction of its phases that failed for each reason
    (`sim.world.FAILURE_REASONS`, mean over seeds), and the gripper switches per phase."""
    reasons = [(kind, reason) for kind in CLOSED_LOOP_KINDS[:2]
               for reason in FAILURE_REASONS[kind]]
    if not any(f"{CLOSED_LOOP}failure/{k}/{r}" in c["mean"] for c in configs.values()
               for k, r in reasons):
        return []
    lines = ["", "Why phases failed: the fraction of a kind's phases that failed for each reason "
             "(the furthest stage the phase reached; see docs/evaluation.md), mean over seeds; "
             "gripper switches: open/close commands per phase.", "",
             "| config | " + " | ".join(f"{k[:3]}: {r}" for k, r in reasons)
             + " | switches per navigation phase | per manipulation phase |",
             "|---" * (len(reasons) + 3) + "|"]
    for name, c in configs.items():
        cells = [c["mean"].get(f"{CLOSED_LOOP}failure/{k}/{r}") for k, r in reasons]
        cells += [c["mean"].get(f"{CLOSED_LOOP}gripper_switches/{k}")
                  for k in CLOSED_LOOP_KINDS[:2]]
        lines.append(f"| {name} | " + " | ".join(
            "n/a" if v is None or not math.isfinite(v) else f"{v:.2f}" for v in cells) + " |")
    return lines


def plot_study(study: Mapping[str, Any], path: Path) -> None:
    """`study.png`: per group, each config's skill over persistence and motion gain (mean, std
    over seeds as error bars), the do-nothing predictors as black markers (and the ceiling, where
    known, as grey ones); closed-loop success beside them when the runs have it."""
    groups, configs = study["groups"], study["configs"]
    width = 0.8 / len(configs)
    closed = has_closed_loop(configs)
    panels = [("skill", "skill over persistence (> 0: better than doing nothing)"),
              ("motion_gain", "motion gain (1 = moves like the data)")]
    fig, axes = plt.subplots(1, len(panels) + closed, squeeze=False, gridspec_kw={
        "width_ratios": [len(groups)] * len(panels) + ([len(CLOSED_LOOP_KINDS)] if closed else [])},
        figsize=(2 * max(7, 1.4 * len(groups) + 0.25 * len(configs)) + (4 if closed else 0), 5))
    x = np.arange(len(groups))
    references = [(name, m, "k", marker) for (name, m), marker
                  in zip(study["do_nothing"].items(), ("_", "x"))]
    if study.get("ceiling"):
        references.append(("ceiling (expert re-run)", study["ceiling"], "gray", "*"))
    for ax, (metric, title) in zip(axes[0], panels):
        for i, (name, c) in enumerate(configs.items()):
            means = [c["mean"].get(f"{metric}/{g}") for g in groups]
            stds = [c["std"].get(f"{metric}/{g}") for g in groups]
            ax.bar(x + (i - (len(configs) - 1) / 2) * width,
                   [np.nan if m is None else m for m in means], width,
                   yerr=[0 if s is None else s for s in stds], capsize=2, label=name)
        for name, m, color, marker in references:
            ax.scatter(x, [_number(m.get(f"{metric}/{g}")) for g in groups], color=color,
                       marker=marker, s=160 if marker == "_" else 50, zorder=3, label=name)
        ax.axhline(0.0, color="black", lw=0.8)
        if metric == "motion_gain":
            ax.axhline(1.0, color="gray", lw=0.8)
        else:
            ax.set_ylim(max(ax.get_ylim()[0], -3.0), 1.1)  # skill is at most 1
        ax.set_xticks(x, groups, rotation=20)
        ax.set(title=title)
        ax.grid(axis="y", alpha=0.3)
    if closed:
        ax = axes[0, -1]
        x = np.arange(len(CLOSED_LOOP_KINDS))
        for i, (name, c) in enumerate(configs.items()):
            keys = [f"{CLOSED_LOOP}success/{k}" for k in CLOSED_LOOP_KINDS]
            ax.bar(x + (i - (len(configs) - 1) / 2) * width,
                   [np.nan if c["mean"].get(k) is None else c["mean"][k] for k in keys], width,
                   yerr=[c["std"].get(k) or 0 for k in keys], capsize=2, label=name)
        ax.set_xticks(x, CLOSED_LOOP_KINDS)
        ax.set(ylim=(0, 1.05), ylabel="success rate", title="closed loop (demo world)")
        ax.grid(axis="y", alpha=0.3)
    axes[0, -1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    seeds = study["min_seeds"]
    fig.suptitle(f"held-out evaluation, mean ± std over {seeds} seed(s) per config "
                 f"(baseline: {study['baseline']})"
                 + (" - fewer than 5 seeds: an anecdote" if study["anecdotal"] else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def ceiling_metrics(results: Sequence[Mapping[str, Any]], workdir: Path
                    ) -> dict[str, float] | None:
    """The ceiling's metrics (`evaluation.ceiling`, the embedded demo only): from the runs'
    `ceiling/...` metrics, or, for runs evaluated before the ceiling existed, measured on the
    first run's held-out chunks. None on other data, or without the first run's checkpoints."""
    prefix = heldout_lib.CEILING + "/"
    for result in results:
        found = {k[len(prefix):]: v for k, v in result["metrics"].items() if k.startswith(prefix)}
        if found:
            return found
    first = results[0]
    try:
        run = inference.restore_run(run_folder(workdir, first["config"], first["seed"]))
    except ValueError:  # results copied without their checkpoints: no ceiling to measure
        return None
    if run.config.data.root:
        return None
    groups = evaluate.eval_groups(run.config.eval, run.layout)
    chunks = heldout_lib.HeldOutChunks(
        run.config, run.layout, run.norm_stats, horizon=run.model_config.action_horizon,
        sums=functools.partial(eval_metrics.chunk_sums, layout=run.layout,
                                  gripper_groups=groups["gripper_groups"],
                                  switch_tolerance=run.config.eval.switch_tolerance))
    return chunks.reference[heldout_lib.CEILING]


def write_reports(results: Sequence[Mapping[str, Any]], workdir: Path, *, steps: int,
                  command: str, primary: str | None = None,
                  ceiling: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Writes `study.md`, `study.json` and `study.png` into `workdir`; returns the aggregate."""
    study = aggregate(results, primary=primary, ceiling=ceiling)
    (workdir / "study.md").write_text(markdown(study, steps=steps, command=command))
    stats_lib.write_json_atomic(workdir / "study.json",
                                {"command": command, "steps": steps, "runs": list(results),
                                 **study})
    plot_study(study, workdir / "study.png")
    return study


# ---------------------------------------------------------------------- entrypoint


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    configs = [c for c in FLAGS.configs if c]
    if not configs:
        raise SystemExit("pi0_armfix.study: --configs names no config")
    missing = [c for c in configs if not (_configs_dir() / f"{c.partition(':')[0]}.py").is_file()]
    if missing:
        raise SystemExit(f"pi0_armfix.study: --configs names {missing}, which are not files of "
                         f"{_configs_dir()}")
    if FLAGS.seeds < 1 or FLAGS.steps < 1 or FLAGS.parallel < 1:
        raise SystemExit("pi0_armfix.study: --seeds, --steps and --parallel must be >= 1")
    bad = [o for o in FLAGS.override if "=" not in o]
    if bad:
        raise SystemExit(f"pi0_armfix.study: --override {bad} must be key=value "
                         "(e.g. data.root=/data/b1k)")
    if FLAGS.primary and FLAGS.primary not in configs:
        raise SystemExit(f"pi0_armfix.study: --primary={FLAGS.primary} is not one of --configs "
                         f"{configs}")
    if FLAGS.seeds < study_stats.MIN_SEEDS:
        print(f"study: {FLAGS.seeds} seed(s) per config: the intervals will be anecdotes "
              f"(use --seeds={study_stats.MIN_SEEDS} or more for results)", flush=True)
    if FLAGS.closed_loop_episodes and not FLAGS.report_only:
        print(f"study: every run also drives {FLAGS.closed_loop_episodes} closed-loop episodes "
              "of the demo world once trained (more than half of a demo run's time; "
              "--closed_loop_episodes=0 skips them)", flush=True)
    workdir = Path(FLAGS.workdir).absolute()
    command = "python -m pi0_armfix.study " + " ".join(sys.argv[1:])
    # Ctrl-C or kill: stop the children (each in its own process group), start no other.
    signal.signal(signal.SIGINT, CHILDREN.stop)
    signal.signal(signal.SIGTERM, CHILDREN.stop)
    try:
        results = run_study(configs, list(range(FLAGS.seeds)), FLAGS.steps, workdir,
                            FLAGS.override, FLAGS.parallel, FLAGS.closed_loop_episodes,
                            train=not FLAGS.report_only)
    except StudyInterrupted as stopped:
        raise SystemExit(f"pi0_armfix.study: stopped; {stopped}. Rerun the same command to go "
                         "on: finished runs are kept, an interrupted one resumes from its last "
                         "checkpoint") from None
    except (RuntimeError, ValueError) as err:
        raise SystemExit(f"pi0_armfix.study: {err}") from None
    write_reports(results, workdir, steps=FLAGS.steps, command=command,
                  primary=FLAGS.primary or None, ceiling=ceiling_metrics(results, workdir))
    print((workdir / "study.md").read_text())
    print(f"study.md, study.json and study.png in {workdir}")


def _configs_dir() -> Path:
    import configs

    return Path(configs.__file__).parent


def cli() -> None:
    """The `pi0-armfix-study` console script (also `python -m pi0_armfix.study`)."""
    flags.DEFINE_list("configs", ["uniform", "arm_focused"],
                      "config names of configs/ (the first is the baseline)")
    flags.DEFINE_integer("seeds", study_stats.MIN_SEEDS, "seeds per config (0 .. seeds-1); "
                         f"fewer than {study_stats.MIN_SEEDS} give anecdotes, not intervals")
    flags.DEFINE_string("primary", "", "the config whose comparison with the baseline is the "
                        "study's question (95 % interval; the others are Bonferroni-corrected); "
                        "default: the second config")
    flags.DEFINE_integer("steps", 1500, "training steps of every run")
    flags.DEFINE_string("workdir", "runs/study", "study folder (one run folder per config/seed)")
    flags.DEFINE_integer("parallel", 1, "runs trained at the same time")
    flags.DEFINE_bool("report_only", False, "write the tables of the finished runs and train "
                      "nothing (a partial study, labelled with its seed counts)")
    flags.DEFINE_multi_string("override", [], "key=value passed to every run as --config.key")
    flags.DEFINE_integer("closed_loop_episodes", 50, "episodes of the demo world each run's "
                         "final checkpoint drives (0: no closed-loop evaluation)")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.study"))


if __name__ == "__main__":
    cli()
