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
import contextlib
import dataclasses
import errno
import functools
import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import jax
import ml_collections
from jax.experimental import multihost_utils
import numpy as np
from absl import app, flags
from etils import epath
from ml_collections import config_flags
from tqdm import tqdm

from pi0_armfix import console
from pi0_armfix import loss as loss_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import background
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import batching, pipeline, video_stream
from pi0_armfix.data.pipeline import chunk_stats as chunk_stats_lib
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import run_inputs
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import heldout as heldout_lib
from pi0_armfix.model import flow_model, pretrained
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.training import checkpoint, finite_checkpoints, fingerprint, plots, preemption
from pi0_armfix.training import metrics_log
from pi0_armfix.training import sharding as sharding_lib
from pi0_armfix.training import state as state_lib
from pi0_armfix.training import step as step_lib
from pi0_armfix.training import workdir_lock
from pi0_armfix.training.run_spec import RunSpec


NORM_STATS_FILE = "norm_stats.json"
# Dispatched steps the loop may run ahead of the device. JAX dispatches asynchronously: unbounded,
# the loop queued a whole log window of steps in milliseconds (their batches held in memory), the
# bar counted them as done, and the log step's sync then stood still while the device caught up
# (the ~5-8 s "stall" every train.log_every steps). Two keep the device fed.
STEPS_IN_FLIGHT = 2


class ConfigurationError(ValueError):
    """A config, layout, data or checkpoint error, found before the first step."""


