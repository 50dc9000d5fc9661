"""Trains a pi0 policy: `python -m pi0_armfix.train --config=configs/arm_focused.py`.

    python -m pi0_armfix.train --config=configs/<name>.py[:b1k] [--workdir=DIR] [--config.a.b=v ...]

Without `--workdir` the run folder is `runs/<name>[_<arg>]`. A run folder that holds checkpoints
is resumed from the latest one: params, optimizer, EMA, loss-balancer state and data position, so
a resumed run ends bitwise where an uninterrupted one would (on the same devices).

Everything a user can get wrong (config, layout, data, checkpoint) fails before the first step.
A workdir holds one run: a second start on it while the first runs stops at once (`run.lock`), and
a start with another config is refused naming the keys (`training/fingerprint.py`,
`train.resume=auto|force|new`).

A non-finite loss stops the run with the step that produced it. A checkpoint is written only from
a finite state after finite losses, and counts as good only once the step computed from it is
finite too; one that is not is set aside (`checkpoints.nonfinite/`), and retention never deletes
the last good one (`training/checkpoint.py`). A damaged latest checkpoint is reported and the
previous one used. SIGTERM (preemption) and Ctrl-C stop after the current step, save it
(`train.save_on_preemption`) and exit with one line (`training/preemption.py`).

The run folder:
  checkpoints/<step>/   orbax: state, data iterator, norm stats, config
  norm_stats.json       the run's normalization stats (computed on first start, reused on resume)
  metrics.jsonl         training records every `train.log_every` steps, evaluation records every
                        `eval.every`; tensorboard/ mirrors them
  plots/                group_losses.png, trajectories_<step>.png
  config.json           the config of the latest start (what a resume is checked against)
  wall_time.json        seconds by part of the latest start (`pi0_armfix.wall_time`)
  run.lock              held while a run is on the folder

Logged training metrics (means over the steps since the previous record): `loss`,
`loss/<group>` (unweighted), `weight/<group>` (effective), `grad_norm`; and `lr`, `phase`
(curriculum phase of the last step), `steps_per_sec` and `data_wait`: the fraction of the wall
time the loop waited for the next batch while the device had no step left to run (an upper bound
of the device time lost to the input pipeline; a wait while queued steps still run costs
nothing). A record equals an uninterrupted run's when `train.checkpoint_every` is a multiple of
`train.log_every` (the defaults).

Multi-process (see launch/): every process runs the same command plus
    --num_processes=N [--coordinator_address=HOST:PORT --process_id=I]
where the bracketed flags may be left to `jax.distributed`'s cluster detection (SLURM).
"""

from __future__ import annotations

import collections
import errno
import os
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import jax
import ml_collections
from absl import app, flags
from etils import epath
from ml_collections import config_flags
from tqdm import tqdm

from pi0_armfix import cache, console, wall_time
from pi0_armfix.action_space import MANIPULATION_ROLES, ActionLayout
from pi0_armfix.data import background
from pi0_armfix.data.pipeline import pipeline
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.evaluation import figures
from pi0_armfix.training import checkpoint, fingerprint, finite_checkpoints, preemption
from pi0_armfix.training import metrics_log
from pi0_armfix.training import state as state_lib
from pi0_armfix.train_setup import ConfigurationError, Run, prepare, say


# Dispatched steps the loop may run ahead of the device. JAX dispatches asynchronously: unbounded,
# the loop queued a whole log window of steps in milliseconds (their batches held in memory), the
# bar counted them as done, and the log step's sync then stood still while the device caught up
# (the ~5-8 s "stall" every train.log_every steps). Two keep the device fed.
STEPS_IN_FLIGHT = 2


