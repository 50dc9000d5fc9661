"""The dataset a run names, opened once: its train / held-out split, the checks that run before
any pass over it, and the passes that compute its statistics.

    spec = DataSpec.from_config(config, layout)              # the config read once
    source = sources.open_source(spec.options, spec.layout)  # once per run; pass it down
    check_data(spec, source, ...)                            # every check that can fail, no pass
    stats = load_or_compute_norm_stats(spec, source=source, action_horizon=H,
                                       cache_path=workdir / NORM_STATS_FILE)

Split: the dataset's last `eval.episodes` episodes are held out (evaluation only); the rest train.
The tools read `which="train"` (default) or `"all"` episodes and say which.

The workdir's `norm_stats.json` is keyed to what it was computed from (`norm_stats_key`: the
dataset's identity, the feature selection, the split, the stats options) in the sidecar
`norm_stats.key.json`: a cached file whose key differs is recomputed (fresh run) or refused (a run
with checkpoints, whose weights were trained with the old stats), never reused silently.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix import state_space
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import json_files
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import curriculum as curriculum_lib
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import commands as commands_lib
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.data.statistics import stats as stats_lib
ABSOLUTE_ACTIONS = stats_lib.ABSOLUTE_ACTIONS
EPISODE_CHOICES = ("train", "all")


# ---------------------------------------------------------------------- episodes

def split_episodes(episode_index: np.ndarray, num_heldout: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`[E]` dataset episode ids -> (training ids, held-out ids = the last `num_heldout`)."""
    episode_index = np.asarray(episode_index, np.int64)
    num_heldout = int(num_heldout)
    if not 0 <= num_heldout < len(episode_index):
        fits = max(1, round(0.1 * len(episode_index))) if len(episode_index) > 1 else 0
        raise ValueError(f"eval.episodes = {num_heldout}: must be >= 0 and leave at least one of "
                         f"the dataset's {len(episode_index)} episodes for training; set "
                         f"--config.eval.episodes={fits} (about 10 % held out"
                         + (")" if fits else "; with 0 nothing is evaluated)"))
    cut = len(episode_index) - num_heldout
    return episode_index[:cut], episode_index[cut:]


def _source(spec: DataSpec, source):
    return source if source is not None else sources.open_source(spec.options, spec.layout)


def training_episodes(spec: DataSpec, source) -> np.ndarray:
    """Dataset ids of the episodes the run trains on (all but the held-out ones)."""
    return split_episodes(source.episode_index, spec.heldout_episodes)[0]


def reading_spec(spec: DataSpec, which: str = "train") -> DataSpec:
    """The spec a tool reads `which` episodes with: the run's for "train"; for "all", one
    without a held-out split (a tool that reads every episode needs no `eval.episodes`)."""
    if which not in EPISODE_CHOICES:
        raise ValueError(f"--episodes={which!r}: choose one of {list(EPISODE_CHOICES)}")
    return spec if which == "train" else dataclasses.replace(spec, heldout_episodes=0,
                                                             eval_every=0)


def select_episodes(spec: DataSpec, source, which: str = "train") -> np.ndarray:
    """Dataset ids of the training episodes (`which="train"`) or of every episode (`"all"`)."""
    return training_episodes(reading_spec(spec, which), source)


def describe_episodes(spec: DataSpec, source, episodes: np.ndarray) -> str:
    """"reading 8 of 12 episodes (ids 10..20030), 9,310 frames; held out: ..." for the tools."""
    frames = num_frames(source, episodes)
    line = (f"reading {len(episodes)} of {source.num_episodes} episodes (ids {_ids(episodes)}), "
            f"{frames:,} frames")
    left_out = np.setdiff1d(source.episode_index, episodes)
    if len(left_out):
        line += (f"; left out: the {len(left_out)} held-out episodes (eval.episodes="
                 f"{spec.heldout_episodes}: ids {_ids(left_out)}); --episodes=all reads them too")
    return line


def _ids(ids: np.ndarray) -> str:
    ids = [int(i) for i in ids]
    return ", ".join(map(str, ids)) if len(ids) <= 6 else f"{ids[0]}..{ids[-1]}"


def num_frames(source, episodes: np.ndarray) -> int:
    """Frames of `episodes`."""
    return int(source.episode_lengths[np.isin(source.episode_index, episodes)].sum())


