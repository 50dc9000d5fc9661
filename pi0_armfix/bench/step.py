"""The project's train step at full speed: `python -m pi0_armfix.bench step [flags]`.

    python -m pi0_armfix.bench step [--config=arm_focused:b1k] [--preset=pi0] [--batch=32] \
        [--flow_samples=4] [--remat=config|on|off] [--steps=10] [--peak_tflops=X] [--no_flops] \
        [--compile_only] [--set=model.attention=fused ...]

The real step (`training.step.train_step`, jitted as `train` jits it: the config's loss, its
levers, AdamW with the config's EMA, the state and batch sharded over every device JAX sees with
the config's fsdp) on a random init and a synthetic batch in the pipeline's format. Prints one
line per measurement:

  compile       seconds to lower and compile the step;
  step          median seconds of `--steps` steps after one warm-up step, and samples/s;
  FLOPs         per step from the cost analysis of the whole program with the layer scans unrolled
                and the batch in one part (a loop body is counted once otherwise, a layer's or
                a microbatch's): the model's (no rematerialization:
                what the computation needs) and the hardware's (with the step's remat: what the
                device runs);
  TFLOP/s, MFU  model FLOPs per second, against the device's peak dense bf16 TFLOP/s
                (`PEAK_TFLOPS` by device kind; `--peak_tflops` for another device) and against a
                bf16 8192^3 matrix product measured on the same device;
  memory        the device's peak bytes in use (`memory_stats`, where it keeps them) and the
                compiled step's memory analysis (arguments + outputs - donated + temporaries).

`--compile_only` stops after the compile and prints its memory analysis: whether a config fits a
card, asked of the compiler without running a step (on the card's platform; another platform's
compiler plans its buffers differently, so a CPU's answer is an estimate).

On a CPU it runs small presets (`tests/test_bench.py` runs `tiny`); the full-size presets are for
a GPU (docs/gpu.md).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import statistics
import sys
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_armfix.bench import common
from pi0_armfix.data.pipeline import batching
from pi0_armfix.data.statistics.stats import NormStats
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model.inputs import fake_observation
from pi0_armfix import sharding as sharding_lib
from pi0_armfix.training import state as state_lib
from pi0_armfix.training import step as step_lib
from pi0_armfix.training.run_spec import RunSpec

# Peak dense bf16 TFLOP/s by the device kind's name (the vendors' spec sheets, without sparsity).
PEAK_TFLOPS = {"H200": 989.0, "H100": 989.0, "A100": 312.0, "L40S": 362.0}
REMAT = ("config", "on", "off")
_MATMUL = 8192
_GIB = 2**30


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench step")
    parser.add_argument("--config", default="arm_focused:b1k",
                        help="a file of pi0_armfix/configs/ with its scale (name[:arg])")
    parser.add_argument("--preset", default="", choices=("", *model_config_lib.PRESETS),
                        help="model.preset in place of the config's ('' = the config's)")
    parser.add_argument("--batch", type=int, default=32, help="global batch (train.batch_size)")
    parser.add_argument("--flow_samples", type=int, default=0,
                        help="loss.flow_samples K (0 = the config's)")
    parser.add_argument("--remat", default="config", choices=REMAT,
                        help="rematerialize each layer in the backward pass: the preset's, on, off")
    parser.add_argument("--steps", type=int, default=10, help="timed steps (>= 1)")
    parser.add_argument("--peak_tflops", type=float, default=0.0,
                        help="the device's peak dense bf16 TFLOP/s (0 = from PEAK_TFLOPS)")
    parser.add_argument("--no_flops", action="store_true",
                        help="skip the cost analysis (lowering the unrolled program is slow)")
    parser.add_argument("--compile_only", action="store_true",
                        help="compile and print the memory analysis, run no step")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a config key to change (repeatable), e.g. model.attention=fused, "
                             "model.remat_policy=dots_saveable, optim.ema_decay=0")
    args = parser.parse_args(argv[1:])
    if args.steps < 1 or args.batch < 1 or args.flow_samples < 0:
        parser.error("--steps and --batch must be >= 1, --flow_samples >= 0")
    return args


def load_config(name: str, preset: str = "", batch: int = 32, flow_samples: int = 0,
                changes: Sequence[str] = ()) -> Any:
    """A config file of `pi0_armfix/configs/` (`name[:arg]`) with the benchmark's settings and
    `changes` ("key=value", the value a Python literal or else a string); the data it never
    reads (a synthetic batch stands in)."""
    file, _, arg = name.partition(":")
    try:
        module = importlib.import_module(f"pi0_armfix.configs.{file}")
    except ModuleNotFoundError:
        raise ValueError(f"--config={name}: no pi0_armfix/configs/{file}.py") from None
    config = module.get_config(arg or None)
    config.data.root = config.data.root or "synthetic"
    config.model.tokenizer = ""
    if preset:
        config.model.preset = preset
    config.train.batch_size = batch
    if flow_samples:
        config.loss.flow_samples = flow_samples
    common.apply_changes(config, changes)
    return config


def _norm_stats(real_dim: int, state_dim: int) -> dict[str, NormStats]:
    """Statistics every dim of which moves (unit spread): all dims carry loss."""
    def unit(width):
        return NormStats(mean=np.zeros(width), std=np.ones(width), q01=-np.ones(width),
                         q99=np.ones(width))

    return {"actions": unit(real_dim), "state": unit(state_dim)}


class Step:
    """The train step of a config, its sharded state and a synthetic batch: `init(rng)` builds
    the step-0 state (jitted), `step_fn(state, batch)` is the step before jit."""

    def __init__(self, config: Any, remat: str = "config"):
        self.spec = spec = RunSpec.resolve(config)
        model = spec.model
        if remat != "config":
            model = model.replace(remat=remat == "on")
        self.model, layout = model, spec.layout
        self.mesh = sharding_lib.make_mesh(spec.fsdp)
        batch_size = spec.train["batch_size"]
        sharding_lib.check_batch_size(batch_size, self.mesh, "--batch",
                                      spec.train["microbatches"])
        norm_stats = _norm_stats(layout.real_dim, layout.action_dim)
        norm = spec.data.norm
        noise_factor = None
        if float(spec.loss["noise_beta"]) < 1.0:
            size = model.action_horizon * layout.real_dim
            noise_factor = noise_lib.correlated_noise_factor(
                np.eye(size), float(spec.loss["noise_beta"]), horizon=model.action_horizon,
                real_dim=layout.real_dim, action_dim=layout.action_dim)
        create = functools.partial(state_lib.create_train_state, model_config=model, tx=spec.tx,
                                   loss_cfg=spec.loss, layout=layout,
                                   ema_decay=spec.optim["ema_decay"])
        def initial_state(rng):
            return create(flow_model.init_params(model, rng))

        abstract = jax.eval_shape(initial_state, jax.random.key(0))
        self.state_shardings = sharding_lib.tree_shardings(abstract, self.mesh)
        self.batch_sharding = sharding_lib.batch_sharding(self.mesh)
        batch = dict(fake_observation(model, batch_size),
                     actions=np.random.default_rng(1).standard_normal(
                         (batch_size, model.action_horizon, model.action_dim)).astype(np.float32),
                     action_is_pad=np.zeros((batch_size, model.action_horizon), bool))
        self.batch = jax.device_put(batch, self.batch_sharding)
        self.init = jax.jit(initial_state, out_shardings=self.state_shardings)
        self.step_fn = functools.partial(
            step_lib.train_step, base_rng=jax.random.key(spec.seed), model_config=model,
            loss_cfg=spec.loss, layout=layout, tx=spec.tx, schedule=spec.schedule,
            ema_decay=spec.optim["ema_decay"], noise_factor=noise_factor,
            switch_threshold=batching.normalized_midpoints(norm_stats, layout, norm,
                                                           model.action_horizon),
            loss_mask=batching.loss_mask(norm_stats, layout, norm, model.action_horizon),
            microbatches=spec.train["microbatches"])
        self._abstract = jax.tree.map(
            lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s), abstract,
            self.state_shardings)

    def _jit(self, step_fn):
        return jax.jit(step_fn, in_shardings=(self.state_shardings, self.batch_sharding),
                       out_shardings=(self.state_shardings, sharding_lib.replicated(self.mesh)),
                       donate_argnums=0)

    def compile(self) -> tuple[Any, float]:
        """`(the compiled step, seconds to lower and compile it)`."""
        start = time.perf_counter()
        with jax.set_mesh(self.mesh):
            compiled = self._jit(self.step_fn).lower(self._abstract, self.batch).compile()
        return compiled, time.perf_counter() - start

    def time_steps(self, compiled: Any, steps: int) -> tuple[float, dict[str, float]]:
        """`(median seconds per step over `steps` after one warm-up step, the last metrics)`."""
        with jax.set_mesh(self.mesh):
            state = self.init(jax.random.key(self.spec.seed))
            state, metrics = compiled(state, self.batch)
            jax.block_until_ready(metrics)
            times = []
            for _ in range(steps):
                start = time.perf_counter()
                state, metrics = compiled(state, self.batch)
                jax.block_until_ready(metrics)
                times.append(time.perf_counter() - start)
        return statistics.median(times), {k: float(v) for k, v in metrics.items()}

    def flops(self, remat: bool) -> float:
        """FLOPs of one step from the cost analysis of the whole program, layer scans unrolled,
        with or without rematerialization. The batch is counted in one part: the cost analysis
        counts a loop's body once, so a step over n microbatches would count one n-th."""
        model = self.model.replace(unroll_layers=True, remat=remat)
        step_fn = functools.partial(self.step_fn, model_config=model, microbatches=1)
        with jax.set_mesh(self.mesh):
            lowered = self._jit(step_fn).lower(self._abstract, self.batch)
        return float(lowered.cost_analysis()["flops"])


