"""Held-out evaluation (`Evaluator`): is an arm stagnating, and does the policy do better than
doing nothing? (docs/evaluation.md) Run by training every `eval.every` steps and offline on a
checkpoint by `python -m pi0_armfix.evaluate` (`run_evaluator`).

The held-out set is the dataset's last `eval.episodes` episodes (never trained on). Its chunks
tile each episode's timeline (`tiled_chunk_starts`: every switch event once), at most
`eval.max_chunks` of them, the same chunks at every evaluation. The evaluator takes a prediction
function (`Predict`): the flow policy's (`policies.batch_policy.BatchPolicy`: `eval.num_steps`
Euler steps from the same noise every call, so two evaluations differ only by the params), or a
regressor's (`pi0_armfix.tools.regressor_baseline`). The predicted chunks are turned back into
absolute actions in the data's units (normalization and delta actions undone) and every dim is
divided by the training split's std of the absolute actions (`evaluation_scale`): runs with
different normalizations or action representations are measured in the same units. The metrics
are `pi0_armfix.evaluation.metrics`'s, for the prediction and for the do-nothing predictors of
`pi0_armfix.evaluation.baselines` scored on the same chunks (keys `persistence/...`,
`state_copy/...`); `skill/<g>` is the prediction's error against holding the previous action.
Figures: predicted vs true trajectories (data units) of the chunks that move the
`eval.plot_groups` most, and the per-group loss curves of `metrics.jsonl`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import numpy as np
from etils import epath
from tqdm import tqdm

from pi0_armfix.action_space import MANIPULATION_ROLES, ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.evaluation import heldout as heldout_lib
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.policies import execution, restore
from pi0_armfix.policies.batch_policy import BatchPolicy
from pi0_armfix.policies.sampling import Sampling
from pi0_armfix.evaluation import figures
from pi0_armfix import sharding as sharding_lib

TRAJECTORY_ROWS = 3  # chunks shown in a trajectory figure
METRICS_FILE = "metrics.json"  # of an offline evaluation, in eval/step_<N>/


def eval_groups(eval_cfg: Mapping[str, Any], layout: ActionLayout
                ) -> dict[str, tuple[str, ...]]:
    """`{"gripper_groups", "plot_groups"}`: the `eval.*` keys, or when empty the layout's groups of
    role gripper, and of the manipulation roles (every group if it declares none)."""
    return {
        "gripper_groups": tuple(eval_cfg["gripper_groups"]) or layout.groups_with_role("gripper"),
        "plot_groups": (tuple(eval_cfg["plot_groups"]) or layout.groups_with_role(*MANIPULATION_ROLES)
                        or layout.group_names),
    }


def check_eval_config(eval_cfg: Mapping[str, Any], layout: ActionLayout, num_devices: int
                      ) -> None:
    """Raises ValueError naming every `eval.*` group key the evaluation cannot run with at once,
    then the first other bad key."""
    problems = []
    for field in ("gripper_groups", "plot_groups"):
        unknown = [g for g in eval_cfg[field] if g not in layout.groups]
        if unknown:
            problems.append(f"eval.{field} names {unknown}")
    if problems:
        raise ValueError(f"{'; '.join(problems)}, which are not groups of the layout "
                         f"({list(layout.group_names)}); set the key(s) to () to take the groups "
                         "from the layout's roles (layout.roles)")
    if eval_cfg["batch_size"] <= 0 or eval_cfg["batch_size"] % num_devices:
        raise ValueError(f"eval.batch_size = {eval_cfg['batch_size']} must be a positive multiple "
                         f"of the number of devices ({num_devices})")
    for key in ("max_chunks", "num_draws"):
        if eval_cfg[key] <= 0:
            raise ValueError(f"eval.{key} = {eval_cfg[key]} must be positive")
    Sampling.from_eval(eval_cfg).latch(layout)  # the policy's levers, each in its range
    tolerance = eval_cfg.get("switch_tolerance", 2)
    if tolerance < 0:
        raise ValueError(f"eval.switch_tolerance = {tolerance} must be >= 0 (steps by which a "
                         "predicted gripper switch may miss the true one)")


def heldout_chunks(spec: DataSpec, eval_cfg: Mapping[str, Any],
                   model_config: model_config_lib.Pi0Config,
                   norm_stats: Mapping[str, stats_lib.NormStats], tokenize, source=None
                   ) -> heldout_lib.HeldOutChunks:
    """A run's held-out chunks (model batches at its image size) with the per-chunk sums of
    its metrics (`metrics.chunk_sums` over its `eval_groups` and `eval.switch_tolerance`)."""
    layout = spec.layout
    return heldout_lib.HeldOutChunks(
        spec, eval_cfg, norm_stats, horizon=model_config.action_horizon,
        sums=functools.partial(eval_metrics.chunk_sums, layout=layout,
                               gripper_groups=eval_groups(eval_cfg, layout)["gripper_groups"],
                               switch_tolerance=eval_cfg.get("switch_tolerance", 2)),
        tokenize=tokenize, image_size=model_config.image_resolution, source=source)


# ---------------------------------------------------------------------- the evaluator

class Evaluation(NamedTuple):
    """One evaluation: `metrics` (`HeldOutChunks.score`: the single draw's with its skill, the
    mean of the draws' under `mean_of_draws/...`, the energy score, and each reference's under
    `<name>/...`), the single draw's `predicted` and the `true` absolute chunks `[N, H, A]` in
    evaluation units, and the per-chunk sums the study resamples (`chunk_sums`, to be written
    as `chunk_sums_lib.CHUNK_SUMS_FILE`)."""

    metrics: dict[str, float]
    predicted: np.ndarray
    true: np.ndarray
    chunk_sums: dict[str, np.ndarray]


Predict = Callable[[Any, Mapping[str, np.ndarray], slice], np.ndarray]
"""`predict(params, observation, rows) -> [M, B, H, D]`: the normalized chunks of a held-out
batch of `B` observations (model batch keys without the actions), `M` draws each; `rows` are the
held-out chunks the batch's first rows hold (the rest is padding). The policy's is
`policies.batch_policy.BatchPolicy`; a deterministic regressor's gives M = 1."""