def heldout_table(spec: DataSpec, *, images: bool = True, source=None,
                  image_size: tuple[int, int] | None = None) -> EpisodeTable:
    """The held-out episodes (the dataset's last `eval.episodes`) for evaluation; video frames
    decoded to fit inside `image_size`, as the training frames are."""
    source = _source(spec, source)
    heldout = split_episodes(source.episode_index, spec.heldout_episodes)[1]
    if not len(heldout):
        raise ValueError("eval.episodes is 0: there are no held-out episodes to evaluate on")
    return source.load_table(heldout, images=images, image_size=image_size)


def training_blocks(spec: DataSpec, keys: Sequence[str] = ("actions", "state"), *, source=None,
                    episodes: np.ndarray | None = None
                    ) -> tuple[Iterator[dict[str, np.ndarray]], int]:
    """A stream of blocks (`Source.iter_blocks`) of `episodes` (default: the training episodes),
    and their number of frames."""
    source = _source(spec, source)
    if episodes is None:
        episodes = training_episodes(spec, source)
    return (stats_lib.checked_blocks(source.iter_blocks(keys, episodes), source.episode_file,
                                     getattr(source, "dim_name", None)),
            num_frames(source, episodes))


# ---------------------------------------------------------------------- checks before any pass

DELTA_UNITS_EPISODES = 4  # training episodes the delta-units test reads


def check_delta_units(spec: DataSpec, source) -> None:
    """Refuses actions relative to the state where a relative group's commands are the velocity of
    the state's joints (the finite-difference test, `commands.velocity_pairs`, on the first
    `DELTA_UNITS_EPISODES` training episodes): `a - s` would subtract positions from
    velocities. A velocity command beside a measured velocity (B1K's base) passes."""
    dims = np.flatnonzero(spec.delta_mask)
    episodes = training_episodes(spec, source)[:DELTA_UNITS_EPISODES]
    blocks = list(source.iter_blocks(("actions", "state"), episodes=episodes))
    if not blocks:
        return
    actions, state, episode = (np.concatenate([b[k] for b in blocks])
                               for k in ("actions", "state", "episode_index"))
    velocity, position_r2, velocity_r2 = commands_lib.velocity_pairs(actions, state, episode,
                                                                    dims, dims)
    if velocity.any():
        groups = sorted({spec.layout.group_of_dim(int(d)) for d in dims[velocity]})
        first = int(np.flatnonzero(velocity)[0])
        raise ValueError(
            f"data.delta_action_mask makes {groups} relative to the state, but their commands are "
            f"the velocity of the state's joints (dim {dims[first]}: R2 "
            f"{velocity_r2[first]:.2f} on the state's change, {position_r2[first]:.2f} on the "
            "state; the finite-difference test): a - s would subtract positions from velocities. "
            "Leave them absolute (and list them in layout.velocity_groups), or make them "
            "relative to the previous command: data.delta_reference='previous_action'")


