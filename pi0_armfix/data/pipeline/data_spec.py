"""The data side of a run, read from its config once: `DataSpec.from_config(config, layout)`.

Every data function (`dataset`, `sampling`, `pipeline`, `chunk_stats`) takes the spec, never the
config: which layout the actions follow, which episodes train and which are held out, how actions
are represented (delta dims) and normalized, which state dims the policy sees, how samples are
drawn (curriculum, stream) and read (workers, prefetch). Two typed views say what their readers
take, each key at `configs/base.py`'s default where a config leaves it unset: `reading` (the
source, the probe, the frame cache, the stream, the workers) and `statistics` (a norm-stats file,
balanced or per-timestep statistics). The config's `data` section stays beside them as plain
values (`options`), for the two readers that take it as a whole: opening the source
(`sources.open_source`) and the statistics cache's key (`dataset.norm_stats_key`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import base as base_config
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data.pipeline import curriculum as curriculum_lib
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.model import config as model_config_lib


@functools.cache
def _defaults() -> dict[str, Any]:
    return base_config.get_config().data.to_dict()


@dataclasses.dataclass(frozen=True)
class _View:
    """A typed view of some `data.*` keys: each dataclass field is a key."""

    @classmethod
    def from_options(cls, options: Mapping[str, Any]):
        """The view of `options` (`config.data` as plain values), each unset key at its
        `configs/base.py` default."""
        defaults = _defaults()
        values = {}
        for field in dataclasses.fields(cls):
            value, default = options.get(field.name), defaults[field.name]
            values[field.name] = default if value is None else type(default)(value)
        return cls(**values)


@dataclasses.dataclass(frozen=True)
class Reading(_View):
    """How the source is opened and its samples read (`data.<field>`, `configs/base.py`)."""

    root: str
    format: str
    state_key: str
    images: bool
    frame_cache: bool
    probe_episodes: int
    video_access: str
    stream_episodes: int
    stream_shuffle: int
    stream_stride: int
    num_workers: int
    prefetch: int
    arm_heavy_episodes: str  # the curriculum's episode list (filter_arm_heavy_episodes)


@dataclasses.dataclass(frozen=True)
class Statistics(_View):
    """Where the normalization statistics come from (`data.<field>`, `configs/base.py`)."""

    norm_stats: str  # a norm_stats.json to load; '' = computed into the workdir
    balanced_norm: bool
    balanced_max_scale: float
    norm_per_timestep: bool
    chunk_stats_chunks: int


@dataclasses.dataclass(frozen=True, eq=False)
class DataSpec:
    """What the data layer reads of a run's config, resolved (`from_config`).

    Attributes:
      layout: the action layout.
      options: `config.data` as plain values.
      seed: the run's seed (sample order, curriculum draws).
      heldout_episodes: `eval.episodes`: the dataset's last episodes, never trained on.
      eval_every, eval_batch_size: the held-out evaluation's schedule and batch (checked
        against the held-out chunks before any pass).
      total_steps: `train.total_steps` (0: not a training run).
      norm: the normalization ('zscore', 'quantile', ...): `data.norm`, else the model's.
      delta_mask: `[A]` bool, the action dims trained relative to the state; None = absolute.
      delta_reference: what they are relative to (`data.delta_reference`,
        `transforms.DELTA_REFERENCES`): "state" or "previous_action".
      state_preset: the state preset read ('' = every stored dim or `data.state_indices`).
      state_groups: the state's {group: (start, stop)} in the action order, or None.
      curriculum: the parsed `data.curriculum` (one phase of the full dataset when unset).
      reading, statistics: the typed views of the rest of `data` (module docstring).
    """

    layout: ActionLayout
    options: Mapping[str, Any]
    seed: int = 0
    heldout_episodes: int = 0
    eval_every: int = 0
    eval_batch_size: int = 0
    total_steps: int = 0
    norm: str = "zscore"
    delta_mask: np.ndarray | None = None
    delta_reference: str = "state"
    state_preset: str = ""
    state_groups: Mapping[str, Sequence[int]] | None = None
    curriculum: curriculum_lib.Curriculum = dataclasses.field(
        default_factory=lambda: curriculum_lib.Curriculum(curriculum_lib.parse_curriculum(()), 0))
    reading: Reading = dataclasses.field(default_factory=lambda: Reading.from_options({}))
    statistics: Statistics = dataclasses.field(
        default_factory=lambda: Statistics.from_options({}))

    @classmethod
    def from_config(cls, config: Mapping[str, Any], layout: ActionLayout,
                    norm: str | None = None) -> "DataSpec":
        """The spec of `config` (its `data`, `eval`, `train` and `seed`); `norm`: the run's
        resolved normalization (default `data.norm`, else the model's, else z-score).

        Raises:
          ValueError naming the key, for a delta mask the layout cannot have or a malformed
          curriculum.
        """
        data = config["data"]
        options = _plain(data)
        evaluation = config.get("eval") or {}
        seed = int(config.get("seed", 0) or 0)
        return cls(
            layout=layout, options=options, seed=seed,
            heldout_episodes=int(evaluation.get("episodes", 0)),
            eval_every=int(evaluation.get("every", 0)),
            eval_batch_size=int(evaluation.get("batch_size", 0)),
            total_steps=int((config.get("train") or {}).get("total_steps", 0)),
            norm=(norm or options.get("norm")
                  or (model_config_lib.norm_mode(config) if "model" in config else "zscore")),
            delta_mask=transforms.delta_action_mask(options.get("delta_action_mask"), layout),
            delta_reference=_delta_reference(options),
            state_preset=selection_lib.state_preset(options),
            state_groups=selection_lib.state_groups(options),
            curriculum=curriculum_lib.Curriculum.from_config(options, seed),
            reading=Reading.from_options(options),
            statistics=Statistics.from_options(options))


def _delta_reference(options: Mapping[str, Any]) -> str:
    kind = options.get("delta_reference") or "state"
    if kind not in transforms.DELTA_REFERENCES:
        raise ValueError(f"data.delta_reference = {kind!r} is not one of "
                         f"{list(transforms.DELTA_REFERENCES)}")
    if kind != "state" and not options.get("delta_action_mask"):
        raise ValueError(f"data.delta_reference = {kind!r} makes no dim relative: "
                         "data.delta_action_mask is empty (every action is absolute); set the "
                         "mask (configs/arm_focused_previous_action.py does) or leave "
                         "data.delta_reference='state'")
    return kind


def _plain(section: Mapping[str, Any]) -> dict[str, Any]:
    """A config section as a dict of its values (nested sections as dicts)."""
    if hasattr(section, "to_dict"):
        return section.to_dict()
    return {k: _plain(v) if isinstance(v, Mapping) else v for k, v in section.items()}
