"""Every config x every seed -> tables with intervals over seeds, every number beside doing
nothing: which lever fixes the arms, and by how much? (docs/evaluation.md)

    python -m pi0_armfix.study --configs=uniform,arm_focused,arm_delta [--seeds=5] \
        [--primary=arm_focused] [--steps=<the main job's>] [--evaluations=4] \
        [--workdir=runs/study] [--parallel=1] [--override=data.root=/data/b1k] \
        [--closed_loop_episodes=-1]

Each (config, seed) trains in its own run folder `<workdir>/<config>/seed_<s>` through
`python -m pi0_armfix.train` (`--config.seed=s`, `--config.train.total_steps=steps`, a held-out
evaluation every steps / `--evaluations` steps and at the end: the learning curve), its console
output in `train.log` there. A run whose
`result.json` exists is finished and skipped; an interrupted one resumes from its checkpoints, so
rerunning the same command finishes a study (seed-major: an interrupted study has every config's
first seeds). The results of all finished runs are gathered into:

  study.md    per group: skill over persistence, motion gain and ratio, error, each with the
              do-nothing rows (and the ceiling on the demo); gripper switch precision / recall /
              F1 with the event counts; each config's difference to the first config (the
              baseline) with a Welch t interval over seeds widened by the held-out episodes'
              sampling error (`evaluation.intervals`), and the targets.
  study.json  every run's metrics, the per-seed headline values and every aggregate.
  study.png   per-group skill and motion gain, mean with the seeds' spread as error bars, the
              do-nothing predictors as markers.
  study_curves.png  the training loss and each group's held-out skill against the training
              minutes (the step where a run logged no timings) at every evaluation the runs
              logged, mean over seeds with their range; study.md's last table holds the same
              per config and step.

Every held-out number is the single draw's (what a robot executes), with the mean of the
`eval.num_draws` draws and the energy skill beside it (docs/evaluation.md).

Execution (`--execution`, default `adopted`): how every config's policy is executed, set alike for
every run (`eval.execution`; `policies.sampling.Sampling.for_run`), so that two configs differ in
the table only in what they train; study.md names the execution of every row.

Closed loop (`--closed_loop_episodes=N`; the default, -1, is one episode per 120 training steps
within [10, 50] on the embedded demo, announced at start with its estimated time, and off for a
study on other data, `--override=data.root=...` or a config's scale `:b1k` / `:g1`, whose actions
the demo world cannot take; 0 = off): every run's final
checkpoint also drives the demo world (`python -m pi0_armfix.evaluate --closed_loop --episodes=N
--tolerances=1,2,4`, the same N episodes for every run), and study.md / study.png add, mean ± std
over seeds: the share of navigation and manipulation phases that succeeded, the episodes whose
every phase of a kind succeeded (and the whole task), why the phases failed, the success curve at
2x and 4x the world's tolerances, and the difference to the baseline with an interval over seeds
and the world episodes (resampled like the held-out ones, from the per-episode outcomes kept in
`result.json`). A finished run without them gets them on the next call.

A config is a file name of `pi0_armfix/configs/` (`arm_focused`, optionally `arm_focused:b1k`),
optionally with overrides of its own after `@` (`arm_focused@data.video_access=random`: two
variants of one file compare; `@train.total_steps=N` trains that config's runs N steps instead of
`--steps`, so that recipes whose steps cost differently compare at equal wall time; the inference
levers (`policies.sampling.LEVERS`: sampled, `@eval.average_draws=k`, `@eval.temperature=t`,
`@eval.group_draws=base=4+torso=8`, `@eval.deadband=base=0.2`; executed, `@eval.n_exec=4`,
`@eval.rtc=true`, `@eval.temporal_ensemble=0.1`, `@eval.gripper_hysteresis=0.9,-0.98`: a
list's commas stay inside its config) make a lever variant, which trains
nothing: once its seed's trained run has finished, it evaluates its trained config's
checkpoints, seed for seed, with those levers, open and closed loop, so `--configs=uniform,
arm_focused,arm_focused@eval.average_draws=4` adds the mean of 4 draws as executed for the cost
of its evaluations); every
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

import functools
import signal
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from absl import app, flags

from pi0_armfix import console
from pi0_armfix.configs import base as base_config
from pi0_armfix.data import json_files
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import heldout as heldout_lib
from pi0_armfix.evaluation import intervals
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.policies import restore
from pi0_armfix.policies.sampling import EXECUTIONS
from pi0_armfix.study.aggregate import aggregate
from pi0_armfix.study import first_chunks
from pi0_armfix.study.curves import CURVES_HEADING, curve_table, plot_curves
from pi0_armfix.study.report import markdown, plot_study
from pi0_armfix.study.run import (CHILDREN, CLOSED_LOOP_STEPS_PER_EPISODE, StudyInterrupted,
                                  check_study_levers, closed_loop_plan, config_names,
                                  default_closed_loop_episodes, parse_config, run_folder,
                                  run_study, trained_config)
from pi0_armfix.training import metrics_log

def on_other_data(configs: Sequence[str], overrides: Sequence[str]) -> str:
    """What puts a study on data other than the embedded demo (a `data.root` override, a config's
    scale, or a config file's own `data.root`: a written recipe's), or ''."""
    roots = [o for o in overrides if o.partition("=")[0] == "data.root" and o.partition("=")[2]]
    scaled = [c for c in configs if parse_config(c)[1]
              or console.load_config(parse_config(c)[0]).data.get("root")]
    return ", ".join([*(f"--override={o}" for o in roots), *(f"the config {c}" for c in scaled)])


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
        run = restore.restore_run(run_folder(workdir, first["config"], first["seed"]))
    except ValueError:  # results copied without their checkpoints: no ceiling to measure
        return None
    if run.config.data.root:
        return None
    groups = evaluator_lib.eval_groups(run.config.eval, run.layout)
    chunks = heldout_lib.HeldOutChunks(
        DataSpec.from_config(run.config, run.layout), run.config.eval, run.norm_stats,
        horizon=run.model_config.action_horizon,
        sums=functools.partial(eval_metrics.chunk_sums, layout=run.layout,
                                  gripper_groups=groups["gripper_groups"],
                                  switch_tolerance=run.config.eval.switch_tolerance))
    return chunks.reference[heldout_lib.CEILING]


def write_reports(results: Sequence[Mapping[str, Any]], workdir: Path, *, steps: int,
                  command: str, primary: str | None = None,
                  ceiling: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Writes `study.md`, `study.json`, `study.png` and (from the runs' metrics logs, where
    kept) `study_curves.png` into `workdir`; returns the aggregate. A study folder kept as its
    report alone (no run folder has a metrics log) keeps the learning curves its `study.md`
    was written with."""
    study = aggregate(results, primary=primary, ceiling=ceiling)
    kept_curves = kept_curve_section(workdir / "study.md")
    (workdir / "study.md").write_text("\n".join([markdown(study, steps=steps, command=command),
                                                *first_chunks.section(results, workdir), ""]))
    # One line: every run's episode resamples make a study's report megabytes.
    json_files.write_json_atomic(workdir / "study.json",
                                {"command": command, "steps": steps, "runs": list(results),
                                 **study}, indent=None)
    plot_study(study, workdir / "study.png")
    curves: dict[str, list[list[dict]]] = {}
    for result in results:
        if trained_config(result["config"]) != result["config"]:
            continue  # a lever variant trains nothing: its curve is its trained config's
        folder = run_folder(workdir, result["config"], result["seed"])
        curves.setdefault(result["config"], []).append(
            metrics_log.read_metrics(folder / metrics_log.METRICS_FILE))
    table = curve_table(curves, study) if any(any(c) for c in curves.values()) else kept_curves
    with open(workdir / "study.md", "a") as report:
        report.write("\n".join(table) + "\n")
    plot_curves(curves, study["groups"], workdir / "study_curves.png")
    return study