def check_data(spec: DataSpec, source, *, images: bool = True) -> list[str]:
    """Every check of the data that can fail, before any pass over it (cheap: metadata, plus the
    probe of `data.probe_episodes` episodes' files and first/last video frames).

    Checks the action width (when the source opened), the state width against
    `layout.action_dim` (naming the fix), the delta-action state layout, the curriculum's
    arm-heavy layout and episode list, the split (an evaluating run needs a held-out episode;
    the evaluation pads a last batch, so any number of held-out chunks will do), and the probe.

    Returns:
      warnings to print once (e.g. batch cameras that no stored camera feeds).
    """
    layout = spec.layout
    where = str(getattr(source, "root", "the dataset"))
    heldout = split_episodes(source.episode_index, spec.heldout_episodes)[1]
    if spec.eval_every > 0 and not len(heldout):
        raise ValueError(f"eval.every = {spec.eval_every} evaluates on the held-out episodes, but "
                         "eval.episodes = 0 holds none out: set eval.episodes (about 10 % of "
                         "the episodes) or eval.every=0")
    if spec.state_groups:
        selection_lib.check_state_groups(spec.state_groups, source.state_width)
    if source.state_width > layout.action_dim:
        stored = getattr(source, "stored_state_width", source.state_width)
        presets = selection_lib.presets_for(stored)
        hint = (f"data.state_preset={presets[0]!r} ({stored}-D state -> "
                f"{state_space.STATE_PRESETS[presets[0]].width} dims in the action order) or "
                if presets else "")
        raise ValueError(
            f"{where}: the state ({spec.reading.state_key!r}) has "
            f"{source.state_width} dims, more than layout.action_dim={layout.action_dim}: it "
            f"cannot be padded into the model's state. Select the dims the policy needs: "
            f"{hint}data.state_indices=(...)")
    if spec.delta_mask is not None and spec.delta_reference == "state":
        transforms.check_delta_state_layout(spec.delta_mask, layout, spec.state_groups,
                                            source.state_width)
        check_delta_units(spec, source)
    curriculum = spec.curriculum
    if "arm_heavy" in curriculum.sources:
        listed = spec.reading.arm_heavy_episodes
        if listed:
            chosen = curriculum_lib.load_episode_list(listed)
            unknown = np.setdiff1d(chosen, source.episode_index)
            if len(unknown):
                raise ValueError(
                    f"data.arm_heavy_episodes ({listed}) lists {len(unknown)} episode(s) that "
                    f"{where} does not have (ids {_ids(unknown)}): it was made for other data; "
                    "rerun filter_arm_heavy_episodes on this dataset")
            heldout = np.setdiff1d(chosen, training_episodes(spec, source))
            if len(heldout):
                logging.warning("data.arm_heavy_episodes lists %d held-out episode(s) (ids %s): "
                                "they are never trained on", len(heldout), _ids(heldout))
        else:
            motion_lib.arm_heavy_groups(layout)
    warnings = []
    total_steps = spec.total_steps
    for number, phase in enumerate(curriculum.phases[:-1]):
        if total_steps and phase.until_step >= total_steps:
            warnings.append(
                f"data.curriculum: phase {number} lasts until step {phase.until_step}, but "
                f"train.total_steps = {total_steps}: the run never leaves it (its sources "
                f"{list(phase.sources)} only); shorten the phases with the run (the config file "
                "sets them from its own total_steps)")
            break
    if images and spec.reading.images:  # with data.images=False no camera is wanted
        missing = cameras_lib.missing_cameras_message(
            source.cameras, getattr(source, "camera_names", ()), where)
        if missing:
            warnings.append(missing)
    source.probe(spec.reading.probe_episodes, videos=images)
    return warnings


