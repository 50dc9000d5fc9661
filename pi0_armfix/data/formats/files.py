"""Errors for dataset files that cannot be read, with git-LFS pointer files named as such."""

from __future__ import annotations

from pathlib import Path

_LFS_POINTER = b"version https://git-lfs"


def lfs_pointer_message(path: Path) -> str | None:
    """"PATH is a git-LFS pointer ..." with the fix, if the file is one; None otherwise."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(_LFS_POINTER))
    except OSError:
        return None
    if head != _LFS_POINTER:
        return None
    return (f"{path} is a git-LFS pointer file ({path.stat().st_size} bytes), not the data: the "
            "dataset was cloned without its LFS objects. Fetch them (`git lfs pull` in the "
            "dataset root, or `huggingface-cli download --repo-type dataset REPO "
            "--local-dir ROOT`)")


def unreadable(path: Path, what: str, err: Exception) -> ValueError:
    """The error for a `what` ("parquet file", "video file") at `path` that failed with `err`."""
    return ValueError(lfs_pointer_message(path) or f"cannot read {what} {path}: {err}")