class Stopped(RuntimeError):
    """The run stopped on SIGTERM or SIGINT after saving (or not) its last step."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum


class DataError(RuntimeError):
    """A file of the dataset could not be read during training (the probe before the first step
    reads only a sample of episodes)."""


class RunFolderVanished(RuntimeError):
    """The run folder was removed (or moved) while the run trained."""


def check_run_folder(workdir: epath.Path, step: int) -> None:
    """Raises `RunFolderVanished` where the run's own record (`config.json`) is gone: writing on
    would recreate a folder holding checkpoints and nothing beside them."""
    if jax.process_index() == 0 and not (workdir / fingerprint.CONFIG_FILE).exists():
        raise RunFolderVanished(
            f"the run folder {workdir} (its {fingerprint.CONFIG_FILE}) vanished before step "
            f"{step} was saved: stopping without writing anything more. Restore the folder and "
            "rerun to resume from its last checkpoint, or start again")


def train_loop(run: Run, stop: preemption.StopRequest | None = None) -> dict[str, float]:
    """Steps `run` to `train.total_steps`, logging, checkpointing and evaluating on the way;
    returns the last training record (on process 0; {} on the others).

    Raises:
      finite_checkpoints.NonFiniteLossError: a step's loss or gradient is not finite (the last
        checkpoint stays the last finite one: `training/finite_checkpoints.py`).
      DataError: a dataset file could not be read.
      RunFolderVanished: the run folder was removed while it trained.
      Stopped: `stop` was requested (SIGTERM, SIGINT): the run stopped after a step.
    """
    spec, workdir, state, train_iter = run.spec, run.workdir, run.state, run.train_iter
    train = spec.train
    stop = stop or preemption.StopRequest()
    is_main = jax.process_index() == 0
    total_steps = train["total_steps"]
    ckpts = run.checkpoints
    finite = finite_checkpoints.FiniteCheckpoints(ckpts, run.start)
    check_run_folder(workdir, run.start + 1)
    writer = metrics_log.MetricsWriter(workdir, resume_step=run.start)
    phase = train_iter.phase
    # The next global batches are built (host -> device included) in a background thread.
    batches = background.prefetched(_with_position(train_iter), depth=2)
    wait, window_start = 0.0, time.perf_counter()
    abandoned = failed = False
    done, data_state = run.start, None
    in_flight: collections.deque = collections.deque()  # losses of the dispatched steps

    def save(step: int, force: bool = False) -> None:
        if force or step % train["checkpoint_every"] == 0:
            check_run_folder(workdir, step)
            finite.save(step, state, data_state, run.norm_stats_json, spec.config_json)

    try:
        with jax.set_mesh(run.mesh), tqdm(total=total_steps, initial=run.start, desc="train",
                                          unit="step", disable=not is_main,
                                          dynamic_ncols=True) as bar:
            step_metrics = None
            cached = jax.config.jax_compilation_cache_dir
            say("compiling the train step (the first step waits for it: from seconds for a "
                "tiny model to minutes for pi0 on a loaded machine; "
                + (f"kept in {cached} for the next run)" if cached else
                   "no compilation cache: PI0_ARMFIX_COMPILATION_CACHE=0)"))
            compile_start = loop_start = time.perf_counter()
            timed_before = sum(run.wall_time.parts.values())  # the loop's own parts follow
            for step in range(run.start + 1, total_steps + 1):  # `step` steps done after this one
                if stop.due(done):
                    break
                fetch_start = time.perf_counter()
                try:
                    batch, data_state, batch_phase = next(batches)
                except ValueError as e:  # the readers name the file, episode and time
                    raise DataError(
                        f"reading the batch of step {step}: {e}. The last checkpoint is intact; "
                        "fix or remove the named file, then rerun to resume") from e
                if step_metrics is None or step_metrics["loss"].is_ready():  # the device idles
                    wait += time.perf_counter() - fetch_start
                if batch_phase != phase:
                    phase = batch_phase
                    say(f"curriculum phase {phase} from step {step - 1}: "
                         f"{train_iter.curriculum.phases[phase].weights}")
                state, step_metrics = run.train_step(state, batch)
                if step == run.start + 1:
                    step_metrics["loss"].block_until_ready()
                    first = time.perf_counter() - compile_start
                    run.wall_time.add("first step (compiled)", first)
                    say(f"first step compiled and ran in {first:.1f} s")
                in_flight.append(step_metrics["loss"])
                if len(in_flight) > STEPS_IN_FLIGHT:
                    in_flight.popleft().block_until_ready()
                ckpts.check_for_errors()
                done = step
                finite.record(step, step_metrics)
                bar.update()

                last = step == total_steps
                if step % train["log_every"] == 0 or last:
                    window = finite.take_window()
                    elapsed = time.perf_counter() - window_start
                    record = {**finite_checkpoints.summarize(window), "phase": phase,
                              "steps_per_sec": len(window) / elapsed,
                              "data_wait": wait / elapsed}
                    writer.write(step, record)
                    bar.set_postfix_str(_postfix(record, run.layout, phase))
                    wait, window_start = 0.0, time.perf_counter()
                save(step, force=last)
                if last:  # no step follows the final state: its own finiteness is the check
                    finite.confirm_final(step)
                if run.evaluator is not None and (step % spec.eval["every"] == 0 or last):
                    check_run_folder(workdir, step)
                    with run.wall_time.part(f"evaluation at step {step}"):
                        _evaluate(run.evaluator, state, step, writer, workdir, run.layout)
                    window_start = time.perf_counter()
        timed_in_loop = sum(run.wall_time.parts.values()) - timed_before  # first step, evaluations
        run.wall_time.add("other steps", time.perf_counter() - loop_start - timed_in_loop)
        if done < total_steps:  # stopped by a signal
            if train["save_on_preemption"] and done > finite.saved:
                save(done, force=True)
            ckpts.wait()  # the save in flight, if any, is finished
            saved = finite.saved
            kept = (f"saved checkpoint {ckpts.directory / str(done)}" if saved == done
                    else f"the last checkpoint is step {saved}" if saved
                    else "no checkpoint was saved")
            raise Stopped(f"stopped by {stop.name} after step {done}: {kept}; rerun the same "
                          "command to resume", stop.signum or 15)
    except preemption.Abandoned:
        abandoned = True
        raise
    except BaseException:
        failed = True
        raise
    finally:
        batches.close()
        if not abandoned:  # an abandoned save is left to orbax's atomic rename
            try:
                ckpts.close()
            except checkpoint.SaveError:
                if not failed:  # else the error on its way out says more
                    raise
        writer.close()
        train_iter.close()
        if run.lock is not None:
            run.lock.close()
    if not is_main:
        return {}
    records = metrics_log.read_metrics(workdir / metrics_log.METRICS_FILE)
    figures.plot_group_losses(records, run.layout, _plots_dir(workdir) / "group_losses.png")
    run.wall_time.save(workdir / wall_time.FILE)
    say(run.wall_time.summary())
    return [r for r in records if "loss" in r][-1]


def _postfix(record: Mapping[str, float], layout: ActionLayout, phase: int) -> str:
    """The bar's summary of a record: the weighted loss, then each group's unweighted loss, the
    arms and grippers first (a narrow terminal cuts the line's end)."""
    first = layout.groups_with_role(*MANIPULATION_ROLES)
    ordered = [*first, *(g for g in layout.group_names if g not in first)]
    groups = " ".join(f"{g} {record[f'loss/{g}']:.3f}" for g in ordered)
    return f"loss {record['loss']:.4f} | {groups} | phase {phase}"


def _with_position(train_iter: pipeline.TrainIterator) -> Iterator[tuple[Any, dict, int]]:
    """`(batch, iterator state after it, its curriculum phase)`, batch after batch: what a
    checkpoint and the log need of the batch the step consumes, whatever was read ahead."""
    while True:
        batch = next(train_iter)
        yield batch, train_iter.get_state(), train_iter.phase


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str) -> dict[str, float]:
    """Runs (or resumes) training in `workdir`; returns the last training record (on process 0;
    {} on the others).

    Raises:
      ConfigurationError: a config, layout, data or checkpoint error, before any step.
      finite_checkpoints.NonFiniteLossError: a step's loss or gradient is not finite (the last
        checkpoint stays the last finite one: `training/finite_checkpoints.py`).
      DataError: a dataset file could not be read during training.
      checkpoint.SaveError: a checkpoint could not be written (disk full).
      Stopped: SIGTERM or SIGINT stopped the run after a step (and its save).
      preemption.Abandoned: a second signal stopped it at once.
    """
    with preemption.stop_on_signals(say) as stop:
        try:
            run = prepare(config, workdir)
        except ValueError as e:
            raise ConfigurationError(str(e)) from e
        return train_loop(run, stop)