# ---------------------------------------------------------------------- normalization statistics
def block_norm_stats(blocks: Iterable[stats_lib.Block], spec: DataSpec, *, action_horizon: int,
                     total_frames: int | None = None, progress: bool = True,
                     absolute: Mapping[str, stats_lib.NormStats] | None = None
                     ) -> dict[str, stats_lib.NormStats]:
    """Statistics `{"actions", "state", "actions_absolute"}` of a stream of blocks
    (`Source.iter_blocks`), with the actions in the model's action space, and the absolute actions
    per frame beside them (the evaluation's common units, whatever the representation).

    Absolute action dims and the state: over frames, each frame once. The relative dims of
    `data.delta_action_mask`: over every step of every chunk, as openpi (which computes its stats
    through the data transforms) and exactly what the training batches hold: for each frame t and
    h < H, `a[min(t + h, last)] - s[t]` (or `- a[t - 1]`, `data.delta_reference`) (float32, clamped at the episode's last frame like the
    chunker; the padded steps are included because the batch holds them too). A frame's own delta
    `a[t] - s[t]` is far smaller than the chunk's later ones, so per-frame stats would blow the
    normalized targets up. This pass re-cuts the stream into whole episodes and costs H times the
    work on those dims; without a delta mask it is the plain per-frame pass.

    Args:
      blocks: `{"actions": [n, A], "state": [n, S], "episode_index": [n]}`, episodes in order.
      spec: the run's data spec (its layout, delta mask and state groups).
      action_horizon: H of the model's chunks (`config.model.action_horizon` resolved against the
        preset by the caller).
      absolute: for actions relative to the previous action, the plain per-frame stats
        `{"actions", "state"}` of the same blocks (a first pass): their means are where each
        episode starts (`transforms.EpisodeStart`), and the actions' are kept as the
        `ABSOLUTE_ACTIONS` entry.
    """
    mask, layout = spec.delta_mask, spec.layout
    if mask is None:
        stats = stats_lib.compute_norm_stats(blocks, total_frames=total_frames, progress=progress)
        return {**stats, ABSOLUTE_ACTIONS: stats["actions"]}
    if action_horizon < 1:
        raise ValueError(f"action_horizon must be >= 1 for the delta action statistics, got "
                         f"{action_horizon}")

    def chunk_steps(block: stats_lib.Block) -> stats_lib.Block:
        actions = np.asarray(block["actions"], np.float32)  # the table's dtype
        state = np.asarray(block["state"], np.float32)
        if spec.delta_reference == "state":
            transforms.check_delta_state_layout(mask, layout, spec.state_groups, state.shape[1])
        episode = np.asarray(block["episode_index"])
        starts = np.concatenate([[0], np.flatnonzero(episode[1:] != episode[:-1]) + 1,
                                 [len(episode)]])
        frames = np.arange(len(episode))
        index, _ = transforms.chunk_indices(frames, starts, action_horizon)
        reference = transforms.delta_reference(spec.delta_reference, actions, state, frames,
                                               starts, start)
        steps = (transforms.to_delta(actions[index[:, h]], reference, mask)[:, mask]
                 for h in range(action_horizon))
        return {"actions": actions, "delta_actions": steps, "state": state}

    if spec.delta_reference == "previous_action" and absolute is None:
        raise ValueError("statistics of actions relative to the previous action need the "
                         "plain stats of the same frames first (absolute=)")
    start = transforms.episode_start(
        spec.delta_reference, {ABSOLUTE_ACTIONS: absolute["actions"], "state": absolute["state"]}
        if absolute is not None else {}, layout, spec.state_groups)
    stats = stats_lib.compute_norm_stats(
        stats_lib.whole_episode_blocks(blocks), ("actions", "delta_actions", "state"),
        total_frames=total_frames, transform=chunk_steps, progress=progress)
    delta = stats.pop("delta_actions")
    stats[ABSOLUTE_ACTIONS] = absolute["actions"] if absolute is not None else stats["actions"]
    fields = {}
    for field in stats_lib.FIELDS:
        fields[field] = getattr(stats["actions"], field).copy()
        fields[field][mask] = getattr(delta, field)
    stats["actions"] = stats_lib.NormStats(**fields)
    return stats


def dataset_norm_stats(spec: DataSpec, *, action_horizon: int, progress: bool = True,
                       source=None, episodes: np.ndarray | None = None
                       ) -> dict[str, stats_lib.NormStats]:
    """Plain statistics `{"actions", "state"}` of `episodes` (default: the training episodes),
    one streaming pass (`block_norm_stats`: the relative dims of `data.delta_action_mask` over
    chunks of H = `action_horizon`)."""
    absolute = None
    if spec.delta_mask is not None and spec.delta_reference == "previous_action":
        # the mean action and state, from which each episode starts (`EpisodeStart`)
        blocks, total = training_blocks(spec, ("actions", "state"), source=source,
                                        episodes=episodes)
        absolute = stats_lib.compute_norm_stats(blocks, ("actions", "state"), total_frames=total,
                                                progress=progress)
    blocks, total = training_blocks(spec, ("actions", "state"), source=source,
                                    episodes=episodes)
    return block_norm_stats(blocks, spec, action_horizon=action_horizon, total_frames=total,
                            progress=progress, absolute=absolute)


def dataset_motion(spec: DataSpec, action_stats: stats_lib.NormStats,
                   norm_mode: str = "zscore", *, progress: bool = True, source=None,
                   episodes: np.ndarray | None = None) -> motion_lib.MotionSummary:
    """Frame-to-frame motion of `episodes` (default: the training episodes), in `norm_mode` units
    of `action_stats`."""
    blocks, total = training_blocks(spec, ("actions",), source=source, episodes=episodes)
    return motion_lib.compute_motion(blocks, spec.layout,
                                     *motion_lib.normalized_units(action_stats, norm_mode),
                                     total_frames=total, progress=progress)


