"""Training benchmarks: the cost of the arm-focused loss, and how long the step waits for data.

    python -m pi0_armfix.bench train [--rounds=10] [--steps=10] [--data_steps=300]
        [--set=KEY=VALUE ...]

1. Step time of `per_group` with delta weighting over `uniform`, on the `demo` preset and the demo
   config's batch: both jitted train steps (the real `train_step`, sharded and donated) run on the
   SAME batch in one process, interleaved round by round (`--rounds` x `--steps` steps each) so
   that machine noise hits both alike; the ratio of the median round times is printed
   (target <= 1.03: the weighting is a few elementwise ops next to the transformer).
2. Throughput of the main job against its compute bound: `pi0_armfix/configs/arm_focused.py` (the
   `demo` preset, K = 4 flow draws) and the same with K = 1, each trained for `--data_steps`
   steps in a temporary folder (evaluation off): samples/s over the logged windows but the first
   (which holds the compilation), and the logged `data_wait` (wall time the loop waited for the
   next batch while the device had no step left to run, see `pi0_armfix.train`; target < 5%).
   Beside them the compiled train step's FLOPs and bytes accessed per sample (its cost analysis)
   and this machine's float32 matmul rate (a 1024^3 product), whose ratio is the samples/s a step
   of large matrix products would reach: the compute bound. Then K = 4 at `--batch_sizes`: were
   per-step overheads (dispatch, op launch) what holds the demo far below its bound, samples/s
   would rise with the batch; if they stay flat or fall, the per-sample work itself runs slowly
   (matrices 32-128 wide, a few FLOPs per byte moved).

`--set` changes both configs alike (`--set=model.preset=tiny --set=data.root=DIR`: the same
measurements of a smaller model on other data).
"""

from __future__ import annotations

import argparse
import functools
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence

import jax

from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.bench import common
from pi0_armfix.bench import model as bench_model
from pi0_armfix.configs import arm_focused, base
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import pipeline
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.training import metrics_log
from pi0_armfix.training import optimizer as optimizer_lib
from pi0_armfix import sharding as sharding_lib
from pi0_armfix.training import state as state_lib
from pi0_armfix.training import step as step_lib

def step_time_ratio(rounds: int, steps: int, changes: Sequence[str] = ()
                    ) -> tuple[float, float]:
    """Median seconds per step of (uniform, per_group + delta weighting) on one batch of the
    base config with `changes`."""
    config = base.get_config()
    common.apply_changes(config, changes)
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
                flow_model.init_params(model_config, rng), model_config=model_config, tx=tx,
                loss_cfg=loss_cfg, layout=layout, ema_decay=0.0)
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


def main_job_throughput(steps: int, flow_samples: int, batch_size: int,
                        changes: Sequence[str] = ()) -> tuple[float, float]:
    """(samples/s, data-wait fraction) of `pi0_armfix/configs/arm_focused.py` with `changes`, K =
    `flow_samples` and global batch `batch_size`, trained `steps` steps, the first logged window
    (the compilation) excluded."""
    config = arm_focused.get_config()
    common.apply_changes(config, changes)
    config.update_from_flattened_dict({"train.total_steps": steps, "eval.every": 0,
                                       "train.checkpoint_every": steps,
                                       "loss.flow_samples": flow_samples,
                                       "train.batch_size": batch_size})
    with tempfile.TemporaryDirectory() as workdir:
        train.train_and_evaluate(config, workdir)
        records = [r for r in metrics_log.read_metrics(f"{workdir}/{metrics_log.METRICS_FILE}")
                   if "data_wait" in r]
    # Window i spans the steps since record i - 1; window 0 holds the compilation.
    durations = [(b["step"] - a["step"]) / b["steps_per_sec"] for a, b in zip(records, records[1:])]
    waits = [d * r["data_wait"] for d, r in zip(durations, records[1:])]
    steps_run = records[-1]["step"] - records[0]["step"]
    return steps_run * config.train.batch_size / sum(durations), sum(waits) / sum(durations)


