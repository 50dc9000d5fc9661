"""The recipe of a new robot as one value: what it is (layout, state map, cameras, split) and the
lever the diagnosis names, every choice with the reason a person reads before changing it.

The lever follows the mechanism verdicts (`pi0_armfix.tools.mechanism`, docs/mechanisms.md):

  verdict                         lever
  offset or lag                   those groups (and any state-copy group) relative to the
                                  previous command (`data.delta_reference='previous_action'`)
  state copy                      those groups relative to the state
  magnitude (alone)               per-group loss weights, each group's inverse motion
  velocity commands, neither      `uniform`: no lever

Velocity groups are never made relative (their state, where there is one, is a position) and
never copied from the state. One lever at a time: the representation where a verdict names one,
else the weights, so that a study of the recipe against `uniform` measures that lever.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pi0_armfix.recipe import naming
from pi0_armfix.data.statistics.commands import DimEvidence

HELDOUT_SHARE = 0.2  # episodes held out: this share of the set ...
MAX_HELDOUT = 20  # ... at most this many (the G1's 20 of 100) ...
MIN_HELDOUT = 2  # ... and at least this many where the set has 5 or more
MODEL_WIDTH = 32  # pi0's action / state width; wider vectors widen the model


@dataclasses.dataclass(frozen=True)
class Group:
    """One proposed action group: its slice, role, whether it is a velocity command, its slice
    in the (stored) state where the state holds the same joints in order (None: not placed),
    and why."""

    name: str
    start: int
    stop: int
    role: str
    velocity: bool
    state_slice: tuple[int, int] | None
    why: str


@dataclasses.dataclass(frozen=True)
class Setting:
    """One line of the written config: `config.<key> = <value>`, and why."""

    key: str
    value: Any
    why: str = ""


def _span(names: Sequence[str] | None, start: int, stop: int) -> str:
    if names is None:
        return f"dims {start}..{stop - 1} (no names)"
    return names[start] if stop - start == 1 else f"{names[start]} .. {names[stop - 1]}"


def propose_groups(action_names: Sequence[str] | None,
                   evidence: Sequence[DimEvidence]) -> list[Group]:
    """The action vector's groups from its names and the data (`naming`, `evidence`)."""
    labels, notes = [], []
    for d, ev in enumerate(evidence):
        read = (naming.read_name(action_names[d]) if action_names is not None
                else naming.DimName("", "", "", False, True))
        if not read.part or (read.guessed and ev.binary):
            part, role = ("gripper", "gripper") if ev.binary else ("arm", "arm")
            note = ("binary (open/close) in the data" if ev.binary
                    else "no body part in its name: taken as an arm joint")
            read = naming.DimName(read.side, part, role, read.velocity, guessed=True)
        else:
            note = ("a joint or pose axis with no body part in its name: taken as an arm"
                    if read.guessed else "named")
        velocity = read.velocity or bool(ev.velocity)
        labels.append((read.group, read.role, velocity))
        notes.append(note)
    groups = []
    runs = naming.runs([f"{g}|{r}|{v}" for g, r, v in labels])
    names = naming.unique_names([label.split("|")[0] for label, _, _ in runs])
    for name, (_, start, stop) in zip(names, runs):
        _, role, velocity = labels[start]
        dims = evidence[start:stop]
        why = [f"{_span(action_names, start, stop)}: {notes[start]}"]
        tested = [ev for ev in dims if ev.position_r2 is not None]
        r2 = (f"mean R2 on the state's change {np.mean([ev.velocity_r2 for ev in tested]):.2f}, "
              f"on the state {np.mean([ev.position_r2 for ev in tested]):.2f}" if tested else "")
        if velocity:
            by_name = action_names is not None and naming.read_name(action_names[start]).velocity
            why.append("a velocity command (" + ("its name" if by_name else
                       f"the finite-difference test: {r2}") + ")")
        elif tested:
            why.append(f"a position command (the finite-difference test: {r2})")
        groups.append(Group(name, start, stop, role, velocity, _state_slice(dims, velocity),
                            "; ".join(why)))
    return groups


def _state_slice(dims: Sequence[DimEvidence], velocity: bool) -> tuple[int, int] | None:
    """Where the state holds a group's joints, as positions, in its order; None elsewhere."""
    found = [ev.state_dim for ev in dims]
    if velocity or any(j is None for j in found) or any(ev.velocity for ev in dims):
        return None
    if found != list(range(found[0], found[0] + len(found))):
        return None
    return found[0], found[0] + len(found)


