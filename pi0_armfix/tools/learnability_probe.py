"""Can the demo's task be seen at its image size? A supervised probe of the cameras.

    python -m pi0_armfix.tools.learnability_probe [--sizes=32,64,96] [--train=6000] \
        [--steps=1500] [--output=results/learnability]

A policy can only stop within the arrival radius, or close a gripper within the reach tolerance,
if its cameras show where the target is to that precision. This probe renders the demo world's
cameras (`sim.render`, exactly as the environment does) for random scenes and trains a small CNN
per camera to read the quantity back: from the head camera the target's distance and bearing, from
a wrist camera the hand's remaining offset to its target (x, y, depth). Its held-out error, near
the goal where it matters (distance below 4 arrival radii, offset below 4 reach tolerances), is
compared with the world's tolerances: an error well under the tolerance says the cue is there to
be learned; one near or above it says no policy trained on these images can meet the criterion,
however good (render larger, or change the cue). Writes `learnability.json` and
`learnability.md` into `--output`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from absl import app, flags
from tqdm import tqdm

from pi0_armfix import console
from pi0_armfix.data import json_files
from pi0_armfix.sim import render
from pi0_armfix.sim.world import TASKS, DemoSpec

COLOUR = TASKS[0].colour  # the target's colour does not change what the probe can read


def head_scenes(rng: np.random.Generator, n: int, spec: DemoSpec
                ) -> tuple[list[dict], np.ndarray]:
    """Scenes with the target at a random distance (half of them within 4 arrival radii) and
    bearing, a random heading; targets `[n, 3]`: distance (m), cos and sin of the bearing."""
    near = rng.random(n) < 0.5
    distance = np.where(near, rng.uniform(0, 4 * spec.arrive_radius, n),
                        rng.uniform(0, spec.nav_distance[1], n))
    bearing = rng.uniform(-math.pi, math.pi, n)
    heading = rng.uniform(-math.pi, math.pi, n)
    scenes = [{"target": d * np.array([math.cos(b), math.sin(b)]), "heading": h, "marks": {},
               "gap": {"left": 0.1, "right": 0.1}, "held": {"left": None, "right": None}}
              for d, b, h in zip(distance, bearing, heading)]
    return scenes, np.stack([distance, np.cos(bearing), np.sin(bearing)], axis=1)


def wrist_scenes(rng: np.random.Generator, n: int, spec: DemoSpec
                 ) -> tuple[list[dict], np.ndarray]:
    """Scenes with the right hand's remaining offset to its target (half of them within 4 reach
    tolerances, the others up to the largest reach) and a random finger gap; targets `[n, 3]`."""
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    near = rng.random(n) < 0.5
    length = np.where(near, rng.uniform(0, 4 * spec.reach_tolerance, n),
                      rng.uniform(0, spec.reach_offset[1], n))
    offset = direction * length[:, None]
    gap = rng.uniform(0, 0.1, n)
    scenes = [{"target": np.zeros(2), "heading": 0.0, "marks": {"right": (o, COLOUR)},
               "gap": {"left": 0.1, "right": g}, "held": {"left": None, "right": None}}
              for o, g in zip(offset, gap)]
    return scenes, offset


class ProbeNet(nn.Module):
    """A small CNN: three stride-2 convolutions, a dense layer, `outputs` regressed values."""

    outputs: int

    @nn.compact
    def __call__(self, images: jax.Array) -> jax.Array:
        """images `[B, S, S, 3]` in [0, 1] -> `[B, outputs]`."""
        x = images
        for features in (32, 64, 64):
            x = nn.gelu(nn.Conv(features, (3, 3), strides=(2, 2))(x))
        x = x.reshape(len(x), -1)
        return nn.Dense(self.outputs)(nn.gelu(nn.Dense(128)(x)))


def fit_probe(train_x: np.ndarray, train_y: np.ndarray, test_x: np.ndarray, *, steps: int,
              batch_size: int = 128, seed: int = 0, desc: str = "probe") -> np.ndarray:
    """Trains `ProbeNet` on images `[N, S, S, 3]` uint8 -> `[N, K]` (standardized) with Adam and
    a cosine schedule; returns its predictions `[M, K]` on `test_x`, in the targets' units."""
    mean, std = train_y.mean(axis=0), train_y.std(axis=0) + 1e-8
    model = ProbeNet(train_y.shape[1])
    params = model.init(jax.random.key(seed), jnp.zeros((1, *train_x.shape[1:]), jnp.float32))
    optimizer = optax.adam(optax.cosine_decay_schedule(1e-3, steps))
    opt_state = optimizer.init(params)

    def loss_fn(params, x, y):
        return jnp.mean(jnp.square(model.apply(params, x) - y))

    @jax.jit
    def step(params, opt_state, x, y):
        loss, grads = jax.value_and_grad(loss_fn)(params, x, y)
        updates, opt_state = optimizer.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state, loss

    rng = np.random.default_rng(seed)
    target = (train_y - mean) / std
    for _ in tqdm(range(steps), desc=desc, unit="step", leave=False):
        idx = rng.integers(len(train_x), size=batch_size)
        params, opt_state, _ = step(params, opt_state, train_x[idx] / np.float32(255),
                                    target[idx])
    predict = jax.jit(functools.partial(model.apply, params))
    out = np.concatenate([np.asarray(predict(test_x[i:i + 256] / np.float32(255)))
                          for i in range(0, len(test_x), 256)])
    return out * std + mean


