"""Episodes of a LeRobot set whose video files are missing (a partial download or mirror, or
videos kept under another path than `meta/info.json`'s `video_path`): found once when the set is
opened (one `stat` per file), named in one line, then refused before a pass reads images or left
out (`data.skip_missing_videos`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

from pi0_armfix.data.formats.lerobot_meta import EpisodeRecord


@dataclasses.dataclass(frozen=True)
class MissingVideos:
    """`missing`: the episodes with a missing video file of a read camera; `found`: what is
    missing, named in one line, and `fix`: what to do ('' where nothing is missing)."""

    missing: tuple[EpisodeRecord, ...] = ()
    found: str = ""
    fix: str = ""

    @property
    def message(self) -> str | None:
        """The one line a pass that reads images is refused with (None: nothing missing)."""
        return f"{self.found}; {self.fix}" if self.found else None

    @classmethod
    def find(cls, root: Path, episodes: Sequence[EpisodeRecord], video_keys: Sequence[str],
             template: str | None) -> MissingVideos:
        """The missing video files of `episodes` at `root`; `template`: `meta/info.json`'s
        `video_path`, named where no file of any episode exists (the path, not the download,
        is then what is wrong)."""
        missing = tuple(e for e in episodes
                        if any(not e.videos[k][0].is_file() for k in video_keys))
        if not missing:
            return cls()
        example = next(e.videos[k][0] for e in missing for k in video_keys
                       if not e.videos[k][0].is_file())
        if len(missing) == len(episodes) and not any(
                e.videos[k][0].is_file() for e in episodes for k in video_keys):
            return cls(missing,
                       f"no video file of the {len(episodes)} episodes of {root} is where "
                       f"meta/info.json's video_path ({template!r}) puts it (e.g. {example})",
                       "where the videos sit under another folder (video/ rather than videos/, "
                       f"say), set video_path in {root / 'meta' / 'info.json'} to their path; "
                       "without videos, read no camera (data.images=False)")
        return cls(missing,
                   f"missing video files for {len(missing)} of {len(episodes)} episodes of "
                   f"{root} (e.g. {example}): episodes {', '.join(str(e.index) for e in missing)}",
                   "fetch the files, or set data.skip_missing_videos=True to leave these episodes "
                   "out of training and evaluation")

    def kept(self, episodes: Sequence[EpisodeRecord]
             ) -> tuple[list[EpisodeRecord], tuple[int, ...]]:
        """`(the episodes with every video file, the ids of the missing ones)`.

        Raises:
          ValueError where no episode is left.
        """
        kept = [e for e in episodes if e not in self.missing]
        if not kept:
            raise ValueError(f"{self.found}: no episode is left (data.skip_missing_videos=True)")
        return kept, tuple(e.index for e in self.missing)

    def check(self) -> None:
        """Refuses, before a pass reads images, a set with missing videos, naming them all."""
        if self.message:
            raise ValueError(self.message)
