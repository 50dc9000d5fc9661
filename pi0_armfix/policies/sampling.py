"""How a policy turns its flow into the chunks a robot executes: the sampling and execution
levers in one typed place, read the same way by the held-out evaluator, the closed loop, the
server and the export.

    sampling = Sampling.from_eval(run.config.eval, average_draws=4)  # a command's --average_draws
    sample = sampling.sampler(model_config, noise_factor)            # flow_model.sample_actions
    latch = sampling.latch(layout)                                   # the grippers' hysteresis

A run keeps its levers in its config's `eval` section (`pi0_armfix/configs/base.py`); a command
may replace them for its own use (`--average_draws`, `--temperature`, `--gripper_hysteresis`);
keys a run predates take their defaults here.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import flow_model
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model.config import Pi0Config
from pi0_armfix.policies import hysteresis

# The levers a study's lever variant may set on a trained config (`arm_focused@eval.average_draws=4`):
# they change the sampled chunks, so an open-loop evaluation measures them.
SAMPLED_LEVERS = ("average_draws", "temperature")


@dataclasses.dataclass(frozen=True)
class Sampling:
    """Attributes (each the `eval` key of its name):
      num_steps: Euler steps from noise to the chunk.
      average_draws: each executed chunk the mean of this many draws (the spread of one draw
        averaged away; the grippers' hysteresis sees the mean).
      temperature: the initial noise's scale, in (0, 1] (1 = the flow as trained).
      gripper_hysteresis: (open_above, close_below) in action units that the gripper commands
        pass (`hysteresis`), or () for the commands as sampled.
    """

    num_steps: int = 10
    average_draws: int = 1
    temperature: float = 1.0
    gripper_hysteresis: tuple[float, ...] = ()

    def __post_init__(self):
        try:
            thresholds = tuple(float(x) for x in self.gripper_hysteresis)
        except (TypeError, ValueError):
            raise ValueError(f"gripper_hysteresis = {self.gripper_hysteresis!r} (eval."
                             "gripper_hysteresis or --gripper_hysteresis) must be two numbers, "
                             "open_above,close_below") from None
        object.__setattr__(self, "gripper_hysteresis", thresholds)
        for field, where in (("num_steps", "eval.num_steps"),
                             ("average_draws", "eval.average_draws or --average_draws")):
            value = getattr(self, field)
            if float(value) != int(value) or int(value) < 1:
                raise ValueError(f"{field} = {value} ({where}) must be a whole number >= 1")
            object.__setattr__(self, field, int(value))
        object.__setattr__(self, "temperature", float(self.temperature))
        if not 0.0 < self.temperature <= 1.0:
            raise ValueError(f"temperature = {self.temperature} (eval.temperature or "
                             "--temperature) must be in (0, 1] (the initial noise's scale; 1 = "
                             "the flow as trained)")
        hysteresis.check_thresholds(self.gripper_hysteresis,
                                    "gripper_hysteresis (eval.gripper_hysteresis or "
                                    "--gripper_hysteresis)")

    @classmethod
    def from_eval(cls, eval_cfg: Mapping[str, Any], **overrides: Any) -> Sampling:
        """The levers of a run's `eval` section (its defaults for keys it predates), with
        `overrides` (a command's; None = the run's) in their place.

        Raises:
          ValueError naming the lever, for an unknown one or a value out of its range.
        """
        fields = {f.name: f.default for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - set(fields))
        if unknown:
            raise ValueError(f"unknown inference lever(s) {unknown}; the levers are "
                             f"{list(fields)}")
        values = {name: eval_cfg.get(name, default) for name, default in fields.items()}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    def tag(self) -> str:
        """`_avg<k>_temp<τ>` for sampled levers other than the plain sampler's (each part only
        when set): the suffix of result files that another setting must not replace."""
        return ((f"_avg{self.average_draws}" if self.average_draws != 1 else "")
                + (f"_temp{self.temperature:g}" if self.temperature != 1.0 else ""))

    def describe(self) -> dict[str, Any]:
        """The levers as JSON values (a server's metadata, a result file's settings)."""
        return {"num_steps": self.num_steps, "average_draws": self.average_draws,
                "temperature": self.temperature,
                "gripper_hysteresis": list(self.gripper_hysteresis) or None}

    def noise(self, rng: jax.Array, shape: Sequence[int],
              noise_factor: np.ndarray | None = None) -> jax.Array:
        """The initial noise of `shape` `[N, H, A]` scaled by the temperature, as the sampler
        draws it from `rng` (`noise.flow_noise`)."""
        return self.temperature * noise_lib.flow_noise(rng, tuple(shape), noise_factor)

    def sampler(self, model_config: Pi0Config, noise_factor: np.ndarray | None = None,
                num_draws: int | None = None) -> Callable[..., jax.Array]:
        """`flow_model.sample_actions` with these levers: `(params, rng, observation, **kw) ->
        [B, H, A]` (the mean of `average_draws` draws), or with `num_draws` M every draw
        `[M, B, H, A]` from the noise it is given (`noise`, already scaled)."""
        return functools.partial(
            flow_model.sample_actions, config=model_config, num_steps=self.num_steps,
            noise_factor=noise_factor, average_draws=self.average_draws,
            temperature=self.temperature, num_draws=num_draws)

    def latch(self, layout: ActionLayout) -> hysteresis.GripperLatch | None:
        """The grippers' hysteresis on `layout`'s gripper dims, or None without one.

        Raises:
          ValueError where a hysteresis is set on a layout without a gripper group.
        """
        if not self.gripper_hysteresis:
            return None
        dims = [d for g in layout.groups_with_role("gripper") for d in layout.group_dims(g)]
        if not dims:
            raise ValueError("gripper_hysteresis is set but the layout has no group of role "
                             "gripper (layout.roles); set it to ()")
        return hysteresis.GripperLatch(dims, *self.gripper_hysteresis)