def kept_curve_section(path: Path) -> list[str]:
    """The learning-curve section of an existing `study.md` (its lines from the heading on, the
    last section), or nothing."""
    if not path.is_file():
        return []
    lines = path.read_text().splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith(CURVES_HEADING)), None)
    return [] if start is None else ["", *lines[start:]]


# ---------------------------------------------------------------------- entrypoint


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    configs = config_names(FLAGS.configs, console.config_names())
    if not configs:
        raise SystemExit("pi0_armfix.study: --configs names no config")
    missing = [c for c in configs if console.config_path(parse_config(c)[0]) is None]
    if missing:
        raise SystemExit(f"pi0_armfix.study: --configs names {missing}, which are files neither "
                         f"of {console.LOCAL_CONFIGS.resolve()} nor of {console.configs_dir()}: "
                         f"use {', '.join(console.config_names())}")
    if FLAGS.seeds < 1 or FLAGS.steps < 1 or FLAGS.parallel < 1 or FLAGS.evaluations < 1:
        raise SystemExit("pi0_armfix.study: --seeds, --steps, --parallel and --evaluations must "
                         "be >= 1")
    episodes = FLAGS.closed_loop_episodes
    if episodes < 0:
        elsewhere = on_other_data(configs, FLAGS.override)
        episodes = 0 if elsewhere else default_closed_loop_episodes(FLAGS.steps)
        if elsewhere:
            print(f"study: no closed loop ({elsewhere}: the demo world takes the embedded "
                  "demo's actions)", flush=True)
    bad = [o for o in FLAGS.override if "=" not in o]
    if bad:
        raise SystemExit(f"pi0_armfix.study: --override {bad} must be key=value "
                         "(e.g. data.root=/data/b1k)")
    bad = [c for c in configs if any("=" not in o or not o.partition("=")[0]
                                     for o in parse_config(c)[2])]
    if bad:
        raise SystemExit(f"pi0_armfix.study: --configs {bad}: what follows a config's '@' must "
                         "be key=value with a key (e.g. arm_focused@data.video_access=random)")
    try:
        check_study_levers(configs, FLAGS.execution)
    except ValueError as err:
        raise SystemExit(f"pi0_armfix.study: {err}") from None
    if FLAGS.primary and FLAGS.primary not in configs:
        raise SystemExit(f"pi0_armfix.study: --primary={FLAGS.primary} is not one of --configs "
                         f"{configs}")
    if FLAGS.seeds < intervals.MIN_SEEDS:
        print(f"study: {FLAGS.seeds} seed(s) per config: the intervals will be anecdotes "
              f"(use --seeds={intervals.MIN_SEEDS} or more for results)", flush=True)
    if episodes and not FLAGS.report_only:
        print(closed_loop_plan(len(configs) * FLAGS.seeds, episodes), flush=True)
    workdir = Path(FLAGS.workdir).absolute()
    command = "python -m pi0_armfix.study " + " ".join(sys.argv[1:])
    # Ctrl-C or kill: stop the children (each in its own process group), start no other.
    signal.signal(signal.SIGINT, CHILDREN.stop)
    signal.signal(signal.SIGTERM, CHILDREN.stop)
    try:
        results = run_study(configs, list(range(FLAGS.seeds)), FLAGS.steps, workdir,
                            [f"eval.execution={FLAGS.execution}", *FLAGS.override],
                            FLAGS.parallel, episodes,
                            train=not FLAGS.report_only, evaluations=FLAGS.evaluations)
    except StudyInterrupted as stopped:
        raise SystemExit(f"pi0_armfix.study: stopped; {stopped}. Rerun the same command to go "
                         "on: finished runs are kept, an interrupted one resumes from its last "
                         "checkpoint") from None
    except (RuntimeError, ValueError) as err:
        raise SystemExit(f"pi0_armfix.study: {err}") from None
    write_reports(results, workdir, steps=FLAGS.steps, command=command,
                  primary=FLAGS.primary or None, ceiling=ceiling_metrics(results, workdir))
    print((workdir / "study.md").read_text())
    print(f"study.md, study.json, study.png (and study_curves.png where the runs kept their "
          f"metrics logs) in {workdir}")