class Evaluator:
    """Scores a prediction function on the fixed held-out chunks (as big_vision's evaluators take
    a `predict_fn`): its chunks are turned back into absolute actions, held still where the
    execution's deadband would hold them, and measured against the truth and the do-nothing
    references (`HeldOutChunks.score`).

    Args:
      chunks: the run's held-out chunks (`heldout_chunks`).
      predict: the prediction function (`Predict`).
      plot_groups: the groups a trajectory figure shows (`eval_groups`).
      bands: the execution's deadband per group (`execution.deadband_groups`; {} = none).
    """

    def __init__(self, chunks: heldout_lib.HeldOutChunks, predict: Predict, *,
                 plot_groups: Sequence[str], bands: Mapping[str, Any] | None = None):
        self.chunks, self.predict = chunks, predict
        self.layout = chunks.layout
        self.plot_groups = tuple(plot_groups)
        self.bands = bands or {}

    @classmethod
    def for_policy(cls, spec: DataSpec, eval_cfg: Mapping[str, Any],
                   model_config: model_config_lib.Pi0Config,
                   norm_stats: Mapping[str, stats_lib.NormStats], tokenize, *,
                   mesh: jax.sharding.Mesh, params_sharding: Any, source=None,
                   noise_factor: np.ndarray | None = None, sampling: Sampling) -> "Evaluator":
        """The evaluator of a run's flow policy (`BatchPolicy`), built once per run (reads the
        held-out episodes; the sampler compiles on first use).

        Args:
          spec: the run's data spec (its layout, held-out split, normalization, seed).
          eval_cfg: the run's `eval` section.
          model_config: the run's model.
          norm_stats: the run's `{"actions", "state"}` statistics.
          tokenize: the run's prompt tokenizer.
          mesh: the run's mesh; params_sharding: NamedShardings of the params.
          source: the run's opened data source (None = open the one `spec` names).
          noise_factor: the correlated noise's Cholesky factor the run trains with, or None.
          sampling: the policy's levers (`Sampling.for_run`), as a command executes them.
        """
        layout = spec.layout
        check_eval_config(eval_cfg, layout, mesh.size)
        chunks = heldout_chunks(spec, eval_cfg, model_config, norm_stats, tokenize, source)
        policy = BatchPolicy(sampling, model_config, layout, num_draws=eval_cfg["num_draws"],
                             num_chunks=len(chunks.frames), seed=spec.seed,
                             noise_factor=noise_factor, mesh=mesh,
                             params_sharding=params_sharding)
        bands = execution.deadband_groups(sampling, layout, stats_lib.fit_width(
            norm_stats["actions"], layout.real_dim, "norm stats 'actions'").std)
        return cls(chunks, policy, plot_groups=eval_groups(eval_cfg, layout)["plot_groups"],
                   bands=bands)

    def sample(self, params: Any) -> np.ndarray:
        """The prediction function's chunks `[M, N, H, D]` (normalized) of all held-out chunks."""
        predicted, start = [], 0
        for batch, rows in zip(tqdm(self.chunks.batches, desc="eval", leave=False,
                                    disable=jax.process_index() != 0), self.chunks.batch_rows):
            observation = {k: v for k, v in batch.items() if k not in ("actions", "action_is_pad")}
            predicted.append(np.asarray(self.predict(params, observation,
                                                     slice(start, start + rows)))[:, :rows])
            start += rows
        return np.concatenate(predicted, axis=1)

    def absolute_draws(self, params: Any) -> np.ndarray:
        """The predicted absolute chunks `[M, N, H, A]` of all held-out chunks in evaluation units
        (`sample`'s draws, with the execution's deadband, comparable with `chunks.true`)."""
        chunks = self.chunks
        draws = np.stack([chunks.transform.absolute_actions(d, chunks.frames)
                          for d in self.sample(params)])
        if self.bands:  # as executed: each chunk held still from the command before it
            draws = execution.hold_still(draws, self.bands,
                                         np.broadcast_to(chunks.executed, draws[:, :, 0].shape))
        return draws / chunks.scale

    def __call__(self, params: Any) -> Evaluation:
        """Predicts the held-out chunks with `params` and scores them (`Evaluation`)."""
        draws = self.absolute_draws(params)
        metrics, sums = self.chunks.score(draws)
        return Evaluation(metrics, draws[0], self.chunks.true, sums)

    def plot(self, predicted: np.ndarray, true: np.ndarray, path: epath.PathLike,
             title: str) -> None:
        """Trajectory figure of the chunks whose `eval.plot_groups` move most in the data."""
        plot_groups = self.plot_groups
        dims = np.concatenate([self.layout.group_dims(g) for g in plot_groups])
        # The base and torso beside the groups of interest: stagnation is the contrast.
        shown = [g for g in self.layout.groups_with_role("base", "torso") if g not in plot_groups]
        shown += list(plot_groups)
        motion = np.linalg.norm(
            eval_metrics.displacement(true, self.chunks.valid, np.zeros(true.shape[-1], bool))[:, dims], axis=-1)
        rows = np.argsort(-motion)[:TRAJECTORY_ROWS]
        scale = self.chunks.scale
        figures.plot_trajectories(predicted[rows] * scale, true[rows] * scale, self.layout,
                                shown, path, title)