def peak_tflops(device_kind: str, given: float = 0.0) -> float | None:
    """The device's peak dense bf16 TFLOP/s: `given`, else `PEAK_TFLOPS` by its kind's name, else
    None (no MFU against the spec sheet)."""
    if given > 0:
        return given
    return next((v for k, v in PEAK_TFLOPS.items() if k in device_kind.upper()), None)


def matmul_tflops(size: int = _MATMUL, repeats: int = 5) -> float:
    """TFLOP/s of a bf16 `size`^3 matrix product on the default device (median of `repeats`)."""
    a = jnp.ones((size, size), jnp.bfloat16)
    product = jax.jit(lambda x: x @ x)
    jax.block_until_ready(product(a))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(product(a))
        times.append(time.perf_counter() - start)
    return 2 * size**3 / statistics.median(times) / 1e12


def device_peak_memory() -> float | None:
    """Bytes: the largest peak in use over the local devices, where they keep the statistic."""
    peaks = [(d.memory_stats() or {}).get("peak_bytes_in_use") for d in jax.local_devices()]
    peaks = [p for p in peaks if p is not None]
    return float(max(peaks)) if peaks else None


def compiled_memory(compiled: Any) -> dict[str, float]:
    """Bytes per device of the compiled step: `total` = arguments + outputs - donated +
    temporaries; `state` = its arguments (the train state and the batch); `temporaries`."""
    stats = compiled.memory_analysis()
    return {"total": float(stats.argument_size_in_bytes + stats.output_size_in_bytes
                           - stats.alias_size_in_bytes + stats.temp_size_in_bytes),
            "state": float(stats.argument_size_in_bytes),
            "temporaries": float(stats.temp_size_in_bytes)}


