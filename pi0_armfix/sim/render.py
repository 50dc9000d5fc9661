"""The demo world's cameras: scenes (`World.scene()`) -> uint8 images, vectorized over frames.

The dataset generator renders a whole episode at once; the environment renders one frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pi0_armfix.sim.world import OPEN_GAP

FINGERS = (200, 200, 205)


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    return u, v


def _disc(canvas: np.ndarray, u0: np.ndarray, v0: np.ndarray, radius: np.ndarray,
          colour: np.ndarray, visible: np.ndarray, wrap: bool = False) -> None:
    """Paints anti-aliased discs into canvas [n, S, S, 3] float32; per-frame centre/radius [n],
    colour [n, 3] or [3], visible [n] bool. `wrap`: columns wrap around (a panorama)."""
    size = canvas.shape[1]
    u, v = _grid(size)
    du = u[None] - u0.astype(np.float32)[:, None, None]
    if wrap:
        du = (du + size / 2) % size - size / 2
    distance = np.hypot(du, v[None] - v0.astype(np.float32)[:, None, None])
    alpha = np.clip(radius.astype(np.float32)[:, None, None] + 0.5 - distance, 0, 1)
    alpha *= visible[:, None, None]
    colour = np.broadcast_to(np.asarray(colour, np.float32), (len(u0), 3))
    canvas += alpha[..., None] * (colour[:, None, None, :] - canvas)


def render_head(scenes: Sequence[dict], colour: tuple, size: int) -> np.ndarray:
    """[n, S, S, 3] uint8 panoramas of the target (the task's `colour`)."""
    n = len(scenes)
    u, v = _grid(size)
    heading = np.array([s["heading"] for s in scenes], np.float32)
    rel = np.array([s["target"] for s in scenes], np.float32)
    canvas = np.empty((n, size, size, 3), np.float32)
    stripes = 0.5 + 0.5 * np.cos(4 * (u[None] / size * 2 * np.pi - heading[:, None, None]))
    wall = np.array([150, 140, 120], np.float32) + 40 * stripes[..., None]
    floor = np.array([90, 80, 70], np.float32) + 60 * (v[None, ..., None] / size)
    canvas[:] = np.where((v < size / 2)[None, ..., None], wall, floor)
    distance = np.hypot(rel[:, 0], rel[:, 1])
    bearing = np.arctan2(rel[:, 1], rel[:, 0])
    # Panorama: bearing +pi (left) .. -pi (right) across the width; near objects sit low and big.
    column = size / 2 - bearing / np.pi * size / 2
    row = size / 2 + (size / 2 - 3) * np.exp(-distance / 0.8)
    radius = np.clip(size / 10 / (distance + 0.25), 1.0, size / 4)
    _disc(canvas, column, row, radius, colour, np.ones(n, bool), wrap=True)
    return canvas.round().astype(np.uint8)


def render_wrist(scenes: Sequence[dict], arm: str, size: int) -> np.ndarray:
    """[n, S, S, 3] uint8 views of `arm`'s fingers, held object and reach marker."""
    n = len(scenes)
    u, v = _grid(size)
    canvas = np.empty((n, size, size, 3), np.float32)
    canvas[:] = np.array([70, 75, 85], np.float32) + 50 * (v[None, ..., None] / size)
    marks = [s["marks"].get(arm) for s in scenes]
    has_mark = np.array([m is not None for m in marks])
    offset = np.array([m[0] if m is not None else np.zeros(3) for m in marks], np.float32)
    mark_colour = np.array([m[1] if m is not None else (0, 0, 0) for m in marks], np.float32)
    _disc(canvas, size / 2 + offset[:, 0] * size / 4, size / 2 + offset[:, 1] * size / 4,
          np.clip(size / 10 * (1.2 - 0.4 * offset[:, 2]), 1.0, size / 4), mark_colour, has_mark)
    held = [s["held"][arm] for s in scenes]
    is_held = np.array([h is not None for h in held])
    held_colour = np.array([h if h is not None else (0, 0, 0) for h in held], np.float32)
    _disc(canvas, np.full(n, size / 2), np.full(n, size * 0.85),
          np.full(n, size * 0.12), held_colour, is_held)
    # Fingers: two bars at the bottom whose gap is the gripper's.
    gap = np.array([s["gap"][arm] for s in scenes], np.float32) / OPEN_GAP * size * 0.35
    left_edge = size / 2 - gap[:, None, None] / 2
    right_edge = size / 2 + gap[:, None, None] / 2
    bottom = (v >= size * 0.7)[None]
    fingers = bottom & (((u[None] >= left_edge - size * 0.12) & (u[None] < left_edge)) |
                        ((u[None] >= right_edge) & (u[None] < right_edge + size * 0.12)))
    canvas[fingers] = FINGERS
    return canvas.round().astype(np.uint8)


def render(scenes: Sequence[dict], colour: tuple, size: int) -> dict[str, np.ndarray]:
    """{"head", "left_wrist", "right_wrist"} -> uint8 [n, S, S, 3]."""
    return {"head": render_head(scenes, colour, size),
            "left_wrist": render_wrist(scenes, "left", size),
            "right_wrist": render_wrist(scenes, "right", size)}
