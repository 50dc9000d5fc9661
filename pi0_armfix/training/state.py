"""The train state: everything a step reads and writes, and everything a checkpoint holds on device.

The adaptive loss strategies keep their state here so that it is sharded, donated and checkpointed
with the params: `loss_balanced` its EMA of the per-group losses (`balancer`), `uncertainty` its
learned per-group log-variances (`loss_params`, trained by the optimizer with the params).

Under LoRA (`training/freeze.py`) `params` holds the frozen weights in bfloat16 beside the trained
ones; the optimizer's state and the EMA cover the trained ones only.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from pi0_armfix import loss as loss_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model.config import Pi0Config
from pi0_armfix.training import freeze


@flax.struct.dataclass
class TrainState:
    """Attributes:
      step: int32 `[]`, the number of optimizer steps taken.
      params: the model's parameter tree (frozen leaves in bfloat16).
      loss_params: trainable loss parameters: `{"log_vars": [G]}` for `uncertainty`, else `{}`.
      opt_state: optimizer state over `trainable(model_config)`.
      ema_params: EMA of `params` (same tree; a frozen leaf is its own EMA), or None when
        `optim.ema_decay` is 0.
      balancer: `{"ema": [G], "count": int32 []}` for `loss_balanced`, else `{}`.
    """

    step: jax.Array
    params: Any
    loss_params: dict[str, jax.Array]
    opt_state: Any
    ema_params: Any
    balancer: dict[str, jax.Array]

    def trainable(self, model_config: Pi0Config) -> dict[str, Any]:
        """The tree the optimizer updates: the params that train (`freeze.split`), the loss's."""
        return {"params": freeze.split(self.params, model_config)[0],
                "loss_params": self.loss_params}


def create_train_state(params: Any, *, model_config: Pi0Config, tx: optax.GradientTransformation,
                       loss_cfg: Mapping[str, Any], layout: ActionLayout,
                       ema_decay: float) -> TrainState:
    """The state at step 0 around `params` (float32; jit it with out_shardings to build it
    sharded)."""
    num_groups = layout.num_groups
    strategy = loss_lib.loss_strategy(loss_cfg["strategy"])
    loss_params = ({"log_vars": jnp.zeros((num_groups,), jnp.float32)}
                   if strategy.learns_log_vars else {})
    balancer = ({"ema": jnp.zeros((num_groups,), jnp.float32), "count": jnp.zeros((), jnp.int32)}
                if strategy.balances else {})
    params = freeze.store_frozen(params, model_config)
    trainable = {"params": freeze.split(params, model_config)[0], "loss_params": loss_params}
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        loss_params=loss_params,
        opt_state=tx.init(trainable),
        ema_params=jax.tree.map(jnp.copy, params) if ema_decay > 0 else None,
        balancer=balancer,
    )
