"""Every config x every seed -> one table with the spread over seeds: which lever fixes the arms?

    python -m pi0_armfix.study --configs=uniform,arm_focused,arm_delta --seeds=3 \
        [--steps=1500] [--workdir=runs/study] [--parallel=1] [--override=data.root=/data/b1k] \
        [--closed_loop_episodes=50]

Each (config, seed) trains in its own run folder `<workdir>/<config>/seed_<s>` through
`python -m pi0_armfix.train` (`--config.seed=s`, `--config.train.total_steps=steps`, one
held-out evaluation at the end), its console output in `train.log` there. A run whose
`result.json` exists is finished and skipped; an interrupted one resumes from its checkpoints, so
rerunning the same command finishes a study. The results of all finished runs are gathered into:

  study.md    per group: held-out error and motion gain, gripper switch precision/recall/F1,
              mean ± std over seeds; then each config's difference to the first config (the
              baseline) with a 95 % bootstrap interval over seeds, and the targets it meets.
  study.json  every run's metrics and every aggregate.
  study.png   per-group motion gain, mean with the seeds' spread as error bars.

Closed loop (`--closed_loop_episodes=N`, default 50; 0 = off): every run's final checkpoint also
drives the demo world (`python -m pi0_armfix.evaluate --closed_loop --episodes=N`, the same N
episodes for every run), and study.md / study.png add the success of navigation, manipulation and
the whole task (episodes whose every phase of that kind succeeded), mean ± std over seeds, with
the difference to the baseline. A finished run without them gets them on the next call.

A config is a file name of `configs/` (`arm_focused`, optionally `arm_focused:b1k`); every
`--override` is passed to every run as `--config.<key>=<value>`. Metrics are those of
`pi0_armfix.evaluate` (evaluation units: absolute actions over the held-out std, so configs with
other normalizations or delta actions compare).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from absl import app, flags  # noqa: E402
from tqdm import tqdm  # noqa: E402

from pi0_armfix.action_space import ActionLayout  # noqa: E402
from pi0_armfix.data import stats as stats_lib  # noqa: E402
from pi0_armfix.training import metrics as metrics_lib  # noqa: E402

RESULT_FILE = "result.json"
BOOTSTRAP_RESAMPLES = 2000
SWITCH_METRICS = ("precision", "recall", "f1")
CLOSED_LOOP = "closed_loop/"  # prefix of the closed-loop metrics of a run
CLOSED_LOOP_KINDS = ("navigation", "manipulation", "task")


@dataclasses.dataclass(frozen=True)
class Targets:
    """The issue's bar for a config that fixes stagnation (reported, never tuned to)."""

    arm_gain: float = 0.5  # mean held-out motion gain of the arm groups, over seeds
    base_err_increase: float = 0.10  # base error at most +10 % over the baseline
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


def _logged(command: list[str], folder: Path, what: str) -> None:
    """Runs `command`, its output appended to the run's `train.log`; raises on failure."""
    with open(folder / "train.log", "a") as log:
        done = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, env=os.environ)
    if done.returncode:
        tail = (folder / "train.log").read_text().splitlines()[-5:]
        raise RuntimeError(f"{what} failed (exit {done.returncode}); the end of "
                           f"{folder / 'train.log'}:\n" + "\n".join(tail))


def closed_loop_metrics(folder: Path, steps: int, episodes: int) -> dict[str, float]:
    """Runs the closed-loop evaluation of a run's step `steps` (`pi0_armfix.evaluate
    --closed_loop`) and returns its rates as `closed_loop/<name>` metrics."""
    _logged([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={folder}",
             f"--step={steps}", "--closed_loop", f"--episodes={episodes}"], folder,
            f"the closed-loop evaluation of {folder}")
    saved = json.loads((folder / "eval" / f"step_{steps}" / "closed_loop.json").read_text())
    return {CLOSED_LOOP + k: v for k, v in saved.items()
            if k.startswith(("success/", "phase_success/", "progress/", "seconds_to"))
            or k == "episodes"}


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
    return json.loads(path.read_text()) if path.exists() else None


