"""Everything a training run is built from, before its first step (`prepare`): the resolved
config, the data opened and checked, the norm stats, the state built or restored, the step
compiled; and the banner that says what the run is. Everything a user can get wrong fails here
(`ConfigurationError`), before any work is lost. The loop that runs it: `pi0_armfix.train`."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
from collections.abc import Callable
from typing import Any

import jax
import ml_collections
import numpy as np
from etils import epath
from jax.experimental import multihost_utils
from tqdm import tqdm

from pi0_armfix import loss as loss_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import batching, pipeline, run_inputs, transforms, video_stream
from pi0_armfix.data.pipeline import chunk_stats as chunk_stats_lib
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.model import flow_model, pretrained
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.policies.sampling import Sampling
from pi0_armfix.training import checkpoint, fingerprint, freeze, workdir_lock
from pi0_armfix import sharding as sharding_lib
from pi0_armfix.training import state as state_lib
from pi0_armfix.training import step as step_lib
from pi0_armfix.training.run_spec import RunSpec
from pi0_armfix.wall_time import WallTime


class ConfigurationError(ValueError):
    """A config, layout, data or checkpoint error, found before the first step."""


def _create_state(spec: RunSpec, params: Any) -> state_lib.TrainState:
    return state_lib.create_train_state(params, model_config=spec.model, tx=spec.tx,
                                        loss_cfg=spec.loss, layout=spec.layout,
                                        ema_decay=spec.optim["ema_decay"])


def _init_state(spec: RunSpec, state_shardings, params_shardings) -> state_lib.TrainState:
    """The step-0 state: pretrained params (`model.pretrained`) or a random init, sharded."""
    if spec.model_section["pretrained"]:
        params = pretrained.load_pretrained(spec.model_section["pretrained"], spec.model,
                                            shardings=params_shardings, seed=spec.seed)
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
    wall_time: WallTime = dataclasses.field(default_factory=WallTime)  # seconds by part so far


def prepare(config: ml_collections.ConfigDict, workdir: str) -> Run:
    """Resolves the config (`RunSpec`), opens the data, builds or restores the state, compiles
    the step: everything a user can get wrong fails here, before any step."""
    wall_time = WallTime()
    workdir = epath.Path(workdir).absolute()
    is_main = jax.process_index() == 0
    if workdir.exists() and not workdir.is_dir():
        raise ValueError(f"--workdir {workdir} is a file, not a folder: name a new or existing "
                         "run folder")
    spec = RunSpec.resolve(config)
    layout, model_config, data = spec.layout, spec.model, spec.data
    for note in spec.notes:
        say(f"note: {note}")
    mesh = sharding_lib.make_mesh(spec.fsdp)
    sharding_lib.check_batch_size(spec.train["batch_size"], mesh, "train.batch_size",
                                  spec.train["microbatches"])
    batch_sharding = sharding_lib.batch_sharding(mesh)
    # The levers the commands will execute the run with by default, fit to this model, read
    # from the resolved config (the config itself is read once, by RunSpec.resolve).
    sampling = Sampling.for_run(spec.config_json, horizon=model_config.action_horizon)
    sampling.check(layout, model_config.action_horizon)
    if spec.evaluates:
        evaluator_lib.check_eval_config(spec.eval, layout, mesh.size)

    # Every data check runs here, on the metadata and a probe of a few episodes: nothing below
    # passes over the data before they all hold.
    with wall_time.part("open and check the data"):  # the demo is generated on first use
        source = sources.open_source(data.options, layout)
        for warning in dataset_lib.check_data(data, source):
            say(f"warning: {warning}")
        video_access, video_why = video_stream.run_access(data.reading, source)
        tokenize = tokenizer_lib.make_tokenizer(spec.model_section, prompts=source.tasks)
    for line in banner(spec, workdir, mesh, source, video_why, sampling):
        say(line)

    workdir.mkdir(parents=True, exist_ok=True)
    lock = workdir_lock.lock_workdir(workdir) if is_main else None
    with contextlib.ExitStack() as on_error:  # a failed start releases the workdir
        if lock is not None:
            on_error.callback(lock.close)
        holds_run = (checkpoint.has_checkpoints(workdir / "checkpoints")
                     or (workdir / dataset_lib.NORM_STATS_FILE).exists())
        for note in fingerprint.check_resume(workdir, spec.config_json, holds_run=holds_run,
                                             may_write=is_main):
            say(f"note: {note}")
        if jax.process_count() > 1:  # the others read the folder process 0 may have archived
            multihost_utils.sync_global_devices("workdir checked")

        def record_run() -> None:
            """The run's config and what serving it needs of its data (a run folder serves
            without it): written for a new run at once, for a resumed one only once its restore
            has succeeded, so that a refused resume leaves the folder as it was."""
            if is_main:
                (workdir / fingerprint.CONFIG_FILE).write_text(json.dumps(spec.config_json,
                                                                          indent=2))
                run_inputs.save(workdir, source, tokenize.model_proto)

        if not holds_run:
            record_run()
        resuming = checkpoint.has_checkpoints(workdir / "checkpoints")
        with wall_time.part("statistics"):  # computed on a run's first start, then read
            norm_stats = dataset_lib.load_or_compute_norm_stats(
                data, action_horizon=model_config.action_horizon,
                cache_path=workdir / dataset_lib.NORM_STATS_FILE, progress=is_main, source=source,
                resuming=resuming, keep_cached=resuming and spec.train["resume"] == "force")
            noise_factor = None
            if spec.uses_chunk_stats:
                chunk = chunk_stats_lib.load_or_compute_chunk_stats(
                    data, action_horizon=model_config.action_horizon, folder=workdir,
                    constant=stats_lib.fit_width(norm_stats["actions"], layout.real_dim,
                                                 "norm stats 'actions'").constant(data.norm),
                    start=transforms.episode_start(data.delta_reference, norm_stats, layout,
                                                   data.state_groups),
                    source=source, resuming=resuming)
                if data.statistics.norm_per_timestep:
                    norm_stats = {**norm_stats, "actions_per_timestep": chunk.per_timestep}
                if spec.loss["noise_beta"] < 1.0:
                    noise_factor = noise_lib.correlated_noise_factor(
                        chunk.correlation, spec.loss["noise_beta"],
                        horizon=model_config.action_horizon, real_dim=layout.real_dim,
                        action_dim=layout.action_dim)
        with wall_time.part("data pipeline and evaluator"):
            train_iter = pipeline.make_train_iterator(
                data, norm_stats=norm_stats, action_horizon=model_config.action_horizon,
                global_batch_size=spec.train["batch_size"], sharding=batch_sharding,
                tokenize=tokenize, source=source, image_size=model_config.image_resolution,
                video_access=video_access)

            abstract_state = jax.eval_shape(
                lambda: _create_state(spec, flow_model.init_params(model_config,
                                                                   jax.random.key(0))))
            state_shardings = sharding_lib.tree_shardings(abstract_state, mesh)
            evaluator = None
            if spec.evaluates:
                evaluator = evaluator_lib.Evaluator.for_policy(
                    data, spec.eval, model_config, norm_stats, tokenize, mesh=mesh,
                    params_sharding=state_shardings.params, source=source,
                    noise_factor=noise_factor, sampling=sampling)
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
        with wall_time.part("state (initialized or restored)"), jax.set_mesh(mesh):
            restored = ckpts.restore_latest(jax.tree.map(
                lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                abstract_state, state_shardings), say=say)
            start = 0
            if restored is not None:
                start, state, data_state = restored
                train_iter.set_state(data_state)
                say(f"resumed from {ckpts.directory / str(start)}")
            else:
                state = _init_state(spec, state_shardings, state_shardings.params)
        if holds_run:
            record_run()
        train_step = jax.jit(
            functools.partial(step_lib.train_step, base_rng=jax.random.key(spec.seed),
                              model_config=model_config, loss_cfg=spec.loss, layout=layout,
                              tx=spec.tx, schedule=spec.schedule,
                              ema_decay=spec.optim["ema_decay"], noise_factor=noise_factor,
                              switch_threshold=batching.normalized_midpoints(
                                  norm_stats, layout, data.norm,
                                  model_config.action_horizon),
                              loss_mask=batching.loss_mask(norm_stats, layout, data.norm,
                                                           model_config.action_horizon),
                              microbatches=spec.train["microbatches"]),
            in_shardings=(state_shardings, batch_sharding),
            out_shardings=(state_shardings, sharding_lib.replicated(mesh)),
            donate_argnums=0)
        on_error.pop_all()
        return Run(spec=spec, workdir=workdir, layout=layout, mesh=mesh, start=start,
                   state=state, train_step=train_step, train_iter=train_iter, checkpoints=ckpts,
                   evaluator=evaluator,
                   norm_stats_json={"norm_stats": {k: v.to_json()
                                                   for k, v in norm_stats.items()}},
                   lock=lock, wall_time=wall_time)


def levers(spec: RunSpec, sampling: Sampling) -> str:
    """Every lever of the recipe in effect, in words: the relative groups and their reference,
    the flow draws and noise, the per-timestep statistics, the state levers, the vision stem,
    LoRA and the execution (`Sampling.summary`)."""
    model, loss, data, layout = spec.model, spec.loss, spec.data, spec.layout
    parts = []
    if data.delta_mask is not None:
        groups = [g for g in layout.group_names
                  if data.delta_mask[list(layout.group_dims(g))].any()]
        parts.append(f"relative to the {data.delta_reference.replace('_', ' ')}: "
                     f"{', '.join(groups)}")
    if loss["flow_samples"] > 1:
        parts.append(f"{loss['flow_samples']} flow draws per prefix")
    if loss["noise_beta"] < 1:
        parts.append(f"correlated noise (beta {loss['noise_beta']:g})")
    if data.statistics.norm_per_timestep:
        parts.append("per-timestep norm stats")
    if data.statistics.balanced_norm:
        parts.append("balanced norm stats")
    if loss["switch_weight"] != 1:
        parts.append(f"gripper switches x{loss['switch_weight']:g}")
    if not model.use_state:
        parts.append("no state")
    for name, value in (("state dropout", model.state_dropout), ("state noise", model.state_noise)):
        if value:
            parts.append(f"{name} {value:g}")
    stem = spec.model_section.get("sizes", {}).get("siglip", {}).get("conv_stem", 0)
    if stem:
        parts.append(f"a {stem}-conv stem")
    if model.lora_experts:
        parts.append(f"LoRA on {', '.join(model.lora_experts)}")
    if "arm_heavy" in data.curriculum.sources:
        parts.append("an arm-heavy curriculum")
    return "; ".join(parts + [f"executed: {sampling.summary()}"])


def banner(spec: RunSpec, workdir: epath.Path, mesh: jax.sharding.Mesh, source,
           video: str = "", sampling: Sampling | None = None) -> list[str]:
    """What a run is, in a few lines, before it starts on its long work (`video`: how its
    camera frames are read, and why; `sampling`: how the commands will execute it)."""
    model_config, layout, data = spec.model, spec.layout, spec.data
    shapes = flow_model.param_shapes(model_config)
    num_params = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(shapes))
    trained = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(
        freeze.split(shapes, model_config)[0]))
    lora = ("" if not model_config.lora_experts else
            f" (LoRA on {', '.join(model_config.lora_experts)}: {trained / 1e6:.1f} M trained)")
    held_out = source.num_episodes - len(dataset_lib.training_episodes(data, source))
    frames = int(np.sum(source.episode_lengths))
    root = getattr(source, "root", data.reading.root)
    loss = spec.loss["strategy"]
    if loss_lib.loss_strategy(loss).config_weights == "group":
        loss += " " + ", ".join(f"{g} {w:g}" for g, w in spec.loss["group_weights"].items())
    axes = ", ".join(f"{name}={size}" for name, size in mesh.shape.items())
    selection = getattr(source, "state_selection", None)
    preset = selection.preset if selection is not None else None
    state = (f"{selection.stored_width}-D {data.reading.state_key!r} -> state preset "
             f"{preset.name!r} ({preset.width}-D in the action order"
             + (f"; written for {preset.dataset})" if preset.dataset else ")")
             if preset is not None else f"{source.state_width}-D, as stored"
             + (" (data.state_indices)" if data.options.get("state_indices") else ""))
    return [
        f"run       {workdir}",
        f"devices   {jax.device_count()} x {jax.devices()[0].platform} in {jax.process_count()} "
        f"process(es); mesh {axes}",
        f"model     {spec.model_section['preset']}: {num_params / 1e6:.1f} M params{lora}, "
        f"{model_config.dtype} activations, {model_config.action_horizon}-step chunks of {layout.action_dim} dims",
        f"data      {root}{' (the embedded demo)' if not data.reading.root else ''}: "
        f"{source.num_episodes} episodes ({held_out} held out), {frames:,} frames at "
        f"{source.fps:g} fps, cameras {dict(source.cameras) or 'none'}",
        f"state     {state}",
        *([f"video     {video}"] if video else []),
        f"loss      {loss}",
        f"levers    {levers(spec, sampling or Sampling())}",
        f"schedule  {spec.train['total_steps']} steps of batch {spec.train['batch_size']}, lr "
        f"{spec.optim['lr']:g}; a record every {spec.train['log_every']} steps, a checkpoint "
        f"every {spec.train['checkpoint_every']}, held-out evaluation "
        + (f"every {spec.eval['every']}" if spec.evaluates else "off"),
    ]


def say(message: str) -> None:
    """A line on the console of process 0 that does not break the progress bar."""
    if jax.process_index() == 0:
        tqdm.write(message)
