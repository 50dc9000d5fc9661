"""Which stored camera feeds which batch camera, and how a stored image becomes pixels.

Shared by every data source. The batch carries three cameras (docs/design.md §4):
`base_0_rgb` (the head / scene camera), `left_wrist_0_rgb` and `right_wrist_0_rgb`. Stored camera
names differ between datasets, so the automatic match looks for aliases in the name
(case-insensitive, as whole `_`/`.`/`-`-separated words or joined words), batch camera by batch
camera, aliases in priority order:

  | batch camera        | aliases, highest priority first                                   |
  |---------------------|-------------------------------------------------------------------|
  | left_wrist_0_rgb    | left_wrist, wrist_left, cam_left_wrist, leftwrist, left_hand,      |
  |                     | left_realsense                                                    |
  | right_wrist_0_rgb   | right_wrist, wrist_right, cam_right_wrist, rightwrist, right_hand, |
  |                     | right_realsense                                                   |
  | left_wrist_0_rgb    | wrist, wrist_image, hand (a single wrist camera: openpi's DROID    |
  |                     | convention), when no left wrist matched                            |
  | base_0_rgb          | head, cam_high, ego_view, base, front, top, overhead, exterior,    |
  |                     | scene, main, image, zed_link                                       |

B1K 2025 (`observation.images.rgb.head` / `.left_wrist` / `.right_wrist`), B1K 2026
(`observation.rgb.zed_link_camera_0`, `.left_realsense_link_camera_0`, `.right_...`), ALOHA (`cam_high`,
`cam_left_wrist`, `cam_right_wrist`; `cam_low` is left out), GR00T-style `ego_view`, LIBERO-style
`image` + `wrist_image` all match. For a batch camera, the stored name with the highest-priority
alias wins; two names at the same priority are an error listing both. Names containing "depth",
"seg" or "mask" are never matched (B1K stores depth and segmentation videos beside the RGB ones).
`data.cameras` (`{batch camera: stored name}`) names the feeds explicitly and replaces the
automatic match; a batch camera the dataset does not feed is masked out (image_mask False).
"""

from __future__ import annotations

import io
import logging
import re
from collections.abc import Mapping, Sequence

import numpy as np
from PIL import Image

BATCH_CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")

_NOT_RGB = ("depth", "seg", "mask")
# (batch camera, aliases in priority order); a later rule only fills a camera still unmatched.
ALIASES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("left_wrist_0_rgb", ("left_wrist", "wrist_left", "cam_left_wrist", "leftwrist",
                          "left_hand", "left_realsense")),
    ("right_wrist_0_rgb", ("right_wrist", "wrist_right", "cam_right_wrist", "rightwrist",
                           "right_hand", "right_realsense")),
    ("left_wrist_0_rgb", ("wrist", "wrist_image", "hand")),
    ("base_0_rgb", ("head", "cam_high", "ego_view", "base", "front", "top", "overhead",
                    "exterior", "scene", "main", "image", "zed_link")),
)


def _words(name: str) -> tuple[list[str], str]:
    """The name's lower-case words (split at `.`, `/`, `-`, `_`) and its `_`-joined form."""
    words = [w for w in re.split(r"[./\-_\s]+", name.lower()) if w]
    return words, "_".join(words)


def _alias_rank(name: str, aliases: Sequence[str]) -> int | None:
    """Priority (index into `aliases`) of the best alias in `name`, or None."""
    words, joined = _words(name)
    if any(w in _NOT_RGB or w.startswith(_NOT_RGB) for w in words):
        return None
    for rank, alias in enumerate(aliases):
        if alias in words or re.search(rf"(^|_){re.escape(alias)}(_|$)", joined):
            return rank
    return None


def match_cameras(names: Sequence[str], override: Mapping[str, str] | None,
                  where: str) -> dict[str, str]:
    """Maps batch cameras to stored camera names.

    Args:
      names: the stored image/video feature names of the dataset.
      override: `data.cameras`, `{batch camera: stored name}`; empty or None = automatic match.
      where: the dataset, named in error messages.

    Returns:
      `{batch camera: stored name}` for the cameras the dataset provides, in BATCH_CAMERAS order.
    """
    if override:
        for camera, name in override.items():
            if camera not in BATCH_CAMERAS:
                raise ValueError(f"data.cameras has unknown batch camera {camera!r}; "
                                 f"known: {list(BATCH_CAMERAS)}")
            if name not in names:
                raise ValueError(f"data.cameras[{camera!r}] = {name!r} is not a camera of {where}; "
                                 f"its cameras are {list(names)}")
        return {camera: override[camera] for camera in BATCH_CAMERAS if camera in override}
    matched: dict[str, str] = {}
    for camera, aliases in ALIASES:
        if camera in matched:
            continue
        free = [n for n in names if n not in matched.values()]
        ranked = [(rank, n) for n in free if (rank := _alias_rank(n, aliases)) is not None]
        if not ranked:
            continue
        best = min(rank for rank, _ in ranked)
        tied = [n for rank, n in ranked if rank == best]
        if len(tied) > 1:
            raise ValueError(f"{where}: cameras {tied} all match batch camera {camera!r}; "
                             f"choose one with data.cameras={{{camera!r}: NAME}}")
        matched[camera] = tied[0]
    unmatched = [n for n in names if n not in matched.values()]
    if unmatched:
        logging.info("%s: cameras %s feed no batch camera (set data.cameras to use them)",
                     where, unmatched)
    return {camera: matched[camera] for camera in BATCH_CAMERAS if camera in matched}


def missing_cameras_message(matched: Mapping[str, str], names: Sequence[str], where: str
                            ) -> str | None:
    """The one warning for batch cameras the dataset does not feed (None if all are fed)."""
    missing = [c for c in BATCH_CAMERAS if c not in matched]
    if not missing:
        return None
    return (f"{where}: no camera feeds {missing} (matched: {dict(matched)}; the dataset's "
            f"cameras: {list(names)}); training with them masked out. Name a feed with "
            f"data.cameras={{'<batch camera>': '<stored name>'}} (aliases: "
            f"pi0_armfix/data/cameras.py)")


def decode_image(data: bytes, where: str) -> np.ndarray:
    """PNG/JPEG bytes -> uint8 [h, w, 3]. `where` (file, frame) is named if the bytes are bad."""
    try:
        with Image.open(io.BytesIO(data)) as image:
            return np.asarray(image.convert("RGB"))
    except Exception as err:  # PIL raises several unrelated types for corrupt data
        raise ValueError(f"cannot decode the image of {where}: {err}") from err


def encode_image(image: np.ndarray, fmt: str) -> bytes:
    """uint8 [h, w, 3] -> PNG or JPEG bytes (deterministic for a given Pillow version)."""
    buffer = io.BytesIO()
    if fmt == "png":
        Image.fromarray(image).save(buffer, format="PNG")
    elif fmt == "jpeg":
        Image.fromarray(image).save(buffer, format="JPEG", quality=95)
    else:
        raise ValueError(f"image format must be 'png' or 'jpeg', got {fmt!r}")
    return buffer.getvalue()
