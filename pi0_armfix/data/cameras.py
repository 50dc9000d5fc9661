"""Which stored camera feeds which batch camera, and how a stored image becomes pixels.

Shared by every data source. The batch carries three cameras (see the team contract):
`base_0_rgb` (B1K head camera), `left_wrist_0_rgb` and `right_wrist_0_rgb`. Stored camera
names differ between datasets, so the automatic match looks at substrings of the name
(case-insensitive), in this order:

  "left_wrist" / "wrist_left"    -> left_wrist_0_rgb
  "right_wrist" / "wrist_right"  -> right_wrist_0_rgb
  "wrist" (a single wrist camera) -> left_wrist_0_rgb   (openpi's convention, e.g. DROID)
  "head" / "base"                 -> base_0_rgb

Names that contain "depth", "seg" or "mask" are never matched (B1K stores depth and
segmentation videos beside the RGB ones). Anything else is left out; `data.cameras`
(`{batch camera: stored name}`) names the feeds explicitly and replaces the automatic match.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Mapping, Sequence

import numpy as np
from PIL import Image

BATCH_CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")

_NOT_RGB = ("depth", "seg", "mask")
_RULES = (
    (("left_wrist", "wrist_left"), "left_wrist_0_rgb"),
    (("right_wrist", "wrist_right"), "right_wrist_0_rgb"),
    (("wrist",), "left_wrist_0_rgb"),
    (("head", "base"), "base_0_rgb"),
)


def _auto_camera(name: str) -> str | None:
    lowered = name.lower()
    if any(word in lowered for word in _NOT_RGB):
        return None
    for words, camera in _RULES:
        if any(word in lowered for word in words):
            return camera
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
    matched: dict[str, list[str]] = {}
    for name in names:
        camera = _auto_camera(name)
        if camera is not None:
            matched.setdefault(camera, []).append(name)
    for camera, found in matched.items():
        if len(found) > 1:
            raise ValueError(f"{where}: cameras {found} all match batch camera {camera!r}; "
                             f"choose one with data.cameras={{{camera!r}: NAME}}")
    unmatched = [n for n in names if n not in {f[0] for f in matched.values()}]
    if unmatched:
        logging.info("%s: cameras %s feed no batch camera (set data.cameras to use them)",
                     where, unmatched)
    return {camera: matched[camera][0] for camera in BATCH_CAMERAS if camera in matched}


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