def measure(config: Any, *, remat: str = "config", steps: int = 10, peak: float = 0.0,
            flops: bool = True, matmul_size: int = _MATMUL, run: bool = True) -> dict[str, Any]:
    """Every number of the module docstring, for one config (see `load_config`); `run=False`
    stops after the compile (its time and memory analysis)."""
    bench = Step(config, remat)
    compiled, compile_s = bench.compile()
    device = jax.devices()[0]
    memory = compiled_memory(compiled)
    result = {"device": f"{jax.device_count()} x {device.device_kind}",
              "preset": config.model.preset, "lora": bench.model.lora_experts,
              "batch": bench.spec.train["batch_size"],
              "flow_samples": int(bench.spec.loss["flow_samples"]), "remat": bench.model.remat,
              "compile_s": compile_s, **{f"compiled_{k}_gib": v / _GIB for k, v in memory.items()}}
    if not run:
        return result
    step_s, metrics = bench.time_steps(compiled, steps)
    result.update(step_s=step_s, samples_per_s=result["batch"] / step_s, loss=metrics["loss"])
    peak_bytes = device_peak_memory()
    result["peak_memory_gib"] = None if peak_bytes is None else peak_bytes / _GIB
    if flops:
        model_flops, hardware_flops = bench.flops(remat=False), bench.flops(remat=bench.model.remat)
        devices = jax.device_count()
        result.update(model_tflop_per_step=model_flops / 1e12,
                      hardware_tflop_per_step=hardware_flops / 1e12,
                      model_tflops_per_s=model_flops / step_s / 1e12 / devices)
        spec_peak = peak_tflops(device.device_kind, peak)
        result["peak_tflops"] = spec_peak
        result["mfu"] = (None if spec_peak is None
                         else result["model_tflops_per_s"] / spec_peak)
        result["matmul_tflops"] = matmul_tflops(matmul_size)
        result["mfu_of_matmul"] = result["model_tflops_per_s"] / result["matmul_tflops"]
    return result