def balanced_dataset_norm_stats(spec: DataSpec, max_scale: float, *, action_horizon: int, progress: bool = True, source=None,
                                episodes: np.ndarray | None = None
                                ) -> tuple[dict[str, stats_lib.NormStats],
                                           list[motion_lib.BalanceReport]]:
    """`dataset_norm_stats` with balanced action statistics (`motion.balanced_norm_stats`): two
    streaming passes (statistics, then motion)."""
    source = _source(spec, source)
    stats = dataset_norm_stats(spec, action_horizon=action_horizon, progress=progress,
                               source=source, episodes=episodes)
    summary = dataset_motion(spec, stats["actions"], progress=progress, source=source,
                             episodes=episodes)
    stats["actions"], reports = motion_lib.balanced_norm_stats(stats["actions"], summary,
                                                               spec.layout, max_scale)
    return stats, reports


# A run folder's statistics, beside `norm_stats.key.json` (what they were computed from).
NORM_STATS_FILE = "norm_stats.json"


def norm_stats_key(spec: DataSpec, source, *, action_horizon: int) -> dict[str, Any]:
    """What the run's statistics are computed from: the dataset's identity (root, metadata,
    episode ids and lengths), the feature selection, the training split and the stats options.
    JSON-able; two equal keys give equal statistics."""
    data, layout = spec.options, spec.layout
    root = Path(getattr(source, "root", "") or ".").resolve()
    info = root / "meta" / "info.json"
    identity = hashlib.sha256()
    if info.is_file():
        identity.update(info.read_bytes())
    identity.update(np.asarray(source.episode_index, np.int64).tobytes())
    identity.update(np.asarray(source.episode_lengths, np.int64).tobytes())
    mask = spec.delta_mask
    key = {
        "data.root": str(root),
        "dataset": identity.hexdigest(),
        "training episodes": len(training_episodes(spec, source)),
        "eval.episodes": spec.heldout_episodes,
        "layout.real_dim": layout.real_dim,
    }
    for field in ("format", "action_key", "state_key", "state_indices", "action_indices",
                  "balanced_norm"):
        key[f"data.{field}"] = _jsonable(data.get(field))
    key["data.state_preset"] = spec.state_preset
    if spec.statistics.balanced_norm:
        key["data.balanced_max_scale"] = spec.statistics.balanced_max_scale
        key["layout.groups"] = {g: list(b) for g, b in layout.groups.items()}
    if mask is not None:
        key["data.delta_action_mask"] = np.flatnonzero(mask).tolist()
        if spec.delta_reference != "state":  # the default adds no entry: existing caches hold
            key["data.delta_reference"] = spec.delta_reference
            # what an episode starts from (`transforms.EpisodeStart`): stats of another rule
            # hold other first-frame deltas
            key["episode_start"] = transforms.EPISODE_START
        key["data.state_groups"] = _jsonable(spec.state_groups)
        key["model.action_horizon"] = int(action_horizon)
    return key


def _jsonable(value: Any) -> Any:
    """A config value as plain JSON; a mapping-like value (a ConfigDict) keeps its values."""
    def plain(v: Any) -> Any:
        if isinstance(v, Mapping) or hasattr(v, "items"):
            return dict(v.items())
        return list(v) if hasattr(v, "__iter__") else str(v)
    return json.loads(json.dumps(value, default=plain))


def _key_path(cache_path: Path) -> Path:
    return cache_path.with_name(cache_path.stem + ".key.json")


def run_episode_start(workdir: str | Path) -> str | None:
    """The episode-start rule (`transforms.EPISODE_START` when they were computed) a run
    folder's statistics were computed under: '' where they make groups relative to the previous
    command but their key predates the rule's entry; None where nothing is relative to the
    previous command or the folder holds no key."""
    key = read_key(_key_path(Path(workdir) / NORM_STATS_FILE))
    if key is None or key.get("data.delta_reference") != "previous_action":
        return None
    return key.get("episode_start", "")


