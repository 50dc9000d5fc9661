"""What makes a run the run it is, and the check that a workdir is resumed only as that run.

A workdir's `config.json` holds the config of its latest start. Its *fingerprint* is the part
that gives the checkpoints, norm stats and data position their meaning: the seed, the model, the
loss, the action layout, the data (which dataset, which features, how they are normalized,
filtered and scheduled) and the global batch size. Resuming with another fingerprint would go on
training the saved params on other targets, so it is refused, naming every differing key, unless
`train.resume` says what to do:

  auto   (default) resume when the fingerprint matches; refuse otherwise.
  force  resume anyway: the checkpoints, norm stats and data position are kept, the new values
         apply from the next step (e.g. to go on training on a changed `data.root`).
  new    start over in the same folder: the old run's files move to `archive/<time>/`.

Everything else (optimizer, schedule length, logging, evaluation, workers) may change between
starts; the keys that did are printed once.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping
from typing import Any

from etils import epath

CONFIG_FILE = "config.json"
CHECKPOINT_CONFIG = "metadata"  # the file of a checkpoint's JSON config item (orbax's name)
ARCHIVE_DIR = "archive"
RESUME_MODES = ("auto", "force", "new")

# Key prefixes of the fingerprint, and the keys under them that only tune how a run is executed.
FINGERPRINT_KEYS = ("seed", "model", "loss", "layout", "data", "train.batch_size")
EXECUTION_KEYS = ("model.pretrained", "model.dtype", "data.num_workers", "data.prefetch",
                  "data.probe_episodes", "data.video_tolerance_frames", "data.frame_cache")
# Keys added after runs were saved without them, with the value that reproduces what those runs
# did: a saved config that lacks one compares as if it held that value.
ADDED_KEYS = {"data.video_access": "auto", "data.stream_episodes": 16, "data.stream_shuffle": 256,
              "data.stream_stride": 1, "data.skip_missing_videos": False,
              "data.delta_reference": "state", "data.frame_cache": False, "model.lora": [],
              "model.remat_policy": "nothing_saveable", "model.attention": "einsum"}
# Paths compare as absolute paths, so that a run restarted from another folder is the same run.
PATH_KEYS = ("data.root", "data.norm_stats", "data.arm_heavy_episodes", "model.tokenizer")


def flatten(config: Mapping[str, Any]) -> dict[str, Any]:
    """`{"a.b.c": value}` of a (JSON-like) config tree; lists for tuples, paths absolute."""
    flat: dict[str, Any] = {}

    def visit(node: Any, prefix: str) -> None:
        if isinstance(node, Mapping) and node:
            for key, value in node.items():
                visit(value, f"{prefix}.{key}" if prefix else str(key))
        else:
            flat[prefix] = node

    visit(json.loads(json.dumps(config, default=list)), "")
    for key in PATH_KEYS:
        if flat.get(key):
            flat[key] = os.path.abspath(os.path.expanduser(flat[key]))
    return flat


def _in(key: str, prefixes: tuple[str, ...]) -> bool:
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def is_fingerprint_key(key: str) -> bool:
    return _in(key, FINGERPRINT_KEYS) and not _in(key, EXECUTION_KEYS)


def differences(saved: Mapping[str, Any], current: Mapping[str, Any]
                ) -> tuple[list[str], list[str]]:
    """`(fingerprint changes, other changes)` between two configs, as "key: old -> new" lines."""
    old, new = flatten(saved), flatten(current)
    old = {**{k: v for k, v in ADDED_KEYS.items() if k in new}, **old}

    def show(values: Mapping[str, Any], key: str) -> str:
        return repr(values[key]) if key in values else "(absent)"

    changes = [(k, f"{k}: {show(old, k)} -> {show(new, k)}")
               for k in sorted(set(old) | set(new))
               if (k in old, old.get(k)) != (k in new, new.get(k)) and k != "train.resume"]
    return ([line for k, line in changes if is_fingerprint_key(k)],
            [line for k, line in changes if not is_fingerprint_key(k)])


def saved_config_path(workdir: epath.Path) -> epath.Path | None:
    """Where a run folder's config is: its `config.json`, else the config item of its newest
    finished checkpoint (every checkpoint holds the config it was saved with), else None."""
    path = workdir / CONFIG_FILE
    if path.exists():
        return path
    steps = sorted((int(d.name) for d in (workdir / "checkpoints").glob("*")
                    if d.name.isdigit() and (d / "config" / CHECKPOINT_CONFIG).exists()),
                   reverse=True) if (workdir / "checkpoints").exists() else []
    return workdir / "checkpoints" / str(steps[0]) / "config" / CHECKPOINT_CONFIG if steps else None


def check_resume(workdir: epath.Path, config: Mapping[str, Any], *, holds_run: bool,
                 may_write: bool) -> list[str]:
    """Applies `train.resume` to `workdir` before anything of it is read; returns notes to print.

    Args:
      workdir: the run folder (locked by this run).
      config: this start's config (a dict tree).
      holds_run: whether the workdir holds what a start computes (checkpoints, norm stats).
      may_write: whether this process moves files (process 0; the others only check).
    Raises:
      ValueError naming the differing keys and the ways out, when the workdir holds a run with
      another fingerprint and `train.resume` is `auto`.
    """
    mode = config["train"]["resume"]
    if mode not in RESUME_MODES:
        raise ValueError(f"train.resume = {mode!r}: use one of {RESUME_MODES}")
    if not holds_run:
        return []
    if mode == "new":  # decided before any file is read: process 0 may be moving them
        destination = workdir / ARCHIVE_DIR / time.strftime("%Y%m%d-%H%M%S")
        if may_write:
            destination.mkdir(parents=True)
            for entry in workdir.iterdir():
                if entry.name not in (ARCHIVE_DIR, "run.lock"):
                    entry.rename(destination / entry.name)
        return [f"train.resume=new: the previous run moved to {destination}; starting at step 0"]
    saved_path = saved_config_path(workdir)
    if saved_path is None:
        raise ValueError(
            f"workdir {workdir} holds a run (checkpoints or norm stats) but neither its "
            f"{CONFIG_FILE} nor a checkpoint's config: nothing says which config it belongs to. "
            "Start a new run with another --workdir or --config.train.resume=new (moves the old "
            "files to archive/), or continue it as this config with --config.train.resume=force")
    try:
        saved = json.loads(saved_path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{saved_path} is not JSON ({e}): restore it from a checkpoint's config "
                         "item, or start over with --config.train.resume=new") from e
    changed, tuned = differences(saved, config)
    notes = [f"resuming with changed settings: {'; '.join(tuned)}"] if tuned else []
    if not changed:
        return notes
    if mode == "force":
        return [f"train.resume=force: going on with changed {'; '.join(changed)} (the norm "
                "stats, checkpoints and data position of the run are kept)", *notes]
    raise ValueError(
        f"workdir {workdir} holds a run with another config ({saved_path}): "
        f"{'; '.join(changed)}. Resume it with its own config; or start a new run with another "
        "--workdir or --config.train.resume=new (moves the old run to archive/); or continue it "
        "with these values with --config.train.resume=force")
