"""Dataset formats: LeRobot v2.1 / v3.0 (reader, metadata, frames, writer, stats files), RLDS,
mp4 video, the on-disk frame store, the embedded demo, and `sources.open_source`, which opens any
of them as one `Source` (docs/design.md)."""