def format_result(r: dict[str, Any]) -> str:
    """The benchmark's lines."""
    step = (f"step         {r['preset']}" + (f" with LoRA on {', '.join(r['lora'])}" if r["lora"]
                                             else "")
            + f", batch {r['batch']}, K = {r['flow_samples']}, remat "
            f"{'on' if r['remat'] else 'off'}: compile {r['compile_s']:.1f} s")
    memory = (f"memory       compiled {r['compiled_total_gib']:.2f} GiB per device (state and "
              f"batch {r['compiled_state_gib']:.2f}, temporaries "
              f"{r['compiled_temporaries_gib']:.2f})")
    if "step_s" not in r:
        return "\n".join([f"device       {r['device']}", step, memory])
    lines = [f"device       {r['device']}",
             step + f", median {r['step_s'] * 1e3:.1f} ms, {r['samples_per_s']:.1f} samples/s, "
             f"loss {r['loss']:.4f}",
             memory + "; peak in use "
             + ("n/a (the device keeps no statistic)" if r["peak_memory_gib"] is None
                else f"{r['peak_memory_gib']:.2f} GiB")]
    if "model_tflop_per_step" in r:
        mfu = ("n/a (unknown device: --peak_tflops)" if r["mfu"] is None
               else f"{100 * r['mfu']:.1f} % of {r['peak_tflops']:g} TFLOP/s")
        lines += [f"FLOPs        {r['model_tflop_per_step']:.3g} TFLOP/step (model), "
                  f"{r['hardware_tflop_per_step']:.3g} (hardware, with the step's remat)",
                  f"throughput   {r['model_tflops_per_s']:.3g} model TFLOP/s per device; MFU "
                  f"{mfu}; {100 * r['mfu_of_matmul']:.1f} % of a measured bf16 matmul "
                  f"({r['matmul_tflops']:.3g} TFLOP/s)"]
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    args = _parse(argv)
    try:
        config = load_config(args.config, args.preset, args.batch, args.flow_samples, args.set)
        print(f"config       {args.config}" + "".join(f", {change}" for change in args.set))
        result = measure(config, remat=args.remat, steps=args.steps, peak=args.peak_tflops,
                         flops=not args.no_flops, run=not args.compile_only)
    except ValueError as e:  # a config the step cannot build: one line naming the key
        sys.exit(f"pi0_armfix.bench step: {e}")
    print(format_result(result))