def format_metrics(metrics: Mapping[str, float], layout: ActionLayout) -> str:
    """A table: per group the single draw's error and skill over persistence, the skill of the
    mean of the draws and the energy-score skill, the single draw's motion gain and ratio, then
    the error and gain of each reference predictor on the same chunks (the do-nothing
    baselines; the ceiling on the demo); then gripper switches, where the layout has grippers."""
    references = [name for name in ("persistence", "state_copy", heldout_lib.CEILING)
                  if f"{name}/err/{layout.group_names[0]}" in metrics]
    draws = int(metrics.get("draws", 1))
    mean = chunk_sums_lib.MEAN_OF_DRAWS
    lines = ["skill: 1 - err / persistence err (> 0: better than holding the previous action) of "
             "the single draw (what a robot executes; its interval a t interval over the held-out "
             "episodes, their sampling variance from resamples of them), of the mean of "
             f"{draws} draws, and of the energy score of the {draws} "
             "draws (spread counted fairly); gain: 1 = moves like the data, 0 = still or "
             "unrelated; rms: the error's root in the data's own units (as the set stores them: "
             "rad or degrees for a joint, m/s for a base)",
             f"{'group':<15}{'err':>9}{'rms':>9}{'skill':>9}{'[95 % over episodes]':>22}"
             f"{f'mean {draws}':>9}{'energy':>9}{'gain':>8}{'ratio':>8}"
             + "".join(f" |{name.replace('_', ' ') + ' err':>16}{'rms':>9}{'gain':>7}"
                       for name in references)]
    def cell(value: float, width: int, spec: str) -> str:
        return f"{'n/a':>{width}}" if not math.isfinite(value) else f"{value:>{width}{spec}}"

    constant = []
    for g in layout.group_names:
        low, high = (metrics.get(f"interval_{end}/skill/{g}", math.nan) for end in ("low", "high"))
        if not math.isfinite(metrics[f"skill/{g}"]):
            constant.append(g)
        interval = (f"[{low:+.3f}, {high:+.3f}]" if math.isfinite(low) and math.isfinite(high)
                    else "n/a")
        lines.append(
            f"{g:<15}{cell(metrics[f'err/{g}'], 9, '.4f')}"
            f"{cell(metrics.get(f'rms_units/{g}', math.nan), 9, '.4g')}"
            f"{cell(metrics[f'skill/{g}'], 9, '.3f')}{interval:>22}"
            + cell(metrics.get(f"{mean}/skill/{g}", math.nan), 9, ".3f")
            + cell(metrics.get(f"energy_skill/{g}", math.nan), 9, ".3f")
            + cell(metrics[f"motion_gain/{g}"], 8, ".3f")
            + cell(metrics[f"motion_ratio/{g}"], 8, ".3f")
            + "".join(f" |{cell(metrics[f'{name}/err/{g}'], 16, '.4f')}"
                      f"{cell(metrics.get(f'{name}/rms_units/{g}', math.nan), 9, '.4g')}"
                      f"{cell(metrics[f'{name}/motion_gain/{g}'], 7, '.3f')}"
                      for name in references))
    if constant:
        lines.append(f"n/a: {', '.join(constant)} never move(s) in the held-out chunks (holding "
                     "the previous action is exact there: no skill to score)")
    if "state_copy" in references and all(
            metrics[f"state_copy/err/{g}"] == metrics[f"persistence/err/{g}"]
            for g in layout.group_names):
        lines.append("state copy = persistence: the state maps to no action group "
                     "(data.state_groups or a state preset places it), so copying it holds the "
                     "previous action")
    if not layout.groups_with_role("gripper"):  # hands are joints: no switch to count
        return "\n".join(lines)
    counts = "/".join(str(int(metrics[f"gripper_switch/{k}"])) for k in ("tp", "fp", "fn"))
    lines.append("gripper switches (each event once): " + ", ".join(
        f"{name} {metrics[f'gripper_switch/{name}']:.3f}" for name in ("precision", "recall", "f1"))
        + f", TP/FP/FN {counts}")
    return "\n".join(lines)


