"""RLDS datasets (a TFDS builder directory of array_record files) read through `tfds.data_source`.

No TensorFlow is needed: `tfds.data_source` decodes records with numpy, and image features are
read with `tfds.decode.SkipDecoding` (encoded bytes) and decoded by Pillow on demand.

An RLDS episode is a record whose `steps` feature is a nested dataset of steps; each step becomes
one frame. Steps hold `action` ([A] float), optionally `observation/state` ([S] float), image
features (any `tfds.features.Image` under `steps`, matched to batch cameras by name, see
`pi0_armfix.data.cameras`) and optionally a `language_instruction` text (the first step's is the
episode's prompt). Feature paths use "/" between nesting levels. Episodes are named by their
position in the split (0..E-1).
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.cache import digest
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats.frame_store import FrameStore

_KEYS = ("actions", "state")


def _flat_features(features: Any, prefix: str = "") -> dict[str, Any]:
    """Nested FeaturesDict -> {"observation/state": feature, ...}."""
    import tensorflow_datasets as tfds

    flat = {}
    for name, feature in features.items():
        path = f"{prefix}{name}"
        if isinstance(feature, tfds.features.FeaturesDict):
            flat.update(_flat_features(feature, path + "/"))
        else:
            flat[path] = feature
    return flat


def _nested(paths: Sequence[str], leaf: Any) -> dict[str, Any]:
    """["a/b", "a/c"] -> {"a": {"b": leaf, "c": leaf}}."""
    tree: dict[str, Any] = {}
    for path in paths:
        node = tree
        *parents, name = path.split("/")
        for parent in parents:
            node = node.setdefault(parent, {})
        node[name] = leaf
    return tree


def _get(step: Mapping[str, Any], path: str) -> Any:
    for name in path.split("/"):
        step = step[name]
    return step


def _open(root: Path, split: str, image_paths: Sequence[str]):
    """The split's data source, with image features left encoded."""
    import tensorflow_datasets as tfds

    builder = tfds.builder_from_directory(root)
    decoders = {"steps": _nested(image_paths, tfds.decode.SkipDecoding())} if image_paths else None
    return builder.as_data_source(split=split, decoders=decoders)