def heldout_episodes(num_episodes: int) -> int:
    """Episodes held out: `HELDOUT_SHARE` of the set within [`MIN_HELDOUT`, `MAX_HELDOUT`] (1
    for a set of fewer than 5)."""
    if num_episodes < 5:
        return 1
    return int(min(MAX_HELDOUT, max(MIN_HELDOUT, round(HELDOUT_SHARE * num_episodes))))


@dataclasses.dataclass(frozen=True)
class Recipe:
    """A robot's recipe: `robot` (the settings of what the robot and its set are, shared by the
    recipe and its `uniform` baseline), `lever` (the diagnosis' settings), and `notes` (tests that
    could not run, choices not made)."""

    groups: tuple[Group, ...]
    robot: tuple[Setting, ...]
    lever: tuple[Setting, ...] = ()
    lever_why: str = ""
    notes: tuple[str, ...] = ()

    @property
    def group_names(self) -> list[str]:
        return [g.name for g in self.groups]

    def config_overrides(self, with_lever: bool = True) -> dict[str, Any]:
        """`{key: value}` of every setting (the lever's too, unless `with_lever` is False)."""
        settings = [*self.robot, *(self.lever if with_lever else ())]
        return {s.key: s.value for s in settings}


def robot_settings(root: str, keys: Mapping[str, str], groups: Sequence[Group], real_dim: int,
                   state_width: int, cameras: Mapping[str, str], images: bool, images_why: str,
                   skip_missing_videos: bool, num_episodes: int,
                   late: Exception | None = None) -> tuple[Setting, ...]:
    """The settings of what the robot and its set are (`late`: the probe's finding that the
    set's timestamps run `late.frames` frames past its videos, or None)."""
    width = max(MODEL_WIDTH, real_dim, state_width)
    placed = {g.name: g.state_slice for g in groups if g.state_slice is not None}
    unplaced = [g.name for g in groups if g.state_slice is None]
    settings = [
        Setting("data.root", str(root), "the LeRobot set this recipe was written from"),
        Setting("data.action_key", keys["action"], "the set's action feature"),
        Setting("data.state_key", keys["state"], "the set's state feature"),
        Setting("layout.groups", {g.name: (g.start, g.stop) for g in groups},
                "\n".join(f"{g.name}: {g.why}" for g in groups)),
        Setting("layout.real_dim", real_dim, "the action feature's width"),
        Setting("layout.roles", {g.name: g.role for g in groups},
                "roles from the names (a binary dim with no body part: a gripper)"),
        Setting("layout.velocity_groups", tuple(g.name for g in groups if g.velocity),
                "velocity commands: never made relative, never copied from the state"),
        Setting("data.state_groups", placed or None,
                "where the state holds each group's joints as positions, in order (by name, or "
                "the state dim that explains the command best)"
                + (f"; not placed: {unplaced}" if unplaced else "")),
        Setting("loss.group_weights", {g.name: 1.0 for g in groups},
                "every group once (what the per-group metrics and weights name)"),
    ]
    if width != MODEL_WIDTH:
        why = (f"the actions ({real_dim}) or the state ({state_width}) are wider than pi0's "
               f"{MODEL_WIDTH}: the model's width follows (pretrained pi0 params need 32)")
        settings += [Setting("layout.action_dim", width, why), Setting("model.action_dim", width)]
    settings.append(Setting("data.images", images, images_why))
    if images:
        settings += [
            Setting("data.cameras", dict(cameras),
                    "the set's cameras by name (pi0_armfix/data/cameras.py's aliases)"),
            Setting("data.frame_cache", True,
                    "every frame decoded once at the model's image size, then read from disk"),
            Setting("data.skip_missing_videos", skip_missing_videos,
                    "episodes without their video files are left out" if skip_missing_videos
                    else "every episode has its video files"),
        ]
        if late is not None:
            settings.append(Setting("data.video_tolerance_frames", late.frames,
                                    f"the probe found: {late}"))
    settings += [
        Setting("data.num_workers", 2, "reads off the training step's critical path"),
        Setting("eval.episodes", heldout_episodes(num_episodes),
                (f"held out: the last {HELDOUT_SHARE:.0%} of the {num_episodes} episodes, "
                 f"within [{MIN_HELDOUT}, {MAX_HELDOUT}]" if num_episodes >= 5 else
                 f"held out: the last of the {num_episodes} episodes (a set of fewer than 5 "
                 "keeps the rest for training)")),
        Setting("eval.evaluations", 4, "a held-out evaluation every quarter of the run"),
        Setting("loss.strategy", "uniform", "the baseline: openpi's plain mean over the dims"),
    ]
    return tuple(settings)