def run_study(configs: Sequence[str], seeds: Sequence[int], steps: int, workdir: Path,
              overrides: Sequence[str] = (), parallel: int = 1, closed_loop_episodes: int = 0
              ) -> list[dict[str, Any]]:
    """Every (config, seed) run, the finished ones read back (and evaluated in closed loop when
    they were not), the others trained."""
    results, todo = {}, []
    for seed in seeds:  # seed-major: an interrupted study has every config's first seeds
        for config in configs:
            result = load_result(run_folder(workdir, config, seed))
            if result is not None and result["steps"] == steps:
                results[config, seed] = add_closed_loop(
                    result, run_folder(workdir, config, seed), closed_loop_episodes)
            elif result is not None:
                raise ValueError(f"{run_folder(workdir, config, seed)} finished {result['steps']} "
                                 f"steps, not --steps={steps}: use another --workdir")
            else:
                todo.append((config, seed))
    if todo:
        print(f"study: {len(results)} of {len(results) + len(todo)} runs finished; training "
              f"{len(todo)} ({parallel} at a time), logs in {workdir}/<config>/seed_<s>/train.log",
              flush=True)
    with concurrent.futures.ThreadPoolExecutor(max_workers=parallel) as pool:
        futures = {pool.submit(run_one, c, s, steps, workdir, overrides, closed_loop_episodes):
                   (c, s) for c, s in todo}
        for future in tqdm(concurrent.futures.as_completed(futures), total=len(futures),
                           desc="study runs", unit="run"):
            results[futures[future]] = future.result()
    return [results[c, s] for c in configs for s in seeds]


# ---------------------------------------------------------------------- aggregation


def arm_groups(layout: ActionLayout) -> tuple[str, ...]:
    return layout.groups_with_role("arm")


def run_summary(metrics: Mapping[str, float], layout: ActionLayout) -> dict[str, float]:
    """The headline numbers of one run: the arms' mean motion gain, the base error, switch F1."""
    arms = arm_groups(layout)
    base = layout.groups_with_role("base")
    return {
        "arm_gain": float(np.mean([_number(metrics.get(f"motion_gain/{g}")) for g in arms]))
        if arms else float("nan"),
        "base_err": _number(metrics.get(f"err/{base[0]}")) if base else float("nan"),
        "switch_f1": _number(metrics.get("gripper_switch/f1")),
    }


def _number(value: Any) -> float:
    return float("nan") if value is None else float(value)


def bootstrap_interval(values: np.ndarray, baseline: np.ndarray, *, relative: bool = False,
                       seed: int = 0, resamples: int = BOOTSTRAP_RESAMPLES
                       ) -> tuple[float, float, float]:
    """Difference of means `mean(values) - mean(baseline)` (relative to the baseline's mean when
    `relative`) and its 95 % percentile bootstrap interval, seeds resampled with replacement
    within each config independently. Deterministic (`seed`)."""
    values, baseline = np.asarray(values, float), np.asarray(baseline, float)

    def diff(v, b):
        d = v.mean(-1) - b.mean(-1)
        return d / b.mean(-1) if relative else d

    rng = np.random.default_rng(seed)
    draws = diff(values[rng.integers(0, len(values), (resamples, len(values)))],
                 baseline[rng.integers(0, len(baseline), (resamples, len(baseline)))])
    low, high = np.percentile(draws, [2.5, 97.5])
    return float(diff(values, baseline)), float(low), float(high)