def cli() -> None:
    """The `pi0-armfix-study` console script (also `python -m pi0_armfix.study`)."""
    flags.DEFINE_list("configs", ["uniform", "arm_focused"],
                      "config names of pi0_armfix/configs/ (the first is the baseline)")
    flags.DEFINE_integer("seeds", intervals.MIN_SEEDS, "seeds per config (0 .. seeds-1); "
                         f"fewer than {intervals.MIN_SEEDS} give anecdotes, not intervals")
    flags.DEFINE_string("primary", "", "the config whose comparison with the baseline is the "
                        "study's question (95 % interval; the others are Bonferroni-corrected); "
                        "default: the second config")
    flags.DEFINE_integer("steps", base_config.get_config().train.total_steps,
                         "training steps of every run (default: the main job's)")
    flags.DEFINE_string("workdir", "runs/study", "study folder (one run folder per config/seed)")
    flags.DEFINE_integer("parallel", 1, "runs trained at the same time")
    flags.DEFINE_bool("report_only", False, "write the tables of the finished runs and train "
                      "nothing (a partial study, labelled with its seed counts)")
    flags.DEFINE_multi_string("override", [], "key=value passed to every run as --config.key")
    flags.DEFINE_integer("closed_loop_episodes", -1, "episodes of the demo world each run's "
                         "final checkpoint drives at each tolerance (0: no closed-loop "
                         "evaluation; -1: one per "
                         f"{CLOSED_LOOP_STEPS_PER_EPISODE} training steps, within [10, 50])")
    flags.DEFINE_enum("execution", "adopted", list(EXECUTIONS), "how every config's policy is "
                      "executed, alike (eval.execution of every run; policies/sampling.py): "
                      "adopted, the world's adopted execution (the demo world's; elsewhere every "
                      "lever off); none, every lever off. A lever variant changes it for itself "
                      "(@eval.execution=none, @eval.deadband=...)")
    flags.DEFINE_integer("evaluations", 4, "held-out evaluations per run, evenly spaced, the last "
                         "at --steps (the learning curves)")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.study"))

