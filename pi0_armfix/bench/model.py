"""Model benchmark: `python -m pi0_armfix.bench model [--part=all|latency|memory] [flags]`.

latency  `sample_actions` wall time on the `demo` preset, prefix KV cache vs full recomputation
         every Euler step (median of `--repeats` runs after compilation).
memory   per-device memory of the compiled `pi0` train step (loss, gradient, AdamW update) on an
         8-device CPU mesh with fsdp=8, from `compiled.memory_analysis()`. Every input is an
         abstract `jax.ShapeDtypeStruct` with its sharding, so nothing is allocated. Params and
         AdamW moments are placed by the training rule table (`training.sharding`). Needs
         `XLA_FLAGS=--xla_force_host_platform_device_count=8` before jax starts, so this part
         re-runs itself in a subprocess with that flag.
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
from pi0_armfix.model import policy
from pi0_armfix.model.inputs import fake_observation

_DEVICES = 8
_GIB = 2**30


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench model")
    parser.add_argument("--part", choices=("all", "latency", "memory"), default="all")
    parser.add_argument("--latency_preset", default="demo", choices=model_config.PRESETS)
    parser.add_argument("--latency_batch", type=int, default=1)
    parser.add_argument("--num_steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--memory_preset", default="pi0", choices=model_config.PRESETS)
    parser.add_argument("--memory_batch", type=int, default=32)
    return parser.parse_args(argv[1:])


def sampling_latency(preset: str, batch_size: int, num_steps: int, repeats: int) -> dict[str, float]:
    """Median seconds of one `sample_actions` call, with and without the prefix KV cache."""
    config = model_config.get_preset(preset)
    params = policy.init_params(config, jax.random.key(0))
    observation = jax.tree.map(jnp.asarray, fake_observation(config, batch_size))
    result = {}
    for name, use_kv_cache in (("cached", True), ("uncached", False)):
        def run():
            return policy.sample_actions(params, jax.random.key(1), observation, config=config,
                                         num_steps=num_steps, use_kv_cache=use_kv_cache)

        run().block_until_ready()  # compile
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            run().block_until_ready()
            times.append(time.perf_counter() - start)
        result[name] = statistics.median(times)
    return result


def train_step_memory(preset: str, batch_size: int) -> dict[str, float]:
    """Per-device bytes of the compiled fsdp train step (abstract inputs; nothing allocated)."""
    from pi0_armfix.training import sharding  # the rule table the trainer uses

    config = model_config.get_preset(preset)
    layout = ActionLayout.preset("b1k_r1pro")
    mesh = sharding.make_mesh(fsdp=_DEVICES)
    tx = optax.adamw(1e-4)

    params = policy.param_shapes(config)
    opt_state = jax.eval_shape(tx.init, params)
    state = {"params": params, "opt_state": opt_state}
    state_shardings = sharding.tree_shardings(state, mesh)
    abstract_state = jax.tree.map(lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                                  state, state_shardings)
    example = dict(fake_observation(config, 1),
                   actions=np.zeros((1, config.action_horizon, config.action_dim), np.float32),
                   action_is_pad=np.zeros((1, config.action_horizon), bool))
    batch_sharding = sharding.batch_sharding(mesh)
    abstract_batch = jax.tree.map(
        lambda x: jax.ShapeDtypeStruct((batch_size, *x.shape[1:]), x.dtype, sharding=batch_sharding),
        example)

    def train_step(state, batch, rng):
        def loss_fn(p):
            return policy.compute_loss(p, rng, batch, config=config, layout=layout, train=True,
                                       strategy="uniform")[0]

        loss, grads = jax.value_and_grad(loss_fn)(state["params"])
        updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
        return {"params": optax.apply_updates(state["params"], updates), "opt_state": opt_state}, loss

    step = jax.jit(train_step, out_shardings=(state_shardings, sharding.replicated(mesh)),
                   donate_argnums=0)
    with jax.set_mesh(mesh):
        compiled = step.lower(abstract_state, abstract_batch, jax.random.key(0)).compile()
    stats = compiled.memory_analysis()
    sizes = {
        "arguments": stats.argument_size_in_bytes,
        "outputs": stats.output_size_in_bytes,
        "aliased (donated)": stats.alias_size_in_bytes,
        "temporaries": stats.temp_size_in_bytes,
    }
    sizes["total (arguments + outputs - aliased + temporaries)"] = (
        sizes["arguments"] + sizes["outputs"] - sizes["aliased (donated)"] + sizes["temporaries"])
    return sizes


def _run_memory_subprocess(argv: list[str]) -> None:
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} "
               f"--xla_force_host_platform_device_count={_DEVICES}".strip(), JAX_PLATFORMS="cpu")
    args = [a for a in argv[1:] if not a.startswith("--part")]
    subprocess.run([sys.executable, "-m", "pi0_armfix.bench", "model", "--part=memory", *args],
                   env=env, check=True)


def main(argv: list[str]) -> None:
    args = _parse(argv)
    if args.part in ("all", "latency"):
        latency = sampling_latency(args.latency_preset, args.latency_batch, args.num_steps, args.repeats)
        print(f"sample_actions, preset={args.latency_preset}, batch={args.latency_batch}, "
              f"{args.num_steps} Euler steps, median of {args.repeats} on {jax.devices()[0].platform}:")
        print(f"  cached prefix KV:      {latency['cached'] * 1e3:8.2f} ms")
        print(f"  full recomputation:    {latency['uncached'] * 1e3:8.2f} ms")
        print(f"  speed-up:              {latency['uncached'] / latency['cached']:8.2f}x")
    if args.part in ("all", "memory"):
        if jax.device_count() != _DEVICES:
            sys.stdout.flush()
            _run_memory_subprocess(argv)
            return
        sizes = train_step_memory(args.memory_preset, args.memory_batch)
        config = model_config.get_preset(args.memory_preset)
        print(f"train step memory per device, preset={args.memory_preset} (dtype={config.dtype}, "
              f"remat={config.remat}), batch={args.memory_batch}, {_DEVICES} CPU devices, fsdp="
              f"{_DEVICES}, AdamW:")
        for name, size in sizes.items():
            print(f"  {name:55s} {size / _GIB:8.2f} GiB")
