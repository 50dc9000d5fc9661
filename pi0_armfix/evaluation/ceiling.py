"""The ceiling of the held-out metrics on the demo: the expert re-run with other random draws.

A policy that samples p(a | o) perfectly does not reproduce the recorded chunk: the teleoperator's
tremor, its Ornstein-Uhlenbeck drive noise and its per-phase draws (speed, hold time, torso bend)
are not in the observation. Its motion gain is the explained part of the motion, not 1, and its
error is not 0. On the demo that sampler exists: replay the episode in the world up to the chunk's
first frame (the same world state as the recording), then let the expert go on with a fresh random
stream. Scored like a policy, its chunks are the best any policy can do on these chunks.
"""

from __future__ import annotations

import numpy as np

from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.sim.expert import ScriptedTeleoperator
from pi0_armfix.sim.world import DemoSpec, World

REDRAW = 7  # the fourth entry of the redraw's seed sequence: unlike any stream of the world


class _SwitchableRng:
    """A random generator whose stream can be replaced mid-episode: the expert keeps references to
    its generator across frames, so the stream is switched under them."""

    def __init__(self, rng: np.random.Generator):
        self.inner = rng

    def __getattr__(self, name):
        return getattr(self.inner, name)


def redraw_chunk(spec: DemoSpec, episode: int, frame: int, horizon: int, draw: int = 0
                 ) -> np.ndarray:
    """`[H, 23]`: episode `episode`'s expert from frame `frame` on, with its own draws replaced
    from that frame by a new stream (`draw` picks it); the world before `frame` is the recorded
    one. An expert that finishes inside the chunk holds its last action."""
    world = World(spec, episode)
    expert = ScriptedTeleoperator(world)
    rng = _SwitchableRng(expert.rng)
    expert.rng = rng
    chunk = []
    for t in range(frame + horizon):
        if t == frame:
            rng.inner = np.random.default_rng([spec.seed, episode, REDRAW, frame, draw])
        action = expert.act() if not expert.finished else chunk[-1]
        if t >= frame:
            chunk.append(action)
        if not expert.finished:
            world.step(action)
    return np.asarray(chunk, np.float64)


def redraw_chunks(table: EpisodeTable, frames: np.ndarray, horizon: int, spec: DemoSpec,
                  draw: int = 0) -> np.ndarray:
    """`[N, H, 23]` the redrawn expert's chunks at global frames `frames` of a table of demo
    episodes (its `episode_index` are the world's episode numbers)."""
    frames = np.asarray(frames, np.int64)
    episode = np.searchsorted(table.episode_starts, frames, side="right") - 1
    return np.stack([redraw_chunk(spec, int(table.episode_index[e]),
                                  int(f - table.episode_starts[e]), horizon, draw)
                     for f, e in zip(frames, episode)])
