"""Diagnose a LeRobot set and write the config file its recipe is: `train` takes it as is.

    python -m pi0_armfix.tools.write_config --root=DIR [--output=configs/<robot>.py]

What it proposes (`pi0_armfix.recipe`), each with its reason, printed and written above its line:

- the layout: groups and roles from the action feature's `names` (arm / hand / gripper / base /
  torso; a binary dim with no body part in its name is a gripper), velocity commands told apart
  from positions by name and by the finite-difference test;
- the state map (`data.state_groups`): where the state holds each group's joints, by name or by
  the data, found where it exists and never required;
- the cameras, whether every episode has its videos, the held-out split, a wider model where the
  vectors are wider than pi0's 32;
- then the analysis (`analyze_action_magnitudes`, its JSON and PNG beside the config) on that
  layout, and the lever its verdicts name (`recipe.choose_lever`).

It prints which tests it could not run. Nothing is trained; reading the set's actions and state
takes seconds (no video is decoded; the video files are only looked for).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
from absl import app, flags

from pi0_armfix import console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import base
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.formats.lerobot_frames import LATE_FRAMES, LateTimestamps
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.data.statistics.bimodal import gripper_like_dims
from pi0_armfix.data.statistics import commands as evidence_lib
from pi0_armfix.recipe import naming
from pi0_armfix.recipe import recipe as recipe_lib
from pi0_armfix.recipe.render import render
from pi0_armfix.tools import analyze_action_magnitudes

ACTION_KEYS = ("action", "actions")
STATE_KEYS = ("observation.state", "state", "observation.states")
MAX_FRAMES = 2_000_000  # frames read for the data tests (the first episodes of a larger set)
PROBE_EPISODES = 64  # episodes whose first and last video frames are decoded, spread over the set


def _key(features: dict, given: str, candidates: tuple[str, ...], what: str, flag: str,
         info_path: Path) -> str:
    if given:
        if given not in features:
            raise ValueError(f"{info_path} has no {given!r} feature ({flag}); its features: "
                             f"{sorted(features)}")
        return given
    found = next((k for k in candidates if k in features), "")
    if not found and what == "action":
        raise ValueError(f"{info_path} has none of the action features {list(candidates)}; name "
                         f"yours with {flag}")
    return found


def read_episodes(source: LeRobotSource, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """`{key: [n, D]}` and `episode_index [n]` of whole episodes, up to `MAX_FRAMES` frames."""
    budget = np.cumsum(source.episode_lengths) <= MAX_FRAMES
    episodes = source.episode_index[budget | (np.arange(len(budget)) == 0)]
    parts: dict[str, list[np.ndarray]] = {k: [] for k in (*keys, "episode_index")}
    for block in source.iter_blocks(keys, episodes=episodes):
        for k in parts:
            parts[k].append(np.asarray(block[k]))
    return {k: np.concatenate(v) for k, v in parts.items()}


def late_timestamps(root: Path, layout: ActionLayout, action_key: str, state_key: str,
                    cameras: dict[str, str], skip: bool) -> LateTimestamps | None:
    """The probe of up to `PROBE_EPISODES` episodes' videos (first and last rows decoded),
    repeated at the tolerance it asks for where the set's timestamps run a frame or two past
    their videos: the last such finding (its `frames` the tolerance that reads the set), or None.
    Any other finding is the set's error, raised."""
    found, tolerance = None, 0.5
    for _ in range(LATE_FRAMES + 1):
        source = LeRobotSource(root, layout, action_key=action_key, cameras=cameras,
                               state_key=state_key or "observation.state", images=True,
                               skip_missing_videos=skip, video_tolerance_frames=tolerance)
        try:
            source.probe(num_episodes=min(source.num_episodes, PROBE_EPISODES))
            return found
        except LateTimestamps as late:
            found, tolerance = late, late.frames
    return found


