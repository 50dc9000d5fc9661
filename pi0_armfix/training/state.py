"""The train state: everything a step reads and writes, and everything a checkpoint holds on device.

The adaptive loss strategies keep their state here so that it is sharded, donated and checkpointed
with the params: `loss_balanced` its EMA of the per-group losses (`balancer`), `uncertainty` its
learned per-group log-variances (`loss_params`, trained by the optimizer with the params).
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


@flax.struct.dataclass
class TrainState:
    """Attributes:
      step: int32 `[]`, the number of optimizer steps taken.
      params: the model's parameter tree.
      loss_params: trainable loss parameters: `{"log_vars": [G]}` for `uncertainty`, else `{}`.
      opt_state: optimizer state over `{"params": params, "loss_params": loss_params}`.
      ema_params: EMA of `params` (same tree), or None when `optim.ema_decay` is 0.
      balancer: `{"ema": [G], "count": int32 []}` for `loss_balanced`, else `{}`.
    """

    step: jax.Array
    params: Any
    loss_params: dict[str, jax.Array]
    opt_state: Any
    ema_params: Any
    balancer: dict[str, jax.Array]

    @property
    def trainable(self) -> dict[str, Any]:
        """The tree the optimizer updates."""
        return {"params": self.params, "loss_params": self.loss_params}


def create_train_state(params: Any, *, tx: optax.GradientTransformation,
                       loss_cfg: Mapping[str, Any], layout: ActionLayout,
                       ema_decay: float) -> TrainState:
    """The state at step 0 around `params` (jit it with out_shardings to build it sharded)."""
    num_groups = layout.num_groups
    strategy = loss_lib.loss_strategy(loss_cfg["strategy"])
    loss_params = ({"log_vars": jnp.zeros((num_groups,), jnp.float32)}
                   if strategy.learns_log_vars else {})
    balancer = ({"ema": jnp.zeros((num_groups,), jnp.float32), "count": jnp.zeros((), jnp.int32)}
                if strategy.balances else {})
    trainable = {"params": params, "loss_params": loss_params}
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        loss_params=loss_params,
        opt_state=tx.init(trainable),
        ema_params=jax.tree.map(jnp.copy, params) if ema_decay > 0 else None,
        balancer=balancer,
    )