def probe_size(size: int, spec: DemoSpec, train: int, test: int, steps: int, seed: int = 0
               ) -> dict[str, Any]:
    """The head and wrist probes at image size `size`: held-out errors, overall and near the
    goal, beside the world's tolerances."""
    spec_size = DemoSpec(**{**spec.__dict__, "image_size": size})
    rng = np.random.default_rng([seed, size])
    result: dict[str, Any] = {"image_size": size}
    scenes, y = head_scenes(rng, train + test, spec_size)
    images = render.render_head(scenes, COLOUR, size)
    predicted = fit_probe(images[:train], y[:train], images[train:], steps=steps, seed=seed,
                          desc=f"head probe {size}px")
    truth = y[train:]
    near = truth[:, 0] < 4 * spec.arrive_radius
    error = np.abs(predicted[:, 0] - truth[:, 0])
    result["head"] = {
        "distance_rmse_m": float(np.sqrt(np.mean(error ** 2))),
        "distance_rmse_near_m": float(np.sqrt(np.mean(error[near] ** 2))),
        "arrive_radius_m": spec.arrive_radius,
        # Within the radius by the probe's reading when it truly is (and not when it is not).
        "within_radius_accuracy_near": float(np.mean(
            (predicted[near, 0] < spec.arrive_radius) == (truth[near, 0] < spec.arrive_radius))),
    }
    scenes, y = wrist_scenes(rng, train + test, spec_size)
    images = render.render_wrist(scenes, "right", size)
    predicted = fit_probe(images[:train], y[:train], images[train:], steps=steps, seed=seed,
                          desc=f"wrist probe {size}px")
    truth = y[train:]
    near = np.linalg.norm(truth, axis=1) < 4 * spec.reach_tolerance
    error = predicted - truth
    result["wrist"] = {
        "offset_rmse_per_axis": [float(v) for v in np.sqrt(np.mean(error[near] ** 2, axis=0))],
        "offset_error_norm_near": float(np.sqrt(np.mean(np.sum(error[near] ** 2, axis=1)))),
        "reach_tolerance": spec.reach_tolerance,
        "within_tolerance_accuracy_near": float(np.mean(
            (np.linalg.norm(predicted[near], axis=1) < spec.reach_tolerance)
            == (np.linalg.norm(truth[near], axis=1) < spec.reach_tolerance))),
    }
    return result


def markdown(results: Sequence[dict[str, Any]], train: int, steps: int) -> str:
    lines = [f"# Learnability probe: a small CNN per camera, {train} rendered training scenes, "
             f"{steps} steps", "",
             "Held-out error near the goal (head: distance below 4 arrival radii; wrist: offset "
             "below 4 reach tolerances) beside the world's tolerance, and how often the probe "
             "tells inside from outside the tolerance there.", "",
             "| image size | head distance RMSE (m) | arrival radius (m) | inside/outside "
             "right | wrist offset error (x, y, depth) | offset error norm | reach tolerance | "
             "inside/outside right |", "|---" * 8 + "|"]
    for r in results:
        head, wrist = r["head"], r["wrist"]
        axes = ", ".join(f"{v:.3f}" for v in wrist["offset_rmse_per_axis"])
        lines.append(f"| {r['image_size']} px | {head['distance_rmse_near_m']:.4f} | "
                     f"{head['arrive_radius_m']} | {head['within_radius_accuracy_near']:.2f} | "
                     f"{axes} | {wrist['offset_error_norm_near']:.3f} | "
                     f"{wrist['reach_tolerance']} | {wrist['within_tolerance_accuracy_near']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    try:
        sizes = [int(s) for s in FLAGS.sizes]
    except ValueError:
        raise SystemExit(f"pi0_armfix.tools.learnability_probe: --sizes={FLAGS.sizes} must be "
                         "image sizes in pixels (e.g. 32,64,96)") from None
    if min(sizes) < 8 or FLAGS.train < 100 or FLAGS.test < 100 or FLAGS.steps < 1:
        raise SystemExit("pi0_armfix.tools.learnability_probe: --sizes must be >= 8 px, --train "
                         "and --test >= 100 scenes, --steps >= 1")
    results = [probe_size(s, DemoSpec(), FLAGS.train, FLAGS.test, FLAGS.steps) for s in sizes]
    out = Path(FLAGS.output)
    out.mkdir(parents=True, exist_ok=True)
    json_files.write_json_atomic(out / "learnability.json", {
        "train": FLAGS.train, "test": FLAGS.test, "steps": FLAGS.steps, "results": results})
    text = markdown(results, FLAGS.train, FLAGS.steps)
    (out / "learnability.md").write_text(text)
    print(text)
    print(f"learnability.json and learnability.md in {out}")


def cli() -> None:
    """The `pi0-armfix-learnability-probe` console script (also `python -m
    pi0_armfix.tools.learnability_probe`)."""
    flags.DEFINE_list("sizes", ["32", "64", "96"], "image sizes to probe (px)")
    flags.DEFINE_integer("train", 6000, "rendered training scenes per camera and size")
    flags.DEFINE_integer("test", 2000, "rendered held-out scenes per camera and size")
    flags.DEFINE_integer("steps", 1500, "training steps of each probe")
    flags.DEFINE_string("output", "results/learnability", "output folder")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.learnability_probe"))


if __name__ == "__main__":
    cli()