def choose_lever(groups: Sequence[Group], mechanism: Mapping[str, Any],
                 suggested_weights: Mapping[str, float]) -> tuple[tuple[Setting, ...], str,
                                                                  tuple[str, ...]]:
    """`(settings, why, notes)` of the lever the mechanism verdicts name (module docstring).

    Args:
      groups: the proposed groups (with their state placement).
      mechanism: the analysis' `mechanism` section (`state_copy`, `offset`, `lag`, `magnitude`:
        group names; `verdict`: its lines).
      suggested_weights: the analysis' per-group inverse-motion weights.
    """
    by_name = {g.name: g for g in groups}
    velocity = {g.name for g in groups if g.velocity}
    offset = [g for g in (*mechanism["offset"], *mechanism["lag"]) if g not in velocity]
    copy = [g for g in mechanism["state_copy"] if g not in velocity]
    magnitude = [g for g in mechanism["magnitude"] if g not in velocity]
    notes = []
    if offset:
        relative = [g for g in by_name if g in offset or g in copy]
        why = (f"the diagnosis: offset or lag on {sorted(set(offset))}"
               + (f", state copy on {copy}" if copy else "")
               + ": those groups relative to the command one frame before (at an episode's "
               "first frame, the state plus its mean offset where data.state_groups holds the "
               "joints as positions, else the training split's mean action)")
        settings = (Setting("data.delta_action_mask", tuple(relative)),
                    Setting("data.delta_reference", "previous_action"))
    elif copy:
        relative = [g for g in by_name if g in copy]
        misplaced = [g for g in relative if by_name[g].state_slice
                     != (by_name[g].start, by_name[g].stop)]
        if misplaced:
            why = (f"the diagnosis: state copy on {copy}; the state does not hold {misplaced} at "
                   "their action slices, so they are relative to the previous command (the "
                   "command the state copies) instead of the state")
            settings = (Setting("data.delta_action_mask", tuple(relative)),
                        Setting("data.delta_reference", "previous_action"))
        else:
            why = f"the diagnosis: state copy on {copy}: those groups relative to the state"
            settings = (Setting("data.delta_action_mask", tuple(relative)),
                        Setting("data.delta_reference", "state"))
    elif magnitude:
        weights = {g: round(float(suggested_weights.get(g, 1.0)), 2) for g in by_name}
        why = (f"the diagnosis: magnitude on {magnitude}: per-group weights, each group's "
               "inverse motion (the analysis' suggested weights)")
        settings = (Setting("loss.strategy", "per_group"), Setting("loss.group_weights", weights))
    else:
        why = ((f"{sorted(velocity)} are velocity commands (left absolute); " if velocity
                else "") + "the diagnosis names no mechanism"
               + (" on the other groups" if velocity else "") + ": no lever (uniform)")
        settings = ()
    if magnitude and settings and settings[0].key != "loss.strategy":
        notes.append(f"magnitude on {magnitude} too: one lever at a time; per-group weights "
                     "(loss.strategy='per_group') are the next to try")
    skipped = [g.name for g in groups if g.velocity]
    if skipped:
        notes.append(f"velocity groups {skipped} are never made relative (their state is a "
                     "position)")
    return settings, why, tuple(notes)


def untested(groups: Sequence[Group], has_state: bool, names: bool) -> list[str]:
    """The tests the writer could not run, each a line."""
    lines = []
    if not names:
        lines.append("the action feature names no dims: groups from the data alone (a binary dim "
                     "a gripper, the rest one arm)")
    if not has_state:
        lines.append("no state feature: no finite-difference (velocity) test, no state-copy, "
                     "offset or lag test")
        return lines
    unplaced = [g.name for g in groups if g.state_slice is None and not g.velocity]
    if unplaced:
        lines.append(f"the state does not hold {unplaced}'s joints in order: their state-copy "
                     "baseline, offset and lag tests were not run")
    return lines