def _code_version() -> str:
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True,
                             text=True, cwd=Path(__file__).parent, timeout=10)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def write(root: str | Path, output: str | Path, action_key: str = "", state_key: str = ""
          ) -> dict[str, Any]:
    """Writes the config file (and the analysis beside it); returns what was chosen and why."""
    root, output = Path(root).expanduser().resolve(), Path(output)
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise ValueError(f"{root} is not a LeRobot dataset root: {info_path} is missing")
    features = json.loads(info_path.read_text()).get("features", {})
    action_key = _key(features, action_key, ACTION_KEYS, "action", "--action_key", info_path)
    state_key = _key(features, state_key, STATE_KEYS, "state", "--state_key", info_path)
    width = int(np.prod(features[action_key]["shape"]))
    probe_layout = ActionLayout({"all": (0, width)}, real_dim=width,
                                action_dim=max(recipe_lib.MODEL_WIDTH, width))
    source = LeRobotSource(root, probe_layout, action_key=action_key,
                           state_key=state_key or "observation.state", images=False)
    keys = ("actions", "state") if state_key else ("actions",)
    data = read_episodes(source, keys)
    actions, state = data["actions"], data.get("state")
    action_stats = stats_lib.StreamingStats(width)
    action_stats.update(actions)
    binary = gripper_like_dims(action_stats)
    action_names = naming.feature_names(features[action_key], width)
    state_names = (naming.feature_names(features[state_key], int(state.shape[1]))
                   if state is not None else None)
    evidence = evidence_lib.dim_evidence(actions, state, data["episode_index"], binary,
                                         action_names, state_names)
    groups = recipe_lib.propose_groups(action_names, evidence)

    camera_names = list(source.camera_names)
    images, cameras, skip, images_why = bool(camera_names), {}, False, "the set has no camera"
    late = None
    num_episodes = source.num_episodes
    if camera_names:
        try:
            cameras = cameras_lib.match_cameras(camera_names, None, str(root))
        except ValueError:
            cameras = {}
        cameras = cameras or {"base_0_rgb": sorted(camera_names)[0]}
        seen = LeRobotSource(root, probe_layout, action_key=action_key, cameras=cameras,
                             state_key=state_key or "observation.state", images=True)
        missing = seen.missing_videos
        if len(missing.missing) == seen.num_episodes:
            images = False
            images_why = (f"{missing.found}: trained without cameras. {missing.fix}, then set "
                          "this True")
        else:
            skip = bool(missing.missing)
            num_episodes -= len(missing.missing)
            images_why = "the set's cameras are read"
            late = late_timestamps(root, probe_layout, action_key, state_key, cameras, skip)
    robot = recipe_lib.robot_settings(
        root, {"action": action_key, "state": state_key or "observation.state"}, groups, width,
        0 if state is None else int(state.shape[1]), cameras, images, images_why, skip,
        num_episodes, late)
    draft = recipe_lib.Recipe(tuple(groups), robot)
    config = base.get_config()
    config.update_from_flattened_dict(draft.config_overrides())
    config.data.probe_episodes = 0  # the analysis reads no video
    report_path = output.with_suffix(".analysis.json")
    report = analyze_action_magnitudes.run(config, report_path)
    mechanism = report["mechanism"]
    lever, lever_why, notes = recipe_lib.choose_lever(
        groups, mechanism, {g: r["suggested_weight"] for g, r in report["groups"].items()})
    untested = recipe_lib.untested(groups, state is not None, action_names is not None)
    recipe = recipe_lib.Recipe(tuple(groups), robot, lever, lever_why, (*untested, *notes))
    command = (f"python -m pi0_armfix.tools.write_config --root={root} --output={output}")
    text = render(recipe, name=output.stem, source=f"{root} (pi0_armfix {_code_version()})",
                  command=command, verdict=mechanism["verdict"])
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(text)
    return {"recipe": recipe, "report": report, "output": output, "analysis": report_path}


def summary(result: dict[str, Any]) -> str:
    """What was chosen and why, for the terminal."""
    recipe = result["recipe"]
    lines = ["groups:"]
    lines += [f"  {g.name} ({g.start}, {g.stop}) {g.role}{' velocity' if g.velocity else ''}"
              f"{f', state {g.state_slice}' if g.state_slice else ''}: {g.why}"
              for g in recipe.groups]
    lines += [f"{s.key} = {s.value!r}" + (f"  ({s.why})" if s.why and "\n" not in s.why else "")
              for s in recipe.robot if s.key not in ("layout.groups", "data.root")]
    lines += [f"VERDICT: {v}" for v in result["report"]["mechanism"]["verdict"]]
    lines += [f"LEVER: {recipe.lever_why}"]
    lines += [f"  {s.key} = {s.value!r}" for s in recipe.lever]
    lines += [f"NOT TESTED / NOT CHOSEN: {n}" for n in recipe.notes]
    lines += [f"wrote {result['output']} (the analysis: {result['analysis']} and its .png)"]
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    root = Path(flags.FLAGS.root)
    output = flags.FLAGS.output or f"configs/{root.resolve().name.replace('-', '_')}.py"
    with console.user_errors("pi0_armfix.tools.write_config"):
        result = write(root, output, flags.FLAGS.action_key, flags.FLAGS.state_key)
    print(summary(result))


def cli() -> None:
    """The `pi0-armfix-write-config` console script (also `python -m
    pi0_armfix.tools.write_config`)."""
    flags.DEFINE_string("root", None, "the LeRobot dataset root", required=True)
    flags.DEFINE_string("output", "", "the config file to write ('' = configs/<root's name>.py)")
    flags.DEFINE_string("action_key", "", f"the action feature ('' = the first of {ACTION_KEYS})")
    flags.DEFINE_string("state_key", "", f"the state feature ('' = the first of {STATE_KEYS})")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.write_config"))


if __name__ == "__main__":
    cli()
