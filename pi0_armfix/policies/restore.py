"""A run folder's checkpoint with what it needs to run: its own config (every `eval` key it
predates at today's default), layout, model config, norm stats and sampling levers
(`RestoredRun`, `restore_run`). Read by the policy (`policies.inference`), the evaluation, the
export and the study; a damaged latest checkpoint falls back to the newest one that reads.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Mapping
from typing import Any

import ml_collections
import numpy as np
from etils import epath

from pi0_armfix import sharding as sharding_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import base as base_config
from pi0_armfix.data.pipeline import chunk_stats as chunk_stats_lib
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.policies.sampling import Sampling, check_levers
from pi0_armfix.training import checkpoint


def norm_stats_from_json(payload: Mapping[str, Any]) -> dict[str, stats_lib.NormStats]:
    """`{"norm_stats": {key: {mean, std, q01, q99}}}` (as checkpointed) -> `{key: NormStats}`."""
    return {key: stats_lib.NormStats(**{f: np.asarray(entry[f], np.float64)
                                        for f in stats_lib.FIELDS})
            for key, entry in payload["norm_stats"].items()}


def run_noise_factor(workdir: epath.Path, config: ml_collections.ConfigDict,
                     layout: ActionLayout, model_config: model_config_lib.Pi0Config
                     ) -> np.ndarray | None:
    """The correlated noise factor a run trained with (`loss.noise_beta < 1`), from the chunk
    correlation in its workdir; None for pi0's independent noise."""
    beta = float(config.loss.get("noise_beta", 1.0))
    if beta >= 1.0:
        return None
    path = workdir / chunk_stats_lib.CORRELATION_FILE
    if not path.exists():
        raise ValueError(f"{path} is missing: the run trained with correlated noise "
                         f"(loss.noise_beta = {beta}) and its policy samples from the same law")
    return noise_lib.correlated_noise_factor(
        np.load(path), beta, horizon=model_config.action_horizon, real_dim=layout.real_dim,
        action_dim=layout.action_dim)


def with_current_keys(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """A run's saved config with every `eval` key it predates at its default
    (`pi0_armfix/configs/base.py`): how a policy is sampled and scored, which training never
    read."""
    defaults = base_config.get_config().eval
    config = ml_collections.ConfigDict(config.to_dict())
    with config.unlocked():
        for key, value in defaults.items():
            if key not in config.eval:
                config.eval[key] = value
    return config


@dataclasses.dataclass(frozen=True)
class RestoredRun:
    """A run's checkpoint with what it needs to run: its own config, layout and norm stats."""

    workdir: epath.Path
    step: int
    config: ml_collections.ConfigDict
    layout: ActionLayout
    model_config: model_config_lib.Pi0Config
    params: Any
    params_name: str  # "ema_params" or "params"
    norm_stats: dict[str, stats_lib.NormStats]
    sampling: Sampling  # the run's levers, a command's in their place
    ema_kept: bool = False  # the checkpoint holds EMA params (read unless "params" was asked)

    def result_tag(self, closed_loop: bool = False) -> str:
        """The suffix of this evaluation's result files: `Sampling.tag` of its levers against the
        run's own (the execution levers too for a closed loop), and `_params` where the raw
        params were read although the run kept an EMA, so that neither replaces the default
        evaluation's files (the EMA's, with the levers of the run's config)."""
        raw = self.ema_kept and self.params_name == "params"
        own = Sampling.for_run(self.config)
        return self.sampling.tag(closed_loop, against=own) + ("_params" if raw else "")


def episode_start_warning(workdir: epath.PathLike) -> str | None:
    """A line where a run's statistics (and so its training) predate today's episode-start rule
    (`transforms.EPISODE_START`), which its evaluation, closed loop and server apply; None where
    they match or nothing is relative to the previous command."""
    rule = dataset_lib.run_episode_start(workdir)
    if rule is None or rule == transforms.EPISODE_START:
        return None
    return (f"warning: {workdir} was trained with an episode's first chunk relative to "
            f"{rule or 'the state (an earlier rule; its norm_stats.key.json names none)'}; it is "
            f"evaluated and served under today's rule ({transforms.EPISODE_START}): episodes' "
            "first chunks and a connection's first request differ from its training; retrain "
            "to compare it like for like")


def restore_run(workdir: epath.PathLike, step: int | None = None, params_name: str = "ema",
                levers: Mapping[str, Any] | None = None, client_executes: bool = False
                ) -> RestoredRun:
    """The checkpoint of `step` (latest if None) of a run folder, on one device. `params_name`:
    "ema" (the EMA params when the run kept them, else the params) or "params"; `levers`: the
    `Sampling` fields that replace the run's (None values: the run's) and `execution` in place of
    the run's `eval.execution`, checked before any checkpoint is read; `client_executes`: for a
    client that executes the chunks itself (`Sampling.for_run`). Only the params are read. A
    damaged latest checkpoint falls back to the newest older one that reads (said on stderr); a
    damaged `step` asked for is a ValueError naming the steps that read."""
    workdir = epath.Path(workdir)
    levers = dict(levers or {})
    check_levers(levers)  # a bad lever fails before the checkpoint is read
    execution = levers.pop("execution", None)
    ckpts = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True)
    steps = ckpts.all_steps()
    if step is not None and step not in steps or not steps:
        raise ValueError(f"{workdir / 'checkpoints'} has no checkpoint "
                         f"{'at all' if not steps else f'of step {step}'} (steps: {steps})")
    mesh = sharding_lib.make_mesh(1)
    damaged = []
    for candidate in ([step] if step is not None else reversed(steps)):
        try:
            state, norm_stats, config = ckpts.restore_for_eval(candidate, mesh)
        except checkpoint.DamagedCheckpointError as e:
            damaged.append(e)
            continue
        if damaged:
            print(f"warning: {damaged[0]}; reading step {candidate}, the newest that reads",
                  file=sys.stderr)
        step = candidate
        break
    else:
        others = "" if step is None else f" (the run's steps: {steps}; ask for another)"
        raise ValueError("; ".join(str(e) for e in damaged)
                         + f": no checkpoint to read{others}. Restore the files or "
                         "train on to write a new one")
    use_ema = params_name == "ema" and bool(state.get("ema_params"))
    config = with_current_keys(config)
    if (warning := episode_start_warning(workdir)) is not None:
        print(warning, file=sys.stderr)
    return RestoredRun(workdir, step, config, ActionLayout.from_config(config.layout),
                       model_config_lib.from_model_config(config.model),
                       state["ema_params"] if use_ema else state["params"],
                       "ema_params" if use_ema else "params", norm_stats_from_json(norm_stats),
                       Sampling.for_run(config, execution, client_executes, **levers),
                       bool(state.get("ema_params")))
