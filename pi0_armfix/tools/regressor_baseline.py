"""How fast can the held-out chunks be learned at all? A plain regressor on a config's data.

    python -m pi0_armfix.tools.regressor_baseline --config=configs/arm_focused.py \
        [--seeds=3] [--steps=2000] [--evaluations=4] [--output=results/regressor]

The reference of the learning-efficiency comparison (RESULTS.md): a flow policy's held-out skill
after so many minutes means little until one knows what the same data lets a plain model learn
in the same minutes. This tool trains a deterministic regressor of the action chunk on the
config's training data, in the config's representation (its split, normalization, delta
actions, batch size): a small CNN per camera (three stride-2 convolutions, flattened: pixel
positions are metric cues in the demo), the state and the mean of the prompt's token embeddings,
an MLP to the normalized chunk `[H, A]`, MSE over every step and dim the flow loss trains (no
group weights: plain). It is scored by the evaluation's own held-out chunks
(`evaluation.heldout.HeldOutChunks`: the same chunks, units and do-nothing references as every
evaluation of a run of that config) every `steps / evaluations` steps, against the training
seconds spent so far (evaluations excluded, the first step's compilation included, as a run's
logged windows count them). Writes `regressor.json` (every seed's metrics at every evaluation)
and `regressor.md` (mean +- std over the seeds) into `--output`.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from absl import app, flags
from ml_collections import config_flags
from tqdm import tqdm

from pi0_armfix import console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import batching, pipeline, video_stream
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import intervals
from pi0_armfix.evaluation.outputs import strict_json
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model, pi0
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.model.inputs import preprocess_observation
from pi0_armfix.tools.export_openpi import code_version
from pi0_armfix import sharding as sharding_lib

RESULT_FILE = "regressor.json"
TABLE_FILE = "regressor.md"
CONV_FEATURES = (16, 32, 64)  # per camera, each a 3x3 convolution of stride 2
TASK_WIDTH = 64  # of the prompt's token embeddings
HIDDEN = 256  # of the MLP's two hidden layers
NETWORKS = ("cnn", "pi0")
OBSERVATION_KEYS = ("image", "image_mask", "state", "tokenized_prompt", "tokenized_prompt_mask")


class ChunkRegressor(nn.Module):
    """An observation batch -> the normalized action chunk `[B, H, A]`."""

    horizon: int
    action_dim: int
    vocab_size: int

    @nn.compact
    def __call__(self, observation: Mapping[str, Any]) -> jax.Array:
        features = []
        for camera in sorted(observation["image"]):
            x = observation["image"][camera].astype(jnp.float32) / 127.5 - 1.0  # [B, h, w, 3]
            for i, width in enumerate(CONV_FEATURES):
                x = nn.relu(nn.Conv(width, (3, 3), strides=2, name=f"{camera}_conv{i}")(x))
            present = observation["image_mask"][camera].astype(jnp.float32)[:, None]
            features.append(x.reshape(len(x), -1) * present)  # a missing camera adds nothing
        mask = observation["tokenized_prompt_mask"].astype(jnp.float32)[..., None]  # [B, L, 1]
        tokens = nn.Embed(self.vocab_size, TASK_WIDTH)(observation["tokenized_prompt"])
        features.append((tokens * mask).sum(axis=1) / jnp.maximum(mask.sum(axis=1), 1.0))
        features.append(observation["state"])
        x = jnp.concatenate(features, axis=-1)
        for _ in range(2):
            x = nn.relu(nn.Dense(HIDDEN)(x))
        return nn.Dense(self.horizon * self.action_dim)(x).reshape(
            -1, self.horizon, self.action_dim)


def chunk_loss(predicted: jax.Array, actions: jax.Array, is_pad: jax.Array,
               dim_mask: jax.Array) -> jax.Array:
    """Mean squared error over the trained entries: predicted, actions `[B, H, A]`, is_pad
    `[B, H]`, dim_mask `[A]` or `[H, A]` (1 on the dims the flow loss trains)."""
    weight = (~is_pad)[..., None].astype(jnp.float32) * dim_mask
    return jnp.sum(weight * (predicted - actions) ** 2) / jnp.maximum(jnp.sum(weight), 1.0)


def observation_of(batch: Mapping[str, Any]) -> dict[str, Any]:
    """A model batch without its actions (what a policy sees)."""
    return {k: batch[k] for k in OBSERVATION_KEYS}


class ConfigData:
    """A config's data, opened once for every seed: its held-out chunks and what its training
    batches are made of."""

    def __init__(self, config: ml_collections.ConfigDict, norm_stats_path: Path):
        self.config = config
        if config.data.norm_per_timestep:
            raise ValueError("data.norm_per_timestep is set: the regressor baseline reads "
                             "per-dim statistics only; set it to False")
        self.layout = ActionLayout.from_config(config.layout)
        self.model = model_config_lib.from_model_config(config.model)
        self.spec = DataSpec.from_config(config, self.layout)
        self.source = sources.open_source(self.spec.options, self.layout)
        dataset_lib.check_data(self.spec, self.source)
        self.tokenize = tokenizer_lib.make_tokenizer(config.model, prompts=self.source.tasks)
        horizon = self.model.action_horizon
        self.norm_stats = dataset_lib.load_or_compute_norm_stats(
            self.spec, action_horizon=horizon, cache_path=norm_stats_path, source=self.source)
        dim_mask = batching.loss_mask(self.norm_stats, self.layout, self.spec.norm, horizon)
        dim_mask[..., self.layout.real_dim:] = 0.0  # padding carries no loss here
        self.dim_mask = dim_mask
        self.chunks = evaluator_lib.heldout_chunks(self.spec, config.eval, self.model,
                                                   self.norm_stats, self.tokenize, self.source)
        self.video_access, _ = video_stream.run_access(self.spec.reading, self.source)

    def train_iterator(self, seed: int, batch_size: int, sharding) -> pipeline.TrainIterator:
        config = ml_collections.ConfigDict(self.config.to_dict())
        config.seed = seed  # the training batches' order and augmentation draws
        spec = DataSpec.from_config(config, self.layout, norm=self.spec.norm)
        return pipeline.make_train_iterator(
            spec, norm_stats=self.norm_stats, action_horizon=self.model.action_horizon,
            global_batch_size=batch_size, sharding=sharding, tokenize=self.tokenize,
            source=self.source, image_size=self.model.image_resolution,
            video_access=self.video_access)

    def score(self, predict, params) -> dict[str, float]:
        """The regressor's held-out metrics (the held-out `Evaluator` of its one prediction per
        chunk: the single draw, the mean of draws and the energy score coincide)."""
        evaluator = evaluator_lib.Evaluator(
            self.chunks, lambda p, observation, rows: np.asarray(
                predict(p, observation_of(observation)))[None], plot_groups=())
        return evaluator(params).metrics


class Network(NamedTuple):
    """A deterministic chunk regressor: `init(rng, observation) -> params` and `apply(params,
    observation, rng, train) -> [B, H, A]` (the normalized chunk)."""

    init: Callable[[jax.Array, Mapping[str, Any]], Any]
    apply: Callable[..., jax.Array]


def make_network(name: str, model_config: model_config_lib.Pi0Config, action_dim: int
                 ) -> Network:
    """`cnn`: `ChunkRegressor`. `pi0`: the config's own pi0 model, its chunk read from one pass
    at flow time 1 on an all-zero x_t (the action expert's output is the chunk itself): the
    architecture of the flow policy with a regression objective in place of flow matching, its
    images augmented as in training."""
    if name == "cnn":
        module = ChunkRegressor(horizon=model_config.action_horizon, action_dim=action_dim,
                                vocab_size=model_config.vocab_size)
        return Network(init=module.init,
                       apply=lambda params, observation, rng, train: module.apply(
                           params, observation))

    def apply(params, observation, rng, train):
        observation = preprocess_observation(rng, observation, config=model_config, train=train)
        batch = observation["state"].shape[0]
        x_t = jnp.zeros((batch, model_config.action_horizon, model_config.action_dim))
        return pi0.forward_velocity(params, observation, x_t, jnp.ones((batch,)),
                                    config=model_config)[..., :action_dim]

    return Network(init=lambda rng, observation: flow_model.init_params(model_config, rng),
                   apply=apply)


def train_seed(data: ConfigData, seed: int, *, network: str, steps: int, evaluations: int,
               batch_size: int, lr: float, progress: bool = True) -> list[dict[str, Any]]:
    """Trains one regressor (`make_network(network)`); returns its evaluations `[{"step",
    "train_seconds", "loss", "metrics"}]`, one every `steps / evaluations` steps (the last at
    `steps`)."""
    net = make_network(network, data.model, data.layout.action_dim)
    mesh = sharding_lib.make_mesh(1)
    train_iter = data.train_iterator(seed, batch_size, sharding_lib.batch_sharding(mesh))
    tx = optax.adam(lr)
    dim_mask = jnp.asarray(data.dim_mask)
    predict = jax.jit(lambda params, observation: net.apply(params, observation, None, False))

    @jax.jit
    def step(params, opt_state, batch, rng):
        def loss_fn(p):
            return chunk_loss(net.apply(p, observation_of(batch), rng, True), batch["actions"],
                              batch["action_is_pad"], dim_mask)
        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    at = sorted({max(1, round(steps * (i + 1) / evaluations)) for i in range(evaluations)})
    records, seconds = [], 0.0
    try:
        with jax.set_mesh(mesh):
            batch = next(train_iter)
            init_rng, rng = jax.random.split(jax.random.key(seed))
            params = net.init(init_rng, observation_of(batch))
            opt_state = tx.init(params)
            bar = tqdm(total=steps, desc=f"regressor seed {seed}", disable=not progress,
                       leave=False)
            done = 0
            for stop in at:
                start = time.perf_counter()
                for i in range(done, stop):
                    params, opt_state, loss = step(params, opt_state, batch,
                                                   jax.random.fold_in(rng, i))
                    batch = next(train_iter)
                    bar.update()
                jax.block_until_ready(params)
                seconds += time.perf_counter() - start
                done = stop
                bar.set_postfix_str(f"loss {float(loss):.4f}")
                records.append({"step": stop, "train_seconds": seconds, "loss": float(loss),
                                "metrics": data.score(predict, params)})
            bar.close()
    finally:
        train_iter.close()
    return records


# ---------------------------------------------------------------------- the report

def _summary(values: Sequence[float]) -> str:
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return "n/a"
    if len(values) == 1:
        return f"{values[0]:+.2f}"
    return f"{np.mean(values):+.2f} ± {np.std(values, ddof=1):.2f}"


def _switch_f1(values: Sequence[float]) -> str:
    # F1 is undefined where neither the regressor nor the held-out chunks switch a gripper.
    finite = [v for v in values if math.isfinite(v)]
    return f"{np.mean(finite):.2f}" if finite else "n/a (no switch, predicted or true)"


def report(result: Mapping[str, Any], layout: ActionLayout, gripper_groups: Sequence[str]
           ) -> str:
    """`regressor.md`: held-out skill over persistence per group at each evaluation, mean +- std
    over the seeds, beside the do-nothing references on the same chunks."""
    runs = list(result["seeds"].values())
    groups = list(layout.group_names)
    arms = layout.groups_with_role("arm")
    header = (["step", "training s"] + [g.replace("_", " ") for g in groups]
              + [f"{' / '.join(a.replace('_', ' ') for a in arms)} gain", "switch F1"])
    lines = [f"# Plain regressor ({result['network']}): held-out skill over persistence "
             f"({len(runs)} seed(s))", "",
             f"Command: `{result['command']}`", f"Code: {result['code']}", "",
             "Skill: 1 - err / persistence err (> 0: better than holding the previous action); "
             "one prediction per chunk (a regressor: its single draw is its mean); mean ± std "
             "over the seeds; gain: 1 = moves like the data, 0 = still or unrelated; training s: "
             "seconds of training to that step, evaluations excluded.", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for i, record in enumerate(runs[0]):
        at = [run[i] for run in runs]
        cells = [str(record["step"]), f"{np.mean([r['train_seconds'] for r in at]):.0f}"]
        cells += [_summary([r["metrics"][f"skill/{g}"] for r in at]) for g in groups]
        cells.append(" / ".join(f"{np.mean([r['metrics'][f'motion_gain/{a}'] for r in at]):.2f}"
                                for a in arms))
        cells.append(_switch_f1([r["metrics"]["gripper_switch/f1"] for r in at])
                     if gripper_groups else "")
        lines.append("| " + " | ".join(cells) + " |")
    metrics = runs[0][-1]["metrics"]
    for name, label in (("persistence", "*persistence (do nothing)*"),
                        ("state_copy", "*state copy (do nothing)*")):
        cells = [label, ""] + [_summary([metrics[f"{name}/skill/{g}"]]) for g in groups]
        cells += [" / ".join(f"{metrics[f'{name}/motion_gain/{a}']:.2f}" for a in arms), "0"]
        lines.append("| " + " | ".join(cells) + " |")
    if len(runs) >= 2:
        last = [run[-1]["metrics"] for run in runs]
        spans = []
        for g in groups:
            mean, low, high = intervals.mean_interval([m[f"skill/{g}"] for m in last])
            spans.append(f"{g.replace('_', ' ')} " + (
                f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]" if math.isfinite(low)
                else "n/a (it never moves in the held-out chunks: holding is exact)"
                if not math.isfinite(mean) else f"{mean:+.2f} (one seed: no interval)"))
        lines += ["", f"At step {runs[0][-1]['step']}, skill with its 95 % t interval over the "
                  f"{len(runs)} seeds (their spread alone: the regressor keeps no per-episode "
                  "sums): " + "; ".join(spans) + "."]
    return "\n".join(lines) + "\n"


def finished_seeds(path: Path, settings: Mapping[str, Any]) -> dict[str, Any]:
    """The seeds a stopped run of the same settings already wrote to `path` (`{seed: records}`;
    none where there is no file); another run's file is refused, naming what differs."""
    if not path.exists():
        return {}
    try:
        kept = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not a regressor result ({e}): remove it or choose another "
                         "--output") from None
    differ = sorted(k for k in settings if kept.get(k) != settings[k])
    if differ:
        raise ValueError(f"{path} holds a regressor run with other settings ({', '.join(differ)}"
                         " differ): choose another --output, or remove it to start again")
    # JSON keeps a metric without a value (NaN) as null: read back as NaN, as it was measured.
    return {seed: [{**r, "metrics": {k: math.nan if v is None else v
                                     for k, v in r["metrics"].items()}} for r in records]
            for seed, records in kept["seeds"].items()}


