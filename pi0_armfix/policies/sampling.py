"""How a policy turns its flow into the actions a robot executes: the sampling and execution
levers in one typed place, read the same way by the held-out evaluator, the closed loop, the
server and the export.

    sampling = Sampling.from_eval(run.config.eval, average_draws=4)  # a command's --average_draws
    sample = sampling.sampler(model_config, noise_factor)            # flow_model.sample_actions
    latch = sampling.latch(layout)                                   # the grippers' hysteresis
    replanning = execution.Replanner(policy)                         # n_exec, rtc, ensembling, deadband

Sampled levers (`SAMPLED_LEVERS`) change the chunks the flow gives, so an open-loop evaluation
measures them; execution levers (`EXECUTION_LEVERS`) change what is executed of them over time
(`policies.execution`), so only a closed loop (or a robot) does.

How a policy executes is a choice of the command that runs it, never of what it trained on
(`Sampling.for_run`): the execution (`eval.execution`, a command's `--execution`; `EXECUTIONS`)
sets every lever, `eval.<lever>` keys that a run sets (None: unset) replace its values, and a
command's lever flags (`console.define_lever_flags`) replace those. No shipped config sets a lever,
so every config a study compares executes alike; the study names the execution in its tables.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import flow_model
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.policies import hysteresis

# The levers a study's lever variant may set on a trained config
# (`arm_focused@eval.average_draws=4`).
# Sampled levers change the chunks the held-out evaluation scores (the deadband too: it needs only
# the previous command, which every held-out chunk has); execution levers act over time.
SAMPLED_LEVERS = ("average_draws", "temperature", "group_draws", "deadband")
EXECUTION_LEVERS = ("n_exec", "rtc", "temporal_ensemble", "gripper_hysteresis")
LEVERS = SAMPLED_LEVERS + EXECUTION_LEVERS

# The executions a command may choose (`eval.execution`, `--execution`): 'adopted' is the world's
# adopted execution where the run's world has one (`adopted_execution`), else every lever off;
# 'none' is every lever off (each chunk as sampled, `n_exec` half the horizon).
EXECUTIONS = ("adopted", "none")
# The levers a chunk-executing client (openpi's protocol) runs itself: a server leaves the
# adopted execution's out of its defaults and refuses them asked for.
CLIENT_LEVERS = ("rtc", "temporal_ensemble")


def check_levers(levers: Mapping[str, Any]) -> None:
    """Refuses a command's levers (`Sampling` fields, and `execution`) out of their range, before
    any work reads them.

    Raises:
      ValueError naming the lever or the execution and its range.
    """
    levers = dict(levers)
    execution = levers.pop("execution", None)
    if execution is not None and execution not in EXECUTIONS:
        raise ValueError(f"execution = {execution!r} (eval.execution or --execution) must be "
                         f"one of {EXECUTIONS}")
    Sampling.from_eval({}, **levers)


def adopted_execution(data_cfg: Mapping[str, Any], horizon: int) -> dict[str, Any]:
    """The adopted execution of the run's world: `{lever: value}`, {} where there is none.

    The demo world's (a run on the embedded demo, `data.root=''`), chosen on a validation world
    and measured over 5 seeds on the evaluation's (RESULTS.md, "Closed loop at the world's own
    tolerance"): every executed action the ensemble of the chunks covering it, replanned every
    quarter of the horizon (8 of 32 steps); the base the mean of 4 draws (it stops where the
    demonstrations stop), the torso of 8 and held within 2 action stds (it holds still).
    """
    if data_cfg.get("root", "") != "" or data_cfg.get("format", "lerobot") != "lerobot":
        return {}
    return {"n_exec": max(horizon // 4, 1), "temporal_ensemble": 0.01,
            "group_draws": "base=4+torso=8", "deadband": "torso=2"}


@dataclasses.dataclass(frozen=True)
class Sampling:
    """Attributes (each the `eval` key of its name):
      num_steps: Euler steps from noise to the chunk.
      average_draws: each executed chunk the mean of this many draws (the spread of one draw
        averaged away; the grippers' hysteresis sees the mean).
      temperature: the initial noise's scale, in (0, 1] (1 = the flow as trained).
      group_draws: `"group=k+group=k"`: those groups' dims the mean of k draws, the others
        of `average_draws` (the base and torso may want the spread averaged away where the arms
        do not); every mean includes the first draw. '' = every dim of `average_draws`.
      n_exec: actions executed of each chunk before the policy is asked again (0: half the
        horizon; `executed`).
      rtc: each new chunk softly follows the unexecuted tail of the last (real-time chunking's
        soft inpainting, from the flow's own noise law).
      temporal_ensemble: ACT's temporal ensembling: each executed action the weighted mean of
        every chunk still covering its step, weight exp(-m i) for the i-th oldest (m = this
        value, > 0; the oldest weighs most); 0 = off.
      deadband: `"group=k+group=k"`: a group holds still where the policy commands less than
        k times each dim's action std (the run's norm stats) of motion: a velocity group
        (`layout.velocity_groups`, the base) is commanded 0 at a step whose every command is
        within its band (the stop the demonstrations make, which the sampler's spread blurs), a
        position group keeps its last command until one leaves the band around it
        (`execution.hold_still`). '' = off.
      gripper_hysteresis: (open_above, close_below) in action units that the gripper commands
        pass (`hysteresis`), or () for the commands as sampled.
    """

    num_steps: int = 10
    average_draws: int = 1
    temperature: float = 1.0
    group_draws: str = ""
    n_exec: int = 0
    rtc: bool = False
    temporal_ensemble: float = 0.0
    deadband: str = ""
    gripper_hysteresis: tuple[float, ...] = ()

    def __post_init__(self):
        given = self.gripper_hysteresis
        try:
            thresholds = tuple(float(x) for x in (given.split(",") if isinstance(given, str)
                                                  else given) if str(x).strip())
        except (TypeError, ValueError):
            raise ValueError(f"gripper_hysteresis = {self.gripper_hysteresis!r} "
                             f"({_where('gripper_hysteresis')}) must be two numbers, "
                             "open_above,close_below") from None
        object.__setattr__(self, "gripper_hysteresis", thresholds)
        for field, least in (("num_steps", 1), ("average_draws", 1), ("n_exec", 0)):
            value = getattr(self, field)
            number = _number(value)
            if not number == int(number if math.isfinite(number) else 0) or number < least:
                raise ValueError(f"{field} = {value} ({_where(field)}) must be a whole number "
                                 f">= {least}")
            object.__setattr__(self, field, int(number))
        rtc = self.rtc
        if isinstance(rtc, str):
            rtc = {"true": True, "1": True, "false": False, "0": False}.get(rtc.lower(), rtc)
        if not isinstance(rtc, (bool, np.bool_)) and rtc not in (0, 1):
            raise ValueError(f"rtc = {self.rtc!r} ({_where('rtc')}) must be true or false")
        object.__setattr__(self, "rtc", bool(rtc))
        if not _number(self.temporal_ensemble) >= 0:
            raise ValueError(f"temporal_ensemble = {self.temporal_ensemble} "
                             f"({_where('temporal_ensemble')}) must be >= 0 (0: off)")
        object.__setattr__(self, "temporal_ensemble", _number(self.temporal_ensemble))
        for field in ("group_draws", "deadband"):
            object.__setattr__(self, field, str(getattr(self, field) or ""))
        self.group_counts(), self.deadbands()  # their syntax, before any use
        object.__setattr__(self, "temperature", _number(self.temperature))
        if not 0.0 < self.temperature <= 1.0:
            raise ValueError(f"temperature = {self.temperature} ({_where('temperature')}) "
                             "must be in (0, 1] (the initial noise's scale; 1 = the flow as "
                             "trained)")
        hysteresis.check_thresholds(self.gripper_hysteresis,
                                    f"gripper_hysteresis ({_where('gripper_hysteresis')})")

    @property
    def most_draws(self) -> int:
        """The draws each chunk needs: the most any dim averages."""
        return max([self.average_draws, *self.group_counts().values()])

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
        values = {name: default if eval_cfg.get(name) is None else eval_cfg[name]
                  for name, default in fields.items()}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    @classmethod
    def for_run(cls, config: Mapping[str, Any], execution: str | None = None,
                client_executes: bool = False, horizon: int | None = None,
                **overrides: Any) -> Sampling:
        """The levers a command runs a trained config with: `execution` (None: the run's
        `eval.execution`, 'adopted' where it predates the key; `EXECUTIONS`), then the `eval`
        levers the run sets, then `overrides` (a command's; None = unset).
        `client_executes`: the client runs the chunks (openpi's protocol), so the execution's
        `CLIENT_LEVERS` are not among the defaults.

        Args:
          config: the run's config (its `eval`, `data` and `model` sections).
          horizon: the model's H where the caller has resolved it (else from `model`).
        Raises:
          ValueError naming the execution or the lever, for one that is unknown or out of its
          range.
        """
        eval_cfg = config["eval"]
        execution = execution or eval_cfg.get("execution") or "adopted"
        check_levers({"execution": execution})
        horizon = horizon or model_config_lib.from_model_config(config["model"]).action_horizon
        adopted = adopted_execution(config["data"], horizon) if execution == "adopted" else {}
        if client_executes:
            adopted = {k: v for k, v in adopted.items() if k not in CLIENT_LEVERS}
        own = {k: eval_cfg.get(k) for k in LEVERS if eval_cfg.get(k) is not None}
        return cls.from_eval({**adopted, **own, "num_steps": eval_cfg.get("num_steps")},
                             **overrides)

    def group_counts(self, layout: ActionLayout | None = None) -> dict[str, int]:
        """`group_draws` as `{group: k}` ({} when unset), its groups checked against `layout`.

        Raises:
          ValueError naming the item, for one that is not `group=k` with a whole k >= 1, or a
          group the layout lacks.
        """
        return _per_group(self.group_draws, "group_draws", int, "a whole k >= 1",
                          "base=4+torso=8", layout)

    def deadbands(self, layout: ActionLayout | None = None) -> dict[str, float]:
        """`deadband` as `{group: k}` ({} when unset), its groups checked against `layout`.

        Raises:
          ValueError naming the item, for one that is not `group=k` with k > 0, or a group the
          layout lacks.
        """
        return _per_group(self.deadband, "deadband", float, "k > 0", "base=0.2+torso=0.5",
                          layout)

    def draw_counts(self, layout: ActionLayout) -> tuple[int, ...] | None:
        """Draws averaged into each of `layout`'s padded action dims `[action_dim]` (None where
        every dim takes `average_draws`).

        Raises:
          ValueError naming a `group_draws` group the layout lacks.
        """
        counts = self.group_counts(layout)
        per_dim = np.full(layout.action_dim, self.average_draws)
        for group, k in counts.items():
            per_dim[layout.group_dims(group)] = k
        return None if (per_dim == self.average_draws).all() else tuple(int(k) for k in per_dim)

    def executed(self, horizon: int) -> int:
        """The actions executed of each chunk: `n_exec`, or half the `horizon` for 0 (each
        chunk's second half then only shapes the next plan).

        Raises:
          ValueError where it exceeds the horizon, or leaves no tail to follow with `rtc`.
        """
        n_exec = self.n_exec or max(horizon // 2, 1)
        if n_exec > horizon or (self.rtc and n_exec == horizon):
            raise ValueError(f"n_exec = {n_exec} ({_where('n_exec')}) must be in [1, H = "
                             f"{horizon}]" + (" and below H with rtc (the tail to follow)"
                                              if self.rtc else ""))
        return n_exec

    def tag(self, closed_loop: bool = False, against: Sampling | None = None) -> str:
        """The suffix of result files that another setting must not replace: one part per lever
        that differs from `against` (a run's own levers, `Sampling.from_eval(run.config.eval)`;
        None: the defaults here), so that the files a run's own levers write carry none.
        Sampled levers: `_avg<k>`, `_temp<τ>`, `_draws-<group><k>...`,
        `_deadband-<group><k>...`; for a closed loop also the execution levers: `_exec<n>`,
        `_rtc`, `_hysteresis`, `_ens<m>`. A lever turned off where `against` has it on is named
        off: `_draws-off`, `_deadband-off`, `_nortc`, `_nohysteresis`, `_ens0`."""
        base = against or Sampling()

        def part(field: str, text: str) -> str:
            return text if getattr(self, field) != getattr(base, field) else ""

        per_group = {field: "-".join(f"{g}{k:g}" for g, k in counts.items()) or "off"
                     for field, counts in (("group_draws", self.group_counts()),
                                           ("deadband", self.deadbands()))}
        tag = (part("average_draws", f"_avg{self.average_draws}")
               + part("temperature", f"_temp{self.temperature:g}")
               + part("group_draws", f"_draws-{per_group['group_draws']}")
               + part("deadband", f"_deadband-{per_group['deadband']}"))
        if closed_loop:
            tag = (part("n_exec", f"_exec{self.n_exec}")
                   + part("rtc", "_rtc" if self.rtc else "_nortc")
                   + part("gripper_hysteresis",
                          "_hysteresis" if self.gripper_hysteresis else "_nohysteresis")
                   + tag + part("temporal_ensemble", f"_ens{self.temporal_ensemble:g}"))
        return tag

    def describe(self) -> dict[str, Any]:
        """The levers as JSON values (a server's metadata, a result file's settings)."""
        return {"num_steps": self.num_steps, "average_draws": self.average_draws,
                "temperature": self.temperature, "group_draws": self.group_draws or None,
                "n_exec": self.n_exec, "rtc": self.rtc,
                "temporal_ensemble": self.temporal_ensemble,
                "deadband": self.deadband or None,
                "gripper_hysteresis": list(self.gripper_hysteresis) or None}

    def summary(self) -> str:
        """The levers off their defaults in words ("every lever off" where none is): what a
        table names as the execution its numbers were measured with."""
        default, parts = Sampling().describe(), []
        for name, value in self.describe().items():
            if value != default[name]:
                parts.append(f"{name} {value if not isinstance(value, list) else tuple(value)}")
        return ", ".join(parts) or "every lever off"

    def noise(self, rng: jax.Array, shape: Sequence[int],
              noise_factor: np.ndarray | None = None) -> jax.Array:
        """The initial noise of `shape` `[N, H, A]` scaled by the temperature, as the sampler
        draws it from `rng` (`noise.flow_noise`)."""
        return self.temperature * noise_lib.flow_noise(rng, tuple(shape), noise_factor)

    def sampler(self, model_config: model_config_lib.Pi0Config,
                noise_factor: np.ndarray | None = None, num_draws: int | None = None,
                layout: ActionLayout | None = None
                ) -> Callable[..., jax.Array]:
        """`flow_model.sample_actions` with these levers: `(params, rng, observation, **kw) ->
        [B, H, A]` (each dim the mean of its draws: `average_draws`, or `group_draws` on
        `layout`), or with `num_draws` M every draw `[M, B, H, A]` from the noise it is given
        (`noise`, already scaled)."""
        return functools.partial(
            flow_model.sample_actions, config=model_config, num_steps=self.num_steps,
            noise_factor=noise_factor, average_draws=self.average_draws,
            temperature=self.temperature, num_draws=num_draws,
            draw_counts=None if layout is None else self.draw_counts(layout))

    def check(self, layout: ActionLayout, horizon: int) -> None:
        """Every lever against a run's layout and horizon `H`, as a closed loop or a server
        would use them (a training run checks its own before its first step).

        Raises:
          ValueError naming the lever: a group the layout lacks, `n_exec` beyond the horizon,
          a hysteresis without grippers.
        """
        self.draw_counts(layout), self.deadbands(layout), self.executed(horizon)
        self.latch(layout)

    def latch(self, layout: ActionLayout | None) -> hysteresis.GripperLatch | None:
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


def _number(value: Any) -> float:
    """`value` as a float (a config's number, a flag's or a study override's text); NaN where it
    is none, so that the range checks name it."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _per_group(text: str, field: str, cast: Callable[[str], float], allowed: str,
               example: str, layout: ActionLayout | None) -> dict[str, Any]:
    """`"group=value+group=value"` -> `{group: cast(value)}`, each value > 0 ({} for ''), the
    groups those of `layout` where one is given.

    Raises:
      ValueError naming the item and `field`, for a malformed one, or the groups `layout` lacks.
    """
    values = {}
    for item in filter(None, text.split("+")):
        group, _, value = item.partition("=")
        try:
            number = cast(value.strip())
        except ValueError:
            number = None
        if not group or number is None or not number > 0:
            raise ValueError(f"{field} item {item!r} ({_where(field)}) must be group=k with "
                             f"{allowed}, items joined by '+' (e.g. {example})")
        if group in values:
            raise ValueError(f"{field} names {group!r} twice ({_where(field)}: {text!r}); give "
                             "each group once")
        values[group] = number
    unknown = sorted(set(values) - set(layout.groups)) if layout is not None else []
    if unknown:
        raise ValueError(f"{field} names {unknown}, not groups of the run's layout "
                         f"{list(layout.groups)}")
    return values


def _where(field: str) -> str:
    """Where a lever is set: its `eval` key, and the flag of a command (`console`)."""
    return f"eval.{field}" + (f" or --{field}" if field in LEVERS else "")
