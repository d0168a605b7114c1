"""The ground's checkpoint: an append-only journal of every wire message it accepted.

A restarted ground reads the journal back through a fresh pipeline (same messages, same order, so
the same state), then carries on with the stream; the publisher's history fills in what was sent
while it was down, and the pipeline drops what it already has. A record cut short by a kill is
detected on reading and cut off; everything before it is kept.

Record: 4-byte little-endian length, then the message's bytes exactly as they came off the wire.
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

log = logging.getLogger(__name__)

_LEN = struct.Struct("<I")


class Journal:
    def __init__(self, path: Path, fsync_every: int = 50):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "ab")
        self._n = 0
        self.fsync_every = fsync_every

    def append(self, payload: bytes) -> None:
        self._f.write(_LEN.pack(len(payload)) + payload)
        self._n += 1
        self._f.flush()
        if self._n % self.fsync_every == 0:
            os.fsync(self._f.fileno())

    def close(self) -> None:
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()


def read_journal(path: Path) -> list[bytes]:
    """Every complete record; a truncated tail is reported and cut off the file."""
    path = Path(path)
    if not path.is_file():
        return []
    data = path.read_bytes()
    out, pos = [], 0
    while pos + _LEN.size <= len(data):
        (n,) = _LEN.unpack_from(data, pos)
        if pos + _LEN.size + n > len(data):
            break
        out.append(data[pos + _LEN.size: pos + _LEN.size + n])
        pos += _LEN.size + n
    if pos < len(data):
        log.warning("%s: the last record is cut short (%d bytes after %d complete records): cut off",
                    path, len(data) - pos, len(out))
        with open(path, "r+b") as f:
            f.truncate(pos)
    return out