def _plots_dir(workdir: epath.Path) -> epath.Path:
    path = workdir / "plots"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _evaluate(evaluator: evaluator_lib.Evaluator, state: state_lib.TrainState, step: int,
              writer: metrics_log.MetricsWriter, workdir: epath.Path,
              layout: ActionLayout) -> None:
    params = state.ema_params if state.ema_params is not None else state.params
    metrics, predicted, true, sums = evaluator(params)
    writer.write(step, metrics)
    if jax.process_index() == 0:
        _, sums_path = evaluator_lib.heldout_paths(workdir, step)
        chunk_sums_lib.save_chunk_sums(sums_path, sums)
        figures.plot_stagnation(metrics_log.read_metrics(workdir / metrics_log.METRICS_FILE),
                              layout, _plots_dir(workdir) / "stagnation.png")
    say(f"step {step} held-out evaluation (sampled actions):\n"
         + evaluator_lib.format_metrics(metrics, layout))
    if jax.process_index() == 0:
        evaluator.plot(predicted, true, _plots_dir(workdir) / f"trajectories_{step}.png",
                       f"step {step}: predicted (dashed) vs true (solid), held-out chunks")


def format_record(record: Mapping[str, float], layout: ActionLayout) -> str:
    """The final per-group losses and weights as a table."""
    lines = [f"{'group':<16}{'loss':>10}{'weight':>10}"]
    for g in layout.group_names:
        lines.append(f"{g:<16}{record[f'loss/{g}']:>10.4f}{record[f'weight/{g}']:>10.3f}")
    lines.append(f"{'total (weighted)':<16}{record['loss']:>10.4f}")
    lines.append(f"(the total is the loss the optimizer sees: sum_d w_d e_d / {layout.action_dim} "
                 f"over all {layout.action_dim} action dims, the weights of mean 1 over them; "
                 "with uniform weights the padding dims, whose error is ~0, pull it below the "
                 "group losses)")
    return "\n".join(lines)