def load_or_compute_norm_stats(spec: DataSpec, *, action_horizon: int,
                               cache_path: str | Path | None = None, progress: bool = True,
                               source=None, resuming: bool = False,
                               keep_cached: bool = False,
                               episodes: np.ndarray | None = None
                               ) -> dict[str, stats_lib.NormStats]:
    """The run's normalization statistics `{"actions", "state"}`.

    Order: `data.norm_stats` if set (read as is: a file written by `recompute_balanced_norm_stats`
    is used unchanged, whatever `data.balanced_norm` says); else `cache_path` if it exists and its
    key (`norm_stats_key`) equals this run's; else `dataset_norm_stats`, balanced
    (`motion.balanced_norm_stats`, capped at `data.balanced_max_scale`) when `data.balanced_norm`,
    written to `cache_path` with its key. A cache whose key differs is recomputed, or refused
    when `resuming` (a run whose checkpoints were trained with the cached stats), or kept with
    `keep_cached` (a run resumed with `train.resume=force`: its params were trained with them),
    its key rewritten to this run's. `episodes`:
    those the statistics are computed over (default: the training episodes; the tools' --episodes
    only, without a cache). The state entry
    keeps the file's width (openpi pads it); `BatchTransform` cuts it to the dataset's state width.
    """
    layout = spec.layout
    widths = {"actions": layout.real_dim, "state": None}
    optional = {ABSOLUTE_ACTIONS: layout.real_dim}
    if spec.statistics.norm_stats:
        return stats_lib.load_norm_stats(spec.statistics.norm_stats, widths, optional)
    source = _source(spec, source)
    key = norm_stats_key(spec, source, action_horizon=action_horizon)
    if episodes is not None and cache_path is not None:
        raise ValueError("load_or_compute_norm_stats: a cache holds the training episodes' stats")
    if cache_path is not None and Path(cache_path).is_file():
        cache_path = Path(cache_path)
        cached = read_key(_key_path(cache_path))
        if cached == key:
            return stats_lib.load_norm_stats(cache_path, widths, optional)
        differing = differing_keys(cached, key)
        if keep_cached:
            logging.warning("%s: keeping the norm stats the run was trained with (differing: %s)",
                            cache_path, differing)
            json_files.write_json_atomic(_key_path(cache_path), key)
            return stats_lib.load_norm_stats(cache_path, widths, optional)
        if resuming:
            if differing == ["episode_start"]:
                raise ValueError(
                    f"{cache_path} was computed when an episode's first chunk started from "
                    f"{cached.get('episode_start') or 'the state (an earlier rule)'}; today it "
                    f"starts from {transforms.EPISODE_START} (transforms.EpisodeStart), and the "
                    "run's checkpoints were trained with the old statistics: resume with "
                    "--config.train.resume=force to keep them (only episodes' first chunks "
                    "differ), or start a new --workdir to train under today's rule")
            if cached is None:  # a run from before the key existed: keep what it trained with
                logging.warning("%s has no key file; reusing it for the resumed run", cache_path)
                json_files.write_json_atomic(_key_path(cache_path), key)
                return stats_lib.load_norm_stats(cache_path, widths, optional)
            raise ValueError(
                f"{cache_path} was computed from other data or options than this run's config "
                f"(differing: {differing}) and the run's checkpoints were trained with it: "
                "resume with the config it was started with, or start a new --workdir")
        logging.warning("%s was computed from other data or options (differing: %s): "
                        "recomputing it", cache_path, differing)
    if spec.statistics.balanced_norm:
        stats, reports = balanced_dataset_norm_stats(
            spec, spec.statistics.balanced_max_scale,
            action_horizon=action_horizon, progress=progress, source=source, episodes=episodes)
        for report in reports:
            logging.info("balanced norm stats (%s): motion RMS before %s after %s",
                         report.mode, report.before, report.after)
    else:
        stats = dataset_norm_stats(spec, action_horizon=action_horizon, progress=progress,
                                   source=source, episodes=episodes)
    if cache_path is not None:
        stats_lib.save_norm_stats(cache_path, stats)
        json_files.write_json_atomic(_key_path(Path(cache_path)), key)
    return stats


def differing_keys(cached: Mapping[str, Any] | None, key: Mapping[str, Any]) -> list[str]:
    """The entries in which a cache's key differs from this run's (`norm_stats_key`)."""
    cached = cached or {}
    return sorted(k for k in set(key) | set(cached) if cached.get(k) != key.get(k))


def read_key(path: Path) -> dict[str, Any] | None:
    """A cache's key file, or None when it is missing or unreadable."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None