def run(config: ml_collections.ConfigDict, output: str | Path, *, network: str, seeds: int,
        steps: int, evaluations: int, lr: float, command: str = "", code: str = ""
        ) -> dict[str, Any]:
    """Trains `seeds` regressors `make_network(network)` on the config's data (seeds
    `config.seed` + 0 .. seeds-1) and writes `regressor.json` and `regressor.md` into `output`
    after each seed; returns the result. Seeds a stopped run of the same settings finished in
    `output` are kept, not trained again."""
    if network not in NETWORKS:
        raise ValueError(f"--network = {network!r}: choose one of {NETWORKS}")
    for name, value in (("--seeds", seeds), ("--steps", steps), ("--evaluations", evaluations)):
        if value <= 0:
            raise ValueError(f"{name} = {value} must be positive")
    if evaluations > steps:
        raise ValueError(f"--evaluations = {evaluations} is more than --steps = {steps}: at "
                         "most one evaluation per step")
    if not lr > 0:
        raise ValueError(f"--lr = {lr} must be positive")
    output = Path(output)
    settings = {"network": network, "lr": lr, "batch_size": int(config.train.batch_size),
                "steps": steps, "evaluations": evaluations,
                "config": json.loads(config.to_json_best_effort(sort_keys=True)) | {"seed": None}}
    finished = finished_seeds(output / RESULT_FILE, settings)
    output.mkdir(parents=True, exist_ok=True)
    data = ConfigData(config, output / "norm_stats.json")
    gripper_groups = evaluator_lib.eval_groups(config.eval, data.layout)["gripper_groups"]
    result = {"command": command, "code": code, **settings, "seeds": {}}
    def save() -> None:
        (output / RESULT_FILE).write_text(json.dumps(
            strict_json(result), indent=2, allow_nan=False) + "\n")
        (output / TABLE_FILE).write_text(report(result, data.layout, gripper_groups))

    for seed in range(int(config.seed), int(config.seed) + seeds):
        if str(seed) in finished:
            result["seeds"][str(seed)] = finished[str(seed)]
            continue
        result["seeds"][str(seed)] = train_seed(
            data, seed, network=network, steps=steps, evaluations=evaluations,
            batch_size=int(config.train.batch_size), lr=lr)
        save()  # after every seed, so that a stopped run keeps the seeds it finished
    save()  # the report of finished seeds too, written again by today's code
    return result


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    f = flags.FLAGS
    program = "pi0_armfix.tools.regressor_baseline"
    with console.user_errors(program):
        run(f.config, f.output, network=f.network, seeds=f.seeds, steps=f.steps,
            evaluations=f.evaluations, lr=f.lr,
            command=" ".join([f"python -m {program}", *sys.argv[1:]]), code=code_version())
    print((Path(f.output) / TABLE_FILE).read_text())
    print(f"wrote {Path(f.output) / RESULT_FILE} and {TABLE_FILE}")


def cli() -> None:
    """The `pi0-armfix-regressor-baseline` console script (also `python -m
    pi0_armfix.tools.regressor_baseline`)."""
    config_flags.DEFINE_config_file("config", None, "experiment config file (its data, split, "
                                    "representation and batch size)", lock_config=True)
    flags.DEFINE_string("output", "results/regressor", "folder of regressor.json / regressor.md")
    flags.DEFINE_enum("network", "cnn", NETWORKS, "cnn: a small CNN per camera + state + task; "
                      "pi0: the config's pi0 model, trained as a regressor (make_network)")
    flags.DEFINE_integer("seeds", 3, "regressors trained, seeds config.seed + 0 .. seeds-1")
    flags.DEFINE_integer("steps", 2000, "training steps of each regressor")
    flags.DEFINE_integer("evaluations", 4, "held-out evaluations, evenly spaced, the last at "
                         "--steps")
    flags.DEFINE_float("lr", 1e-3, "Adam's learning rate (constant)")
    flags.mark_flag_as_required("config")
    app.run(main, flags_parser=console.config_flags_parser("pi0_armfix.tools.regressor_baseline"))


if __name__ == "__main__":
    cli()
