"""TensorBoard's event file, scalars only, written without a TensorBoard package.

tensorboardX imports torch when it is installed (about 3 s of every process start, a third of
`pi0_armfix.train`'s imports); a run only ever logs scalars, whose encoding is short: a TFRecord
file (per record: its length as uint64, the length's masked CRC-32C, the bytes, their masked
CRC-32C) of `Event` protocol buffers, the first one naming the file version.

  Event          wall_time = 1 (double), step = 2 (int64), file_version = 3 (string),
                 summary = 5 (Summary)
  Summary        value = 1 (repeated Value)
  Summary.Value  tag = 1 (string), simple_value = 2 (float)
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Mapping

FILE_VERSION = "brain.Event:2"


def _crc32c_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)  # Castagnoli, reflected
        table.append(crc)
    return tuple(table)


_CRC32C_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) of `data`, as TFRecord checks its records."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc = _CRC32C_TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def _varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1  # int64 as protobuf writes it: a negative step takes ten bytes
    while True:
        bits, value = value & 0x7F, value >> 7
        out.append(bits | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited field (wire type 2)."""
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def encode_event(wall_time: float, step: int, *, scalars: Mapping[str, float] | None = None,
                 file_version: str | None = None) -> bytes:
    """One serialized `Event`: the scalars as one `Summary` at `step`, or the file's version."""
    out = bytearray(b"\x09" + struct.pack("<d", wall_time))
    if step:
        out += b"\x10" + _varint(int(step))
    if file_version is not None:
        out += _field(3, file_version.encode())
    if scalars:
        values = b"".join(
            _field(1, _field(1, tag.encode()) + b"\x15" + struct.pack("<f", float(value)))
            for tag, value in scalars.items())
        out += _field(5, values)
    return bytes(out)


def record(data: bytes) -> bytes:
    """`data` framed as one TFRecord."""
    length = struct.pack("<Q", len(data))
    return (length + struct.pack("<I", masked_crc32c(length)) + data
            + struct.pack("<I", masked_crc32c(data)))


class EventFile:
    """`<folder>/events.out.tfevents.<time>.<host>`, unbuffered: a record is on disk when its
    write returns, and a failed write (a full disk, an OSError for the caller) leaves nothing to
    fail again at close or at exit.

    Args:
      folder: an existing folder (the run's `tensorboard/`).
    """

    def __init__(self, folder: str):
        now = time.time()
        self.path = f"{folder}/events.out.tfevents.{int(now):010d}.{socket.gethostname()}"
        self._file = open(self.path, "ab", buffering=0)
        self._write(encode_event(now, 0, file_version=FILE_VERSION))

    def write_scalars(self, step: int, scalars: Mapping[str, float]) -> None:
        self._write(encode_event(time.time(), step, scalars=scalars))

    def _write(self, event: bytes) -> None:
        data = memoryview(record(event))
        while data:
            data = data[self._file.write(data):]

    def close(self) -> None:
        self._file.close()