def cost_per_sample(flow_samples: int, changes: Sequence[str] = ()) -> tuple[float, float]:
    """(FLOPs, bytes accessed) of the main job's compiled train step (with `changes`) per training
    sample (its K draws included; bytes as XLA counts them after fusion, whether or not a cache
    serves them)."""
    config = arm_focused.get_config()
    common.apply_changes(config, changes)
    model_config = model_config_lib.from_model_config(config.model)
    batch = config.train.batch_size
    cost = bench_model.lower_train_step(model_config, batch, flow_samples).compile().cost_analysis()
    return cost["flops"] / batch, cost["bytes accessed"] / batch


def matmul_flops_per_second(size: int = 1024, repeats: int = 10) -> float:
    """This machine's float32 matmul rate (the best of `repeats` products of size^3)."""
    a = jax.random.normal(jax.random.key(0), (size, size), jax.numpy.float32)
    product = jax.jit(lambda x: x @ x)
    product(a).block_until_ready()
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        product(a).block_until_ready()
        best = min(best, time.perf_counter() - start)
    return 2 * size ** 3 / best


def main(argv: Sequence[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench train")
    parser.add_argument("--rounds", type=int, default=10, help="interleaved timing rounds")
    parser.add_argument("--steps", type=int, default=10, help="train steps per timing round")
    parser.add_argument("--data_steps", type=int, default=300,
                        help="steps of the demo training measured for the data-wait fraction")
    parser.add_argument("--batch_sizes", default="64,128",
                        help="further global batch sizes trained at K = 4 ('' = none): samples/s "
                             "that rise with the batch say per-step overheads bound the step")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a change to both configs (repeatable), e.g. model.preset=tiny")
    args = parser.parse_args(argv[1:])
    demo = base.get_config()
    try:  # both configs, before any work
        common.apply_changes(demo, args.set)
        common.apply_changes(arm_focused.get_config(), args.set)
    except ValueError as e:
        parser.error(str(e))
    batch, preset = demo.train.batch_size, demo.model.preset
    uniform, weighted = step_time_ratio(args.rounds, args.steps, args.set)
    print(f"{preset} train step, batch {batch}, "
          f"{jax.device_count()} {jax.default_backend()} device(s), median of {args.rounds} "
          f"rounds of {args.steps} steps:")
    print(f"  uniform                 {uniform * 1e3:8.1f} ms")
    print(f"  per_group + delta       {weighted * 1e3:8.1f} ms")
    print(f"  ratio                   {weighted / uniform:8.3f}   (target <= 1.03)")
    peak = matmul_flops_per_second()
    print(f"main job (pi0_armfix/configs/arm_focused.py, {preset} preset, batch {batch}), "
          f"{args.data_steps} steps each; this machine's float32 matmul rate "
          f"{peak / 1e9:.1f} GFLOP/s:")
    for k in (4, 1):
        rate, waiting = main_job_throughput(args.data_steps, k, batch, args.set)
        flops, bytes_accessed = cost_per_sample(k, args.set)
        print(f"  K = {k}: {rate:7.1f} samples/s, {flops / 1e6:6.1f} MFLOP/sample -> "
              f"{rate * flops / 1e9:5.2f} GFLOP/s, {rate * flops / peak:5.1%} of the compute "
              f"bound ({peak / flops:7.0f} samples/s); {bytes_accessed / 1e6:5.1f} MB accessed "
              f"per sample ({flops / bytes_accessed:.1f} FLOP/byte); data wait {waiting:.1%} "
              "(target < 5%)")
    for size in (int(b) for b in args.batch_sizes.split(",") if b):
        rate, _ = main_job_throughput(args.data_steps, 4, size, args.set)
        print(f"  K = 4, batch {size}: {rate:7.1f} samples/s ({rate / size:.2f} steps/s)")


if __name__ == "__main__":
    main(sys.argv)