def default_workdir(config_filename: str) -> str:
    """`runs/<config file stem>[_<arg>]` for `--config=configs/<stem>.py[:<arg>]`."""
    path, _, arg = config_filename.partition(":")
    return str(epath.Path("runs") / (epath.Path(path).stem + (f"_{arg}" if arg else "")))


FLAGS = flags.FLAGS


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    console.quiet_library_logging()
    cache.use_compilation_cache()
    if FLAGS.num_processes > 1:
        jax.distributed.initialize(FLAGS.coordinator_address, FLAGS.num_processes,
                                   FLAGS.process_id)
    config = FLAGS.config
    config_file = config_flags.get_config_filename(FLAGS["config"])
    if FLAGS.print_config:
        print(f"# {config_file} with the command line's overrides; set any key with "
              f"--config.<key>=<value>\n{config}")
        return
    workdir = FLAGS.workdir or default_workdir(config_file)
    say(f"config    {config_file}")
    try:
        record = train_and_evaluate(config, workdir)
    except (ConfigurationError, finite_checkpoints.NonFiniteLossError, DataError,
            checkpoint.SaveError, RunFolderVanished) as e:
        raise SystemExit(f"pi0_armfix.train: {e}") from None
    except OSError as e:  # a file the run writes (metrics, plots): a full disk, most often
        fix = ("free space on that disk" if e.errno == errno.ENOSPC
               else "check the path and its permissions")
        raise SystemExit(f"pi0_armfix.train: {e.filename or workdir}: {e.strerror or e}: {fix}, "
                         "then rerun to resume from the last checkpoint") from None
    except Stopped as e:
        print(f"pi0_armfix.train: {e}", file=sys.stderr)
        raise SystemExit(128 + e.signum) from None
    except preemption.Abandoned as e:
        print(f"pi0_armfix.train: stopped at once by a second {e}: the checkpoint being "
              "written (if any) is abandoned; the last complete one is kept", file=sys.stderr)
        sys.stderr.flush()
        preemption.stop_workers()
        os._exit(128 + e.signum)  # noqa: SLF001 - no waiting on the save threads
    if jax.process_index() == 0:
        layout = ActionLayout.from_config(config.layout)
        print(f"\nfinished {config.train.total_steps} steps in {workdir}; last logged losses "
              f"(unweighted per group, normalized units):\n{format_record(record, layout)}")


def define_flags() -> None:
    """The entrypoint's flags (defined only when run as a program, so that importing this module
    defines no absl flags)."""
    config_flags.DEFINE_config_file(
        "config", None, "experiment config: pi0_armfix/configs/<name>.py[:b1k] (or an "
        "installed config's name). Any key is set with --config.<key>=<value>: all keys, with "
        "comments, are in pi0_armfix/configs/base.py; --print_config prints the resolved tree",
        lock_config=True)
    flags.DEFINE_bool("print_config", False, "print the config (file and overrides applied) and "
                      "exit")
    flags.DEFINE_string("workdir", None, "run folder (default runs/<config name>); resumed when "
                        "it holds checkpoints")
    flags.DEFINE_integer("num_processes", 1, "number of processes; > 1 starts jax.distributed")
    flags.DEFINE_string("coordinator_address", None, "host:port of process 0 (unset: detected "
                        "from the cluster environment, e.g. SLURM)")
    flags.DEFINE_integer("process_id", None, "index of this process (unset: detected from the "
                         "cluster environment, e.g. SLURM_PROCID)")
    flags.mark_flag_as_required("config")


def cli() -> None:
    """The `pi0-armfix-train` console script (also `python -m pi0_armfix.train`)."""
    define_flags()
    app.run(main, flags_parser=console.config_flags_parser("pi0_armfix.train"))


if __name__ == "__main__":
    cli()
