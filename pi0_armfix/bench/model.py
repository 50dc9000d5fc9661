"""Model benchmark: `python -m pi0_armfix.bench model [--part=PART] [flags]`.

latency     `sample_actions` wall time on the `demo` preset, prefix KV cache vs full recomputation
            every Euler step (median of `--repeats` runs after compilation).
memory      per-device memory of the compiled `pi0` and `pi05` train steps (loss, gradient, AdamW
            update) on an 8-device CPU mesh with fsdp=8, from `compiled.memory_analysis()`. Every
            input is an abstract `jax.ShapeDtypeStruct` with its sharding, so nothing is
            allocated. Params and AdamW moments are placed by the training rule table
            (`pi0_armfix.sharding`).
flow_time   K flow-matching samples per prefix pass (`loss.flow_samples`): train-step time per
            flow-matching sample at each K of `--flow_samples` on the `demo` preset, against K
            separate K=1 steps. The K variants run interleaved round by round on one batch, so
            machine noise hits them alike; medians over `--rounds`.
flow_flops  the same for the `pi0` preset without running it: FLOPs per flow-matching sample of
            the abstract train step at each K (`Lowered.cost_analysis()`, the whole program before
            partitioning), and the per-device memory of the compiled step at `--flow_memory_k`.

memory and flow_flops need `XLA_FLAGS=--xla_force_host_platform_device_count=8` before jax
starts, so they re-run themselves in a subprocess with that flag.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model
from pi0_armfix.model.inputs import fake_observation

_DEVICES = 8
_GIB = 2**30
_MESH_PARTS = ("memory", "flow_flops")


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench model")
    parser.add_argument("--part", default="all",
                        choices=("all", "latency", "memory", "flow_time", "flow_flops", "mesh"),
                        help="'mesh' = the parts that need 8 devices (memory, flow_flops)")
    parser.add_argument("--latency_preset", default="demo", choices=model_config.PRESETS)
    parser.add_argument("--latency_batch", type=int, default=1)
    parser.add_argument("--num_steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--memory_preset", default="pi0,pi05",
                        help="comma-separated presets whose train step memory is compared; the "
                             "first is the one of flow_flops")
    parser.add_argument("--memory_batch", type=int, default=32)
    parser.add_argument("--flow_samples", default="1,4,8", help="the K values compared")
    parser.add_argument("--flow_time_preset", default="demo", choices=model_config.PRESETS)
    parser.add_argument("--flow_time_batch", type=int, default=32, help="the demo config's batch")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved flow_time rounds")
    parser.add_argument("--steps", type=int, default=5, help="train steps per flow_time round")
    parser.add_argument("--flow_memory_k", type=int, default=4)
    args = parser.parse_args(argv[1:])
    args.flow_samples = tuple(int(k) for k in args.flow_samples.split(","))
    args.memory_preset = tuple(args.memory_preset.split(","))
    for preset in args.memory_preset:
        if preset not in model_config.PRESETS:
            parser.error(f"--memory_preset: unknown preset {preset!r}; choose from "
                         f"{model_config.PRESETS}")
    if args.flow_samples[0] != 1:
        parser.error(f"--flow_samples={args.flow_samples} must start at 1 (the baseline)")
    return args


def sampling_latency(preset: str, batch_size: int, num_steps: int, repeats: int) -> dict[str, float]:
    """Median seconds of one `sample_actions` call, with and without the prefix KV cache."""
    config = model_config.get_preset(preset)
    params = flow_model.init_params(config, jax.random.key(0))
    observation = jax.tree.map(jnp.asarray, fake_observation(config, batch_size))
    result = {}
    for name, use_kv_cache in (("cached", True), ("uncached", False)):
        def run():
            return flow_model.sample_actions(params, jax.random.key(1), observation, config=config,
                                         num_steps=num_steps, use_kv_cache=use_kv_cache)

        run().block_until_ready()  # compile
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            run().block_until_ready()
            times.append(time.perf_counter() - start)
        result[name] = statistics.median(times)
    return result


def _train_step(config: model_config.Pi0Config, tx: optax.GradientTransformation,
                flow_samples: int):
    """(state, batch, rng) -> (state, loss): uniform loss, gradient, AdamW update."""
    layout = ActionLayout.preset("b1k_r1pro")

    def train_step(state, batch, rng):
        def loss_fn(p):
            return flow_model.compute_loss(p, rng, batch, config=config, layout=layout, train=True,
                                       flow_samples=flow_samples, strategy="uniform")[0]

        loss, grads = jax.value_and_grad(loss_fn)(state["params"])
        updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
        return {"params": optax.apply_updates(state["params"], updates), "opt_state": opt_state}, loss

    return train_step


def _example_batch(config: model_config.Pi0Config, batch_size: int) -> dict:
    return dict(fake_observation(config, batch_size),
                actions=np.zeros((batch_size, config.action_horizon, config.action_dim), np.float32),
                action_is_pad=np.zeros((batch_size, config.action_horizon), bool))


def lower_train_step(config: model_config.Pi0Config, batch_size: int,
                     flow_samples: int = 1) -> jax.stages.Lowered:
    """The fsdp train step over every device, lowered from abstract inputs (nothing allocated)."""
    from pi0_armfix import sharding  # the rule table the trainer uses

    mesh = sharding.make_mesh(fsdp=jax.device_count())
    tx = optax.adamw(1e-4)
    params = flow_model.param_shapes(config)
    state = {"params": params, "opt_state": jax.eval_shape(tx.init, params)}
    state_shardings = sharding.tree_shardings(state, mesh)
    abstract_state = jax.tree.map(lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                                  state, state_shardings)
    batch_sharding = sharding.batch_sharding(mesh)
    abstract_batch = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((batch_size, *x.shape[1:]), x.dtype, sharding=batch_sharding),
        _example_batch(config, 1))
    step = jax.jit(_train_step(config, tx, flow_samples),
                   out_shardings=(state_shardings, sharding.replicated(mesh)), donate_argnums=0)
    with jax.set_mesh(mesh):
        return step.lower(abstract_state, abstract_batch, jax.random.key(0))


def train_step_memory(lowered: jax.stages.Lowered) -> dict[str, float]:
    """Per-device bytes of the compiled step, from its memory analysis."""
    stats = lowered.compile().memory_analysis()
    sizes = {
        "arguments": stats.argument_size_in_bytes,
        "outputs": stats.output_size_in_bytes,
        "aliased (donated)": stats.alias_size_in_bytes,
        "temporaries": stats.temp_size_in_bytes,
    }
    sizes["total (arguments + outputs - aliased + temporaries)"] = (
        sizes["arguments"] + sizes["outputs"] - sizes["aliased (donated)"] + sizes["temporaries"])
    return sizes


def flops_per_flow_sample(preset: str, batch_size: int, ks: tuple[int, ...]) -> dict[int, float]:
    """FLOPs of one train step / (batch * K) for each K: the whole program, before partitioning,
    with the layer scans unrolled (the cost analysis counts a loop body once)."""
    config = model_config.get_preset(preset).replace(unroll_layers=True)
    return {k: lower_train_step(config, batch_size, k).cost_analysis()["flops"] / (batch_size * k)
            for k in ks}


def step_time_per_flow_sample(preset: str, batch_size: int, ks: tuple[int, ...], rounds: int,
                              steps: int) -> dict[int, float]:
    """Median seconds of one train step / K for each K, on one batch, K variants interleaved."""
    config = model_config.get_preset(preset)
    tx = optax.adamw(1e-4)
    params = flow_model.init_params(config, jax.random.key(0))
    batch = jax.tree.map(jnp.asarray, _example_batch(config, batch_size))
    batch["actions"] = jax.random.normal(jax.random.key(2), batch["actions"].shape)
    runs = {}
    for k in ks:
        step = jax.jit(_train_step(config, tx, k))
        state = {"params": params, "opt_state": tx.init(params)}
        jax.block_until_ready(step(state, batch, jax.random.key(0)))  # compile
        runs[k] = (step, state, [])
    for _ in range(rounds):
        for step, state, times in runs.values():
            start = time.perf_counter()
            for i in range(steps):
                _, loss = step(state, batch, jax.random.key(i))
            jax.block_until_ready(loss)
            times.append((time.perf_counter() - start) / steps)
    return {k: statistics.median(times) / k for k, (_, _, times) in runs.items()}


def _run_mesh_subprocess(argv: list[str], part: str) -> None:
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} "
               f"--xla_force_host_platform_device_count={_DEVICES}".strip(), JAX_PLATFORMS="cpu")
    args = [a for a in argv[1:] if not a.startswith("--part")]
    subprocess.run([sys.executable, "-m", "pi0_armfix.bench", "model", f"--part={part}", *args],
                   env=env, check=True)


def _print_memory(sizes: dict[str, float]) -> None:
    for name, size in sizes.items():
        print(f"  {name:55s} {size / _GIB:8.2f} GiB")


def main(argv: list[str]) -> None:
    args = _parse(argv)
    if args.part in ("all", "latency"):
        latency = sampling_latency(args.latency_preset, args.latency_batch, args.num_steps, args.repeats)
        print(f"sample_actions, preset={args.latency_preset}, batch={args.latency_batch}, "
              f"{args.num_steps} Euler steps, median of {args.repeats} on {jax.devices()[0].platform}:")
        print(f"  cached prefix KV:      {latency['cached'] * 1e3:8.2f} ms")
        print(f"  full recomputation:    {latency['uncached'] * 1e3:8.2f} ms")
        print(f"  speed-up:              {latency['uncached'] / latency['cached']:8.2f}x")
    if args.part in ("all", "flow_time"):
        per_sample = step_time_per_flow_sample(args.flow_time_preset, args.flow_time_batch,
                                               args.flow_samples, args.rounds, args.steps)
        print(f"train step per flow-matching sample, preset={args.flow_time_preset}, batch="
              f"{args.flow_time_batch}, median of {args.rounds} interleaved rounds of {args.steps} "
              f"steps on {jax.devices()[0].platform}:")
        for k, seconds in per_sample.items():
            print(f"  K={k:<3d} {k * seconds * 1e3:8.1f} ms per step   {seconds * 1e3:8.2f} ms per "
                  f"flow-matching draw of the batch   {seconds / per_sample[1]:5.2f}x of K "
                  "separate K=1 steps")
    mesh_parts = _MESH_PARTS if args.part in ("all", "mesh") else (args.part,)
    if not set(mesh_parts) & set(_MESH_PARTS):
        return
    if jax.device_count() != _DEVICES:
        sys.stdout.flush()
        _run_mesh_subprocess(argv, "mesh" if args.part == "all" else args.part)
        return
    if "memory" in mesh_parts:
        for preset in args.memory_preset:
            config = model_config.get_preset(preset)
            print(f"train step memory per device, preset={preset} (dtype={config.dtype}, "
                  f"remat={config.remat}), batch={args.memory_batch}, {_DEVICES} CPU devices, "
                  f"fsdp={_DEVICES}, AdamW:")
            _print_memory(train_step_memory(lower_train_step(config, args.memory_batch)))
    if "flow_flops" in mesh_parts:
        preset = args.memory_preset[0]
        flops = flops_per_flow_sample(preset, args.memory_batch, args.flow_samples)
        print(f"train step FLOPs per flow-matching sample, preset={preset}, batch="
              f"{args.memory_batch} (abstract step, layers unrolled, cost analysis before "
              "partitioning):")
        for k, value in flops.items():
            print(f"  K={k:<3d} {value / 1e9:12.5g} GFLOP per sample   {value / flops[1]:5.3f}x K=1")
        print(f"train step memory per device at K={args.flow_memory_k}, preset={preset}, "
              f"batch={args.memory_batch}, {_DEVICES} CPU devices, fsdp={_DEVICES}:")
        _print_memory(train_step_memory(lower_train_step(
            model_config.get_preset(preset), args.memory_batch, args.flow_memory_k)))