class RldsSource:
    """An RLDS dataset directory (the folder holding dataset_info.json and *.array_record-*).

    Args:
      root: the builder directory, e.g. `.../my_dataset/1.0.0`.
      layout: the action layout; the dataset's action width must equal `layout.real_dim`.
      split: the split to read.
      cameras: `data.cameras` ({batch camera: image feature path}); None = automatic match.
      use_images: `data.images`; False matches no camera (every camera all-zero and masked).
      action_key, state_key, prompt_key: step feature paths.

    Attributes:
      num_episodes, episode_index ([E] int64 = positions), episode_lengths ([E] int64),
      tasks ([E] prompts), fps (RLDS stores no frame rate: 0.0), cameras.
    """

    fps = 0.0

    def __init__(self, root: str | Path, layout: ActionLayout, *, split: str = "train",
                 cameras: Mapping[str, str] | None = None, use_images: bool = True,
                 action_key: str = "action",
                 state_key: str = "observation/state", prompt_key: str = "language_instruction"):
        import tensorflow_datasets as tfds

        self.root, self.split = Path(root), split
        if not (self.root / "dataset_info.json").is_file():
            raise ValueError(f"{self.root} is not a TFDS dataset directory: "
                             f"{self.root / 'dataset_info.json'} is missing")
        try:
            builder = tfds.builder_from_directory(self.root)
        except Exception as err:  # TFDS raises many types for unreadable metadata
            raise ValueError(f"cannot open the TFDS dataset {self.root}: {err}") from err
        if split not in builder.info.splits:
            raise ValueError(f"{self.root} has no split {split!r}; splits: "
                             f"{sorted(builder.info.splits)}")
        file_format = str(builder.info.file_format.value if builder.info.file_format else "")
        if file_format != "array_record":
            raise ValueError(f"{self.root} is stored as {file_format or 'tfrecord'!r}; "
                             "tfds.data_source needs array_record files")
        steps = builder.info.features["steps"] if "steps" in builder.info.features else None
        if not isinstance(steps, tfds.features.Dataset):
            raise ValueError(f"{self.root} is not an RLDS dataset: it has no 'steps' dataset "
                             "feature")
        features = _flat_features(steps.feature)
        if action_key not in features:
            raise ValueError(f"{self.root}: steps have no {action_key!r} feature "
                             f"(features: {sorted(features)})")
        self.action_width = int(np.prod(features[action_key].shape))
        layout.check_real_dim(self.action_width,
                              source=f"{self.root} (feature 'steps/{action_key}')")
        self._keys = {"actions": action_key, "state": state_key if state_key in features else None}
        self._prompt_key = prompt_key if prompt_key in features else None
        images = [path for path, f in features.items()
                  if isinstance(f, tfds.features.Image) and f.shape[-1] == 3]
        self.camera_names = tuple(images)
        self.cameras = (cameras_lib.match_cameras(images, cameras, str(self.root))
                        if use_images else {})
        self._image_paths = list(self.cameras.values())
        self.state_width = (int(np.prod(features[state_key].shape)) if self._keys["state"]
                            else 0)
        self.num_episodes = int(builder.info.splits[split].num_examples)
        self.episode_index = np.arange(self.num_episodes, dtype=np.int64)

    block_keys = _KEYS

    def identity(self) -> dict[str, Any]:
        """What the frames read from this source depend on (the key of its `FrameStore`)."""
        files = sorted((str(p.relative_to(self.root)), p.stat().st_size, p.stat().st_mtime_ns)
                       for p in self.root.iterdir() if p.is_file())
        return {"root": str(self.root.resolve()), "format": "rlds", "split": self.split,
                "files": digest(files), "keys": dict(self._keys)}

    def episode_file(self, episode: int) -> str:
        """"RLDS ROOT split S episode E" (for messages)."""
        return f"RLDS {self.root} split {self.split!r} episode {int(episode)}"

    @functools.cached_property
    def frame_store(self) -> FrameStore:
        """The on-disk frame columns of this source (built on first use)."""
        return FrameStore.open(self)

    def __repr__(self) -> str:
        return (f"RldsSource({str(self.root)!r}, split={self.split!r}, {self.num_episodes} "
                f"episodes, cameras={self.cameras})")

    def probe(self, num_episodes: int = 4, videos: bool = True) -> None:
        """Reads a sample of `num_episodes` episodes, first and last included (their array_record
        records and images decode), before any pass over the data (`videos`: unused, an RLDS
        episode holds its images)."""
        if num_episodes <= 0:
            return
        for episode in np.unique(np.linspace(0, self.num_episodes - 1, num_episodes).round()):
            self._data[int(episode)]

    @functools.cached_property
    def _data(self):
        return _open(self.root, self.split, self._image_paths)

    @functools.cached_property
    def _summary(self) -> tuple[np.ndarray, tuple[str, ...]]:
        """(lengths, prompts): RLDS stores neither outside the episodes, so one pass reads them."""
        lengths, prompts = [], []
        for position in range(self.num_episodes):
            steps = self._data[position]["steps"]
            lengths.append(len(steps))
            prompt = _get(steps[0], self._prompt_key) if self._prompt_key and len(steps) else ""
            prompts.append(prompt.decode() if isinstance(prompt, bytes) else str(prompt))
        return np.array(lengths, np.int64), tuple(prompts)

    @property
    def episode_lengths(self) -> np.ndarray:
        return self._summary[0]

    @property
    def tasks(self) -> tuple[str, ...]:
        return self._summary[1]

    def _positions(self, episodes: Sequence[int] | None) -> list[int]:
        if episodes is None:
            return list(range(self.num_episodes))
        for episode in episodes:
            if not 0 <= int(episode) < self.num_episodes:
                raise ValueError(f"episode {int(episode)} is out of range: {self.root} split "
                                 f"{self.split!r} has {self.num_episodes} episodes")
        return [int(e) for e in episodes]

    def iter_blocks(self, keys: Sequence[str] = _KEYS,
                    episodes: Sequence[int] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """One block per episode: `{"actions": [n, A], "state": [n, S], "episode_index": [n]}`
        (the keys asked for; state is [n, 0] if the steps have none), stored float dtype."""
        unknown = [k for k in keys if k not in _KEYS]
        if unknown:
            raise ValueError(f"unknown block key(s) {unknown}; known: {list(_KEYS)}")
        for position in self._positions(episodes):
            steps = self._data[position]["steps"]
            rows = [steps[i] for i in range(len(steps))]
            block = {}
            for key in keys:
                path = self._keys[key]
                if path is None:
                    block[key] = np.zeros((len(rows), 0), np.float32)
                else:
                    values = np.stack([np.asarray(_get(r, path)) for r in rows])
                    block[key] = values.reshape(len(rows), -1)
            block["episode_index"] = np.full(len(rows), position, np.int64)
            yield block

    def load_table(self, episodes: Sequence[int] | None = None, *, images: bool = True,
                   image_size: tuple[int, int] | None = None) -> EpisodeTable:
        """The chosen episodes (None = all), actions and state read by row from the
        `frame_store`, images lazy. `image_size` is unused (images are stored decoded-size)."""
        positions = self._positions(episodes)
        if not positions:
            raise ValueError(f"{self.root}: load_table needs at least one episode")
        lengths = self.episode_lengths[positions]
        starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        reader = None
        if images and self.cameras:
            reader = RldsFrameImages(self.root, self.split, self.cameras, positions, starts)
        store = self.frame_store
        return EpisodeTable(
            actions=store.column("actions", positions), state=store.column("state", positions),
            episode_starts=starts, episode_index=np.array(positions, np.int64),
            tasks=[self.tasks[p] for p in positions], images=reader, fps=self.fps)


class RldsFrameImages:
    """Lazy images of an EpisodeTable built from an RLDS split (a FrameImages).

    Keeps the encoded images of the last `max_episodes` episodes read and decodes one frame per
    request. Picklable: each process reopens the data source on first use.
    """

    def __init__(self, root: Path, split: str, cameras: Mapping[str, str],
                 positions: Sequence[int], episode_starts: np.ndarray, max_episodes: int = 4):
        self.cameras = tuple(cameras)
        self._root, self._split, self._paths = root, split, dict(cameras)
        self._positions, self._starts = list(positions), np.asarray(episode_starts)
        self._max_episodes = max_episodes
        self._data = None
        self._episodes: collections.OrderedDict[int, dict[str, list]] = collections.OrderedDict()

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_data": None, "_episodes": collections.OrderedDict()}

    def _encoded(self, position: int) -> dict[str, list]:
        if position not in self._episodes:
            if self._data is None:
                self._data = _open(self._root, self._split, list(self._paths.values()))
            steps = self._data[position]["steps"]
            rows = [steps[i] for i in range(len(steps))]
            self._episodes[position] = {camera: [_get(r, path) for r in rows]
                                        for camera, path in self._paths.items()}
            if len(self._episodes) > self._max_episodes:
                self._episodes.popitem(last=False)
        self._episodes.move_to_end(position)
        return self._episodes[position]

    def __call__(self, frame: int) -> dict[str, np.ndarray]:
        if not 0 <= frame < self._starts[-1]:
            raise IndexError(f"frame {frame} outside [0, {int(self._starts[-1])})")
        index = int(np.searchsorted(self._starts, frame, side="right")) - 1
        position, step = self._positions[index], frame - int(self._starts[index])
        encoded = self._encoded(position)
        return {camera: cameras_lib.decode_image(
            encoded[camera][step], f"{self._root} episode {position} step {step} {path!r}")
            for camera, path in self._paths.items()}
