"""A training run's config, read once: `RunSpec.resolve(config)`.

Every check of the config that needs no data runs here, each failure one error naming the key,
and every module is then handed the part it needs, never the config:

    layout     action_space.ActionLayout        the action dims, groups and roles
    model      model.config.Pi0Config           the network; `model_section` for the tokenizer
    data       data.data_spec.DataSpec          split, representation, normalization, sampling
    loss       the checked `loss` section       the train step's loss (`training.step`)
    tx, schedule                                the optimizer (`training.optimizer`)
    train, eval, optim, sharding                their checked sections

The normalization is resolved here too (`data.norm`, else the model's), and written back into the
config before it is kept as `config_json`: what the run folder's `config.json` and every
checkpoint hold, and what a resume is checked against.

    spec = RunSpec.resolve(config)     # ValueError naming the key, before any I/O
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from typing import Any

import ml_collections
import optax

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import pretrained
from pi0_armfix.training import fingerprint
from pi0_armfix.training import optimizer as optimizer_lib
from pi0_armfix.training import step as step_lib


@dataclasses.dataclass(frozen=True, eq=False)
class RunSpec:
    """A training run's parts, resolved and checked (`resolve`); see the module docstring."""

    config_json: dict[str, Any]
    layout: ActionLayout
    model: model_config_lib.Pi0Config
    model_section: dict[str, Any]
    data: DataSpec
    loss: dict[str, Any]
    optim: dict[str, Any]
    tx: optax.GradientTransformation
    schedule: optax.Schedule
    notes: tuple[str, ...]  # lines the run says before it starts (a shortened warmup, ...)
    train: dict[str, Any]
    eval: dict[str, Any]
    fsdp: int
    seed: int
    uses_chunk_stats: bool

    @classmethod
    def resolve(cls, config: ml_collections.ConfigDict) -> "RunSpec":
        """Reads and checks every section of `config`; resolves `data.norm` and, where
        `eval.evaluations` is set, `eval.every` in it.

        Raises:
          ValueError naming the key and the fix.
        """
        layout = ActionLayout.from_config(config.layout)
        model = model_config_lib.from_model_config(config.model)
        config.data.norm = config.data.get("norm") or model.default_norm
        evaluations = int(config.eval.get("evaluations") or 0)
        if evaluations < 0:
            raise ValueError(f"eval.evaluations = {evaluations} must be >= 0 (0: eval.every "
                             "decides)")
        if evaluations:  # spread over this run's steps, whatever train.total_steps became
            config.eval.every = max(1, int(config.train.total_steps) // evaluations)
        if model.action_dim != layout.action_dim:
            raise ValueError(f"layout.action_dim = {layout.action_dim} but the model (preset "
                             f"{config.model.preset!r}, model.action_dim="
                             f"{config.model.action_dim}) has action_dim {model.action_dim}: set "
                             "both to the same width (actions wider than 32 need "
                             "model.action_dim; pretrained pi0 params need 32)")
        loss = config.loss.to_dict()
        step_lib.check_loss_config(loss, layout)
        train = config.train.to_dict()
        check_train_config(train)
        if config.model.pretrained:
            pretrained.check_pretrained(config.model.pretrained, model)
        if config.data.root is None:
            raise ValueError("data.root is unset: the b1k scale needs --config.data.root=<LeRobot "
                             "B1K root> ('' = the built-in demo dataset)")
        optim = config.optim.to_dict()
        tx, schedule = optimizer_lib.make_optimizer(optim, train["total_steps"])
        _, warmup_note = optimizer_lib.effective_warmup(optim, train["total_steps"])
        notes = (warmup_note,) if warmup_note else ()
        if model.lora_experts and not config.model.pretrained:
            notes += (f"model.lora = {model.lora_experts} without model.pretrained: the adapters "
                      "fine-tune frozen random weights; point model.pretrained at the base "
                      "model's params (openpi's pi0_base / pi05_base)",)
        data = DataSpec.from_config(config, layout, norm=config.data.norm)
        return cls(
            config_json=json.loads(config.to_json_best_effort()), layout=layout, model=model,
            model_section=config.model.to_dict(), data=data, loss=loss, optim=optim, tx=tx,
            schedule=schedule, notes=notes, train=train,
            eval=config.eval.to_dict(), fsdp=int(config.sharding.fsdp), seed=int(config.seed),
            uses_chunk_stats=bool(config.data.norm_per_timestep) or loss["noise_beta"] < 1.0)

    @property
    def evaluates(self) -> bool:
        """Whether the run evaluates on its held-out episodes while training."""
        return int(self.eval["every"]) > 0


def check_train_config(train: Mapping[str, Any]) -> None:
    """Raises ValueError naming the `train.*` key that is out of range."""
    for field in ("total_steps", "log_every", "checkpoint_every", "keep_checkpoints"):
        if int(train[field]) <= 0:
            raise ValueError(f"train.{field} = {train[field]} must be positive")
    if train["resume"] not in fingerprint.RESUME_MODES:
        raise ValueError(f"train.resume = {train['resume']!r}: use one of "
                         f"{fingerprint.RESUME_MODES}")
