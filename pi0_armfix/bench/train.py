"""Training benchmarks: the cost of the arm-focused loss, and how long the step waits for data.

    python -m pi0_armfix.bench train [--rounds=10] [--steps=10] [--data_steps=300]

1. Step time of `per_group` with delta weighting over `uniform`, on the `demo` preset and the demo
   config's batch: both jitted train steps (the real `train_step`, sharded and donated) run on the
   SAME batch in one process, interleaved round by round (`--rounds` x `--steps` steps each) so
   that machine noise hits both alike; the ratio of the median round times is printed
   (target <= 1.03: the weighting is a few elementwise ops next to the transformer).
2. Data-wait fraction of the demo training: `configs/arm_focused.py` trained for `--data_steps`
   steps in a temporary folder (evaluation off); the logged `data_wait` (wall time the loop waited
   for the next batch while the device had no step left to run, see `pi0_armfix.train`) over all
   logged windows but the first (which holds the compilation). Target < 5%.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence

import jax

from pi0_armfix.configs import base
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import dataset as dataset_lib
from pi0_armfix.data import pipeline, sources
from pi0_armfix.data.data_spec import DataSpec
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.training import metrics_log
from pi0_armfix.training import optimizer as optimizer_lib
from pi0_armfix.training import sharding as sharding_lib
from pi0_armfix.training import state as state_lib
from pi0_armfix.training import step as step_lib

def step_time_ratio(rounds: int, steps: int) -> tuple[float, float]:
    """Median seconds per step of (uniform, per_group + delta weighting) on one demo batch."""
    config = base.get_config()
    config.data.norm = model_config_lib.norm_mode(config)
    layout = ActionLayout.from_config(config.layout)
    model_config = model_config_lib.from_model_config(config.model)
    mesh = sharding_lib.make_mesh(config.sharding.fsdp)
    batch_sharding = sharding_lib.batch_sharding(mesh)
    spec = DataSpec.from_config(config, layout)
    source = sources.open_source(spec.options, layout)
    norm_stats = dataset_lib.load_or_compute_norm_stats(
        spec, action_horizon=model_config.action_horizon, source=source)
    tokenize = tokenizer_lib.make_tokenizer(config.model, prompts=source.tasks)
    batches = pipeline.make_train_iterator(
        spec, norm_stats=norm_stats, action_horizon=model_config.action_horizon,
        global_batch_size=config.train.batch_size, sharding=batch_sharding, tokenize=tokenize,
        source=source)
    batch = next(batches)
    batches.close()

    tx, schedule = optimizer_lib.make_optimizer(config.optim, config.train.total_steps)
    losses = {
        "uniform": dict(config.loss, strategy="uniform"),
        "per_group+delta": dict(config.loss, strategy="per_group", delta_weighting=True,
                                group_weights=base.group_weights(3.0)),
    }
    runs = {}
    with jax.set_mesh(mesh):
        for name, loss_cfg in losses.items():
            init = lambda rng, loss_cfg=loss_cfg: state_lib.create_train_state(  # noqa: E731
                flow_model.init_params(model_config, rng), tx=tx, loss_cfg=loss_cfg, layout=layout,
                ema_decay=0.0)
            shardings = sharding_lib.tree_shardings(jax.eval_shape(init, jax.random.key(0)), mesh)
            state = jax.jit(init, out_shardings=shardings)(jax.random.key(0))
            step = jax.jit(
                functools.partial(step_lib.train_step, base_rng=jax.random.key(0),
                                  model_config=model_config, loss_cfg=loss_cfg, layout=layout,
                                  tx=tx, schedule=schedule, ema_decay=0.0),
                in_shardings=(shardings, batch_sharding),
                out_shardings=(shardings, sharding_lib.replicated(mesh)), donate_argnums=0)
            state, metrics = step(state, batch)  # compile
            jax.block_until_ready(metrics)
            runs[name] = [step, state, []]

        for _ in range(rounds):
            for run in runs.values():
                step, state, times = run
                start = time.perf_counter()
                for _ in range(steps):
                    state, metrics = step(state, batch)
                jax.block_until_ready((state, metrics))
                times.append((time.perf_counter() - start) / steps)
                run[1] = state
    return (statistics.median(runs["uniform"][2]), statistics.median(runs["per_group+delta"][2]))


def data_wait_fraction(steps: int) -> float:
    """Wall-time fraction spent waiting for batches in the demo training (first window excluded)."""
    config = base.get_config()
    config.update_from_flattened_dict({"train.total_steps": steps, "eval.every": 0,
                                       "train.checkpoint_every": steps})
    with tempfile.TemporaryDirectory() as workdir:
        train.train_and_evaluate(config, workdir)
        records = [r for r in metrics_log.read_metrics(f"{workdir}/{metrics_log.METRICS_FILE}")
                   if "data_wait" in r]
    # Window i spans the steps since record i - 1; window 0 holds the compilation.
    durations = [(b["step"] - a["step"]) / b["steps_per_sec"] for a, b in zip(records, records[1:])]
    waits = [d * r["data_wait"] for d, r in zip(durations, records[1:])]
    return sum(waits) / sum(durations)


def main(argv: Sequence[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench train")
    parser.add_argument("--rounds", type=int, default=10, help="interleaved timing rounds")
    parser.add_argument("--steps", type=int, default=10, help="train steps per timing round")
    parser.add_argument("--data_steps", type=int, default=300,
                        help="steps of the demo training measured for the data-wait fraction")
    args = parser.parse_args(argv[1:])
    uniform, weighted = step_time_ratio(args.rounds, args.steps)
    print(f"demo train step, batch {base.get_config().train.batch_size}, "
          f"{jax.device_count()} {jax.default_backend()} device(s), median of {args.rounds} "
          f"rounds of {args.steps} steps:")
    print(f"  uniform                 {uniform * 1e3:8.1f} ms")
    print(f"  per_group + delta       {weighted * 1e3:8.1f} ms")
    print(f"  ratio                   {weighted / uniform:8.3f}   (target <= 1.03)")
    fraction = data_wait_fraction(args.data_steps)
    print(f"demo training (configs/arm_focused.py) data-wait fraction over {args.data_steps} "
          f"steps: {fraction:.1%}   (target < 5%)")


if __name__ == "__main__":
    main(sys.argv)