def aggregate(results: Sequence[Mapping[str, Any]], targets: Targets = Targets()
              ) -> dict[str, Any]:
    """Mean and std over seeds of every metric per config, the headline numbers, and each
    config's difference to the first config with bootstrap intervals."""
    configs = list(dict.fromkeys(r["config"] for r in results))
    layout = ActionLayout.from_config(results[0]["layout"])
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
        }
    baseline = configs[0]
    base_values = per_config[baseline]["headline"]
    for config in configs:
        entry = per_config[config]
        values = entry["headline"]
        entry["vs_baseline"] = {
            "arm_gain": bootstrap_interval(values["arm_gain"], base_values["arm_gain"]),
            "base_err": bootstrap_interval(values["base_err"], base_values["base_err"],
                                           relative=True),
            "switch_f1": bootstrap_interval(values["switch_f1"], base_values["switch_f1"]),
        }
        runs = [r for r in results if r["config"] == config]
        base_runs = [r for r in results if r["config"] == baseline]
        for kind in CLOSED_LOOP_KINDS:
            key = f"{CLOSED_LOOP}success/{kind}"
            if all(key in r["metrics"] for r in runs + base_runs):
                entry["vs_baseline"][key] = bootstrap_interval(
                    [r["metrics"][key] for r in runs], [r["metrics"][key] for r in base_runs])
        mean = entry["mean"]
        entry["targets"] = {
            "arm_gain": bool(mean["arm_gain"] >= targets.arm_gain),
            "base_err": bool(entry["vs_baseline"]["base_err"][0] <= targets.base_err_increase),
            "switch_f1": bool(mean["switch_f1"] >= targets.switch_f1),
        }
    return {"baseline": baseline, "configs": per_config, "groups": list(layout.group_names),
            "arm_groups": list(arm_groups(layout)), "targets": dataclasses.asdict(targets)}


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


def _interval(d: Sequence[float], percent: bool = False) -> str:
    """`+0.123 [+0.010, +0.200]` (a percentage for a relative difference)."""
    scale, unit, digits = (100.0, " %", 1) if percent else (1.0, "", 3)
    mean, low, high = (f"{v * scale:+.{digits}f}" for v in d)
    return f"{mean}{unit} [{low}, {high}]"


def markdown(study: Mapping[str, Any], *, steps: int, command: str) -> str:
    """`study.md`: the tables of `aggregate`."""
    groups, configs = study["groups"], study["configs"]
    seeds = max(len(c["seeds"]) for c in configs.values())
    targets = study["targets"]
    lines = [f"# Study: {len(configs)} configs x {seeds} seeds, {steps} steps", "",
             f"`{command}`", "",
             "Held-out chunks sampled by the policy, mean ± std over seeds (evaluation units: "
             "absolute actions over each dim's held-out std).", "",
             "## Motion gain (1 = moves like the data, 0 = stagnation)", "",
             "| config | " + " | ".join(groups) + " | arms (mean) |",
             "|---" * (len(groups) + 2) + "|"]
    for name, c in configs.items():
        lines.append(f"| {name} | " + " | ".join(_cell(c, f"motion_gain/{g}") for g in groups)
                     + f" | {_cell(c, 'arm_gain')} |")
    lines += ["", "## Error (MSE of the sampled chunk)", "",
              "| config | " + " | ".join(groups) + " |", "|---" * (len(groups) + 1) + "|"]
    for name, c in configs.items():
        lines.append(f"| {name} | " + " | ".join(_cell(c, f"err/{g}", 4) for g in groups) + " |")
    lines += ["", "## Gripper switches (events matched within the tolerance)", "",
              "| config | precision | recall | F1 |", "|---|---|---|---|"]
    for name, c in configs.items():
        lines.append(f"| {name} | " + " | ".join(_cell(c, f"gripper_switch/{k}")
                                                 for k in SWITCH_METRICS) + " |")
    lines += ["", f"## Against `{study['baseline']}` (difference of means, 95 % bootstrap "
              "interval over seeds)", "",
              f"Targets: arms' mean gain >= {targets['arm_gain']}, base error <= "
              f"+{targets['base_err_increase']:.0%} over the baseline, gripper switch F1 >= "
              f"{targets['switch_f1']}.", "",
              "| config | arms' gain | base error | switch F1 | targets met |",
              "|---|---|---|---|---|"]
    for name, c in configs.items():
        vs, met = c["vs_baseline"], c["targets"]
        met_names = [k for k, v in met.items() if v]
        lines.append(f"| {name} | {_interval(vs['arm_gain'])} | "
                     f"{_interval(vs['base_err'], percent=True)} | {_interval(vs['switch_f1'])} | "
                     f"{'all' if all(met.values()) else ', '.join(met_names) or 'none'} |")
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
             "rate, mean ± std over seeds; then the difference to the baseline [95 % bootstrap]. "
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
    return lines