# ---------------------------------------------------------------------- offline entrypoint

def run_evaluator(run: restore.RestoredRun) -> tuple[Evaluator, jax.sharding.Mesh]:
    """The `Evaluator` of a restored run (its own config, norm stats and data) on one device,
    and the mesh to call it under."""
    config, layout, model_config = run.config, run.layout, run.model_config
    mesh = sharding_lib.make_mesh(1)
    spec = DataSpec.from_config(config, layout)
    source = sources.open_source(spec.options, layout)
    tokenize = tokenizer_lib.make_tokenizer(config.model, prompts=source.tasks)
    with jax.set_mesh(mesh):
        evaluator = Evaluator.for_policy(
            spec, config.eval, model_config, run.norm_stats, tokenize, mesh=mesh,
            params_sharding=sharding_lib.tree_shardings(run.params, mesh), source=source,
            noise_factor=restore.run_noise_factor(run.workdir, config, layout, model_config),
            sampling=run.sampling)
    return evaluator, mesh


def heldout_paths(workdir: epath.PathLike, step: int, levers: str = ""
                  ) -> tuple[epath.Path, epath.Path]:
    """An offline evaluation's `eval/step_<N>/metrics[levers].json` and its per-chunk sums
    (`chunk_sums_lib.CHUNK_SUMS_FILE`, tagged the same): `levers` is `Sampling.tag` of the
    sampler, so that another setting never replaces the plain sampler's files."""
    out = epath.Path(workdir) / "eval" / f"step_{step}"
    sums = epath.Path(chunk_sums_lib.CHUNK_SUMS_FILE)
    return (out / f"{epath.Path(METRICS_FILE).stem}{levers}.json",
            out / f"{sums.stem}{levers}{sums.suffix}")