class Stopped(RuntimeError):
    """The run stopped on SIGTERM or SIGINT after saving (or not) its last step."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum


class DataError(RuntimeError):
    """A file of the dataset could not be read during training (the probe before the first step
    reads only a sample of episodes)."""


def _create_state(spec: RunSpec, params: Any) -> state_lib.TrainState:
    return state_lib.create_train_state(params, tx=spec.tx, loss_cfg=spec.loss,
                                        layout=spec.layout, ema_decay=spec.optim["ema_decay"])


def _init_state(spec: RunSpec, state_shardings, params_shardings) -> state_lib.TrainState:
    """The step-0 state: pretrained params (`model.pretrained`) or a random init, sharded."""
    if spec.model_section["pretrained"]:
        params = pretrained.load_pretrained(spec.model_section["pretrained"], spec.model,
                                            shardings=params_shardings)
        return jax.jit(functools.partial(_create_state, spec), in_shardings=(params_shardings,),
                       out_shardings=state_shardings)(params)
    init = lambda rng: _create_state(spec, flow_model.init_params(spec.model, rng))  # noqa: E731
    return jax.jit(init, out_shardings=state_shardings)(jax.random.key(spec.seed))


@dataclasses.dataclass
class Run:
    """A run ready for its next step: everything built from its spec, the state restored."""

    spec: RunSpec
    workdir: epath.Path
    layout: ActionLayout
    mesh: jax.sharding.Mesh
    start: int  # steps already taken
    state: state_lib.TrainState
    train_step: Callable
    train_iter: pipeline.TrainIterator
    checkpoints: checkpoint.Checkpoints
    evaluator: evaluator_lib.Evaluator | None
    norm_stats_json: dict[str, Any]
    lock: Any = None  # the workdir's lock file (process 0), released by closing it


def prepare(config: ml_collections.ConfigDict, workdir: str) -> Run:
    """Resolves the config (`RunSpec`), opens the data, builds or restores the state, compiles
    the step: everything a user can get wrong fails here, before any step."""
    workdir = epath.Path(workdir).absolute()
    is_main = jax.process_index() == 0
    if workdir.exists() and not workdir.is_dir():
        raise ValueError(f"--workdir {workdir} is a file, not a folder: name a new or existing "
                         "run folder")
    spec = RunSpec.resolve(config)
    layout, model_config, data = spec.layout, spec.model, spec.data
    if spec.warmup_note:
        _say(f"note: {spec.warmup_note}")
    mesh = sharding_lib.make_mesh(spec.fsdp)
    sharding_lib.check_batch_size(spec.train["batch_size"], mesh, "train.batch_size")
    batch_sharding = sharding_lib.batch_sharding(mesh)
    if spec.evaluates:
        evaluator_lib.check_eval_config(spec.eval, layout, mesh.size)

    # Every data check runs here, on the metadata and a probe of a few episodes: nothing below
    # passes over the data before they all hold.
    source = sources.open_source(data.options, layout)
    for warning in dataset_lib.check_data(data, source):
        _say(f"warning: {warning}")
    keyframes = (source.video_keyframes()
                 if data.get("images") and hasattr(source, "video_keyframes") else None)
    video_access, video_why = video_stream.choose_access(
        data.get("video_access"), keyframes, open_episodes=int(data.get("stream_episodes")),
        shuffle_window=int(data.get("stream_shuffle")), stride=int(data.get("stream_stride")))
    tokenize = tokenizer_lib.make_tokenizer(spec.model_section, prompts=source.tasks)
    for line in banner(spec, workdir, mesh, source, video_why if keyframes is not None else ""):
        _say(line)

    workdir.mkdir(parents=True, exist_ok=True)
    lock = workdir_lock.lock_workdir(workdir) if is_main else None
    with contextlib.ExitStack() as on_error:  # a failed start releases the workdir
        if lock is not None:
            on_error.callback(lock.close)
        holds_run = (checkpoint.has_checkpoints(workdir / "checkpoints")
                     or (workdir / NORM_STATS_FILE).exists())
        for note in fingerprint.check_resume(workdir, spec.config_json, holds_run=holds_run,
                                             may_write=is_main):
            _say(f"note: {note}")
        if jax.process_count() > 1:  # the others read the folder process 0 may have archived
            multihost_utils.sync_global_devices("workdir checked")
        if is_main:
            (workdir / fingerprint.CONFIG_FILE).write_text(json.dumps(spec.config_json,
                                                                      indent=2))
            # What serving the run needs of its data: a run folder serves without it.
            run_inputs.save(workdir, source, tokenize.model_proto)
        resuming = checkpoint.has_checkpoints(workdir / "checkpoints")
        norm_stats = dataset_lib.load_or_compute_norm_stats(
            data, action_horizon=model_config.action_horizon,
            cache_path=workdir / NORM_STATS_FILE, progress=is_main, source=source,
            resuming=resuming, keep_cached=resuming and spec.train["resume"] == "force")
        noise_factor = None
        if spec.uses_chunk_stats:
            chunk = chunk_stats_lib.load_or_compute_chunk_stats(
                data, action_horizon=model_config.action_horizon, folder=workdir,
                source=source, resuming=resuming)
            if data.get("norm_per_timestep"):
                norm_stats = {**norm_stats, "actions_per_timestep": chunk.per_timestep}
            if spec.loss["noise_beta"] < 1.0:
                noise_factor = noise_lib.correlated_noise_factor(
                    chunk.correlation, spec.loss["noise_beta"],
                    horizon=model_config.action_horizon, real_dim=layout.real_dim,
                    action_dim=layout.action_dim)
        train_iter = pipeline.make_train_iterator(
            data, norm_stats=norm_stats, action_horizon=model_config.action_horizon,
            global_batch_size=spec.train["batch_size"], sharding=batch_sharding,
            tokenize=tokenize, source=source, image_size=model_config.image_resolution,
            video_access=video_access)

        abstract_state = jax.eval_shape(
            lambda: _create_state(spec, flow_model.init_params(model_config, jax.random.key(0))))
        state_shardings = sharding_lib.tree_shardings(abstract_state, mesh)
        evaluator = None
        if spec.evaluates:
            evaluator = evaluator_lib.Evaluator(data, spec.eval, model_config, norm_stats, tokenize,
                                           mesh=mesh, params_sharding=state_shardings.params,
                                           source=source, noise_factor=noise_factor)
        ckpts = checkpoint.Checkpoints(workdir / "checkpoints",
                                       every=spec.train["checkpoint_every"],
                                       keep=spec.train["keep_checkpoints"])
        latest = ckpts.latest_step()
        if latest is not None and latest > spec.train["total_steps"]:
            raise ConfigurationError(
                f"workdir {workdir} holds a run at step {latest}, past train.total_steps = "
                f"{spec.train['total_steps']}: nothing to train. Evaluate it (python -m "
                f"pi0_armfix.evaluate --workdir={workdir}), or set train.total_steps above "
                f"{latest} to train on")
        with jax.set_mesh(mesh):
            restored = ckpts.restore_latest(jax.tree.map(
                lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                abstract_state, state_shardings), say=_say)
            start = 0
            if restored is not None:
                start, state, data_state = restored
                train_iter.set_state(data_state)
                _say(f"resumed from {ckpts.directory / str(start)}")
            else:
                state = _init_state(spec, state_shardings, state_shardings.params)
        train_step = jax.jit(
            functools.partial(step_lib.train_step, base_rng=jax.random.key(spec.seed),
                              model_config=model_config, loss_cfg=spec.loss, layout=layout,
                              tx=spec.tx, schedule=spec.schedule,
                              ema_decay=spec.optim["ema_decay"], noise_factor=noise_factor,
                              switch_threshold=batching.normalized_midpoints(
                                  norm_stats, layout, data.norm,
                                  model_config.action_horizon),
                              loss_mask=batching.loss_mask(norm_stats, layout, data.norm,
                                                           model_config.action_horizon)),
            in_shardings=(state_shardings, batch_sharding),
            out_shardings=(state_shardings, sharding_lib.replicated(mesh)),
            donate_argnums=0)
        on_error.pop_all()
        return Run(spec=spec, workdir=workdir, layout=layout, mesh=mesh, start=start,
                   state=state, train_step=train_step, train_iter=train_iter, checkpoints=ckpts,
                   evaluator=evaluator,
                   norm_stats_json={"norm_stats": {k: v.to_json()
                                                   for k, v in norm_stats.items()}},
                   lock=lock)


def banner(spec: RunSpec, workdir: epath.Path, mesh: jax.sharding.Mesh, source,
           video: str = "") -> list[str]:
    """What a run is, in a few lines, before it starts on its long work (`video`: how its
    camera frames are read, and why)."""
    model_config, layout, data = spec.model, spec.layout, spec.data
    num_params = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(
        flow_model.param_shapes(model_config)))
    held_out = source.num_episodes - len(dataset_lib.training_episodes(data, source))
    frames = int(np.sum(source.episode_lengths))
    root = getattr(source, "root", data.get("root"))
    loss = spec.loss["strategy"]
    if loss_lib.loss_strategy(loss).config_weights == "group":
        loss += " " + ", ".join(f"{g} {w:g}" for g, w in spec.loss["group_weights"].items())
    axes = ", ".join(f"{name}={size}" for name, size in mesh.shape.items())
    selection = getattr(source, "state_selection", None)
    preset = selection.preset if selection is not None else None
    state = (f"{selection.stored_width}-D {data.get('state_key')!r} -> state preset "
             f"{preset.name!r} ({preset.width}-D in the action order"
             + (f"; written for {preset.dataset})" if preset.dataset else ")")
             if preset is not None else f"{source.state_width}-D, as stored"
             + (" (data.state_indices)" if data.get("state_indices") else ""))
    return [
        f"run       {workdir}",
        f"devices   {jax.device_count()} x {jax.devices()[0].platform} in {jax.process_count()} "
        f"process(es); mesh {axes}",
        f"model     {spec.model_section['preset']}: {num_params / 1e6:.1f} M params, "
        f"{model_config.dtype} "
        f"activations, {model_config.action_horizon}-step chunks of {layout.action_dim} dims",
        f"data      {root}{' (the embedded demo)' if not data.get('root') else ''}: "
        f"{source.num_episodes} episodes ({held_out} held out), {frames:,} frames at "
        f"{source.fps:g} fps, cameras {dict(source.cameras) or 'none'}",
        f"state     {state}",
        *([f"video     {video}"] if video else []),
        f"loss      {loss}",
        f"schedule  {spec.train['total_steps']} steps of batch {spec.train['batch_size']}, lr "
        f"{spec.optim['lr']:g}; a record every {spec.train['log_every']} steps, a checkpoint "
        f"every {spec.train['checkpoint_every']}, held-out evaluation "
        + (f"every {spec.eval['every']}" if spec.evaluates else "off"),
    ]


def train_loop(run: Run, stop: preemption.StopRequest | None = None) -> dict[str, float]:
    """Steps `run` to `train.total_steps`, logging, checkpointing and evaluating on the way;
    returns the last training record (on process 0; {} on the others).

    Raises:
      finite_checkpoints.NonFiniteLossError: a step's loss or gradient is not finite (the last
        checkpoint stays the last finite one: `training/finite_checkpoints.py`).
      DataError: a dataset file could not be read.
      Stopped: `stop` was requested (SIGTERM, SIGINT): the run stopped after a step.
    """
    spec, workdir, state, train_iter = run.spec, run.workdir, run.state, run.train_iter
    train = spec.train
    stop = stop or preemption.StopRequest()
    is_main = jax.process_index() == 0
    total_steps = train["total_steps"]
    ckpts = run.checkpoints
    finite = finite_checkpoints.FiniteCheckpoints(ckpts, run.start)
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
            finite.save(step, state, data_state, run.norm_stats_json, spec.config_json)

    try:
        with jax.set_mesh(run.mesh), tqdm(total=total_steps, initial=run.start, desc="train",
                                          unit="step", disable=not is_main,
                                          dynamic_ncols=True) as bar:
            step_metrics = None
            _say("compiling the train step (the first step waits for it: seconds for the demo, "
                 "about a minute for pi0; JAX_COMPILATION_CACHE_DIR keeps it across runs)")
            compile_start = time.perf_counter()
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
                    _say(f"curriculum phase {phase} from step {step - 1}: "
                         f"{train_iter.curriculum.phases[phase].weights}")
                state, step_metrics = run.train_step(state, batch)
                if step == run.start + 1:
                    step_metrics["loss"].block_until_ready()
                    _say(f"first step compiled and ran in {time.perf_counter() - compile_start:.1f}"
                         " s")
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
                    _evaluate(run.evaluator, state, step, writer, workdir, run.layout)
                    window_start = time.perf_counter()
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
    plots.plot_group_losses(records, run.layout, _plots_dir(workdir) / "group_losses.png")
    return [r for r in records if "loss" in r][-1]


def _postfix(record: Mapping[str, float], layout: ActionLayout, phase: int) -> str:
    """The bar's summary of a record: the weighted loss, then each group's unweighted loss, the
    arms and grippers first (a narrow terminal cuts the line's end)."""
    first = layout.groups_with_role("arm", "gripper")
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
    with preemption.stop_on_signals(_say) as stop:
        try:
            run = prepare(config, workdir)
        except ValueError as e:
            raise ConfigurationError(str(e)) from e
        return train_loop(run, stop)


def _say(message: str) -> None:
    """A line on the console of process 0 that does not break the progress bar."""
    if jax.process_index() == 0:
        tqdm.write(message)


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
        heldout_lib.save_chunk_sums(
            workdir / "eval" / f"step_{step}" / heldout_lib.CHUNK_SUMS_FILE, sums)
    if jax.process_index() == 0:
        plots.plot_stagnation(metrics_log.read_metrics(workdir / metrics_log.METRICS_FILE),
                              layout, _plots_dir(workdir) / "stagnation.png")
    _say(f"step {step} held-out evaluation (sampled actions):\n"
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
    # A run stopped by an error leaves batches of its data workers in shared memory; the
    # resource tracker (a child started with these options) unlinks them, and need not say so.
    sys.warnoptions.append("ignore:resource_tracker:UserWarning")
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
    _say(f"config    {config_file}")
    try:
        record = train_and_evaluate(config, workdir)
    except (ConfigurationError, finite_checkpoints.NonFiniteLossError, DataError,
            checkpoint.SaveError) as e:
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
        os._exit(128 + e.signum)  # noqa: SLF001 - no waiting on the save threads
    if jax.process_index() == 0:
        layout = ActionLayout.from_config(config.layout)
        print(f"\nfinished {config.train.total_steps} steps in {workdir}; last logged losses "
              f"(unweighted per group, normalized units):\n{format_record(record, layout)}")


def define_flags() -> None:
    """The entrypoint's flags (defined only when run as a program, so that importing this module
    defines no absl flags)."""
    config_flags.DEFINE_config_file(
        "config", None, "experiment config: pi0_armfix/configs/<name>.py[:b1k] (or an installed config's "
        "name). Any key is set with --config.<key>=<value>: all keys, with comments, are in "
        "pi0_armfix/configs/base.py; --print_config prints the resolved tree", lock_config=True)
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