def plot_study(study: Mapping[str, Any], path: Path) -> None:
    """`study.png`: per-group motion gain, one bar per config, std over seeds as error bars."""
    groups, configs = study["groups"], study["configs"]
    width = 0.8 / len(configs)
    closed = has_closed_loop(configs)
    fig, axes = plt.subplots(1, 2 if closed else 1, squeeze=False, gridspec_kw={
        "width_ratios": [len(groups), len(CLOSED_LOOP_KINDS)] if closed else [1]},
        figsize=(max(8, 1.6 * len(groups) + 0.25 * len(configs)) + (4 if closed else 0), 4.8))
    ax = axes[0, 0]
    x = np.arange(len(groups))
    for i, (name, c) in enumerate(configs.items()):
        means = [c["mean"].get(f"motion_gain/{g}") for g in groups]
        stds = [c["std"].get(f"motion_gain/{g}") for g in groups]
        ax.bar(x + (i - (len(configs) - 1) / 2) * width,
               [np.nan if m is None else m for m in means], width,
               yerr=[0 if s is None else s for s in stds], capsize=2, label=name)
    ax.axhline(1.0, color="gray", lw=0.8)
    ax.axhline(0.0, color="black", lw=0.8)
    ax.set_xticks(x, groups)
    ax.set(ylabel="held-out motion gain (1 = like the data)",
           title=f"motion gain per group, mean ± std over seeds (baseline: {study['baseline']})")
    ax.grid(axis="y", alpha=0.3)
    if closed:
        ax = axes[0, 1]
        x = np.arange(len(CLOSED_LOOP_KINDS))
        for i, (name, c) in enumerate(configs.items()):
            keys = [f"{CLOSED_LOOP}success/{k}" for k in CLOSED_LOOP_KINDS]
            ax.bar(x + (i - (len(configs) - 1) / 2) * width,
                   [np.nan if c["mean"].get(k) is None else c["mean"][k] for k in keys], width,
                   yerr=[c["std"].get(k) or 0 for k in keys], capsize=2, label=name)
        ax.set_xticks(x, CLOSED_LOOP_KINDS)
        ax.set(ylim=(0, 1.05), ylabel="success rate", title="closed loop (demo world)")
        ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_reports(results: Sequence[Mapping[str, Any]], workdir: Path, *, steps: int,
                  command: str) -> dict[str, Any]:
    """Writes `study.md`, `study.json` and `study.png` into `workdir`; returns the aggregate."""
    study = aggregate(results)
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
    workdir = Path(FLAGS.workdir).absolute()
    command = "python -m pi0_armfix.study " + " ".join(sys.argv[1:])
    try:
        results = run_study(configs, list(range(FLAGS.seeds)), FLAGS.steps, workdir,
                            FLAGS.override, FLAGS.parallel, FLAGS.closed_loop_episodes)
    except (RuntimeError, ValueError) as err:
        raise SystemExit(f"pi0_armfix.study: {err}") from None
    write_reports(results, workdir, steps=FLAGS.steps, command=command)
    print((workdir / "study.md").read_text())
    print(f"study.md, study.json and study.png in {workdir}")


def _configs_dir() -> Path:
    import configs

    return Path(configs.__file__).parent


def cli() -> None:
    """The `pi0-armfix-study` console script (also `python -m pi0_armfix.study`)."""
    flags.DEFINE_list("configs", ["uniform", "arm_focused"],
                      "config names of configs/ (the first is the baseline)")
    flags.DEFINE_integer("seeds", 3, "seeds per config (0 .. seeds-1)")
    flags.DEFINE_integer("steps", 1500, "training steps of every run")
    flags.DEFINE_string("workdir", "runs/study", "study folder (one run folder per config/seed)")
    flags.DEFINE_integer("parallel", 1, "runs trained at the same time")
    flags.DEFINE_multi_string("override", [], "key=value passed to every run as --config.key")
    flags.DEFINE_integer("closed_loop_episodes", 50, "episodes of the demo world each run's "
                         "final checkpoint drives (0: no closed-loop evaluation)")
    app.run(main)


if __name__ == "__main__":
    cli()
