"""The ground's checkpoint: an append-only journal of every wire message it accepted.

A restarted ground reads the journal back through a fresh pipeline (same messages, same order, so
the same state), then carries on with the stream; the publisher's history fills in what was sent
while it was down, and the pipeline drops what it already has.

File: the 8-byte header ``POMARJ02``, then records. Record: the 4-byte marker ``PJR\\x1e``, the
payload's length (4 bytes, little-endian), the CRC32 of length and payload (4 bytes, little-endian),
then the payload: the message's bytes exactly as they came off the wire.

Reading never trusts a record blindly: a bad marker, a length past the end of the file or a CRC that
does not match makes the reader look for the next marker, so one damaged record costs that record
only. The damaged bytes are copied to a side file beside the journal
(``journal.bin.damaged-<offset>``) and reported; the journal itself is never rewritten or truncated.
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from pomar.cli import InputError

log = logging.getLogger(__name__)

HEADER = b"POMARJ02"
MARKER = b"PJR\x1e"
_REC = struct.Struct("<4sII")  # marker, length, crc32(length + payload)
_LEN = struct.Struct("<I")


class JournalError(InputError, ValueError):
    """A file that is not a journal this build can read."""


def _crc(payload: bytes) -> int:
    return zlib.crc32(payload, zlib.crc32(_LEN.pack(len(payload))))


def record(payload: bytes) -> bytes:
    """One journal record holding ``payload``."""
    return _REC.pack(MARKER, len(payload), _crc(payload)) + payload


class Journal:
    """Appends records. A journal that cannot be written (a full disk, a read-only folder) stops the journal, never
    the flight: it warns once, keeps why in ``failed`` (the flight can then no longer be resumed from it), and writes
    nothing more, so that the records before stay as they were (a record cut short at the end is a damaged record to
    the reader, which keeps the others)."""

    def __init__(self, path: Path, fsync_every: int = 50):
        self.path = Path(path)
        self._f = None
        self.failed: str | None = None
        self._n = 0
        self.fsync_every = fsync_every
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            new = not self.path.exists() or self.path.stat().st_size == 0
            if not new:
                with open(self.path, "rb") as f:
                    _check_header(self.path, f.read(len(HEADER)))
            self._f = open(self.path, "ab")
            if new:
                self._f.write(HEADER)
                self._f.flush()
        except OSError as exc:
            self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        self.failed = f"{self.path}: {exc.strerror or exc}"
        log.warning("the journal cannot be written (%s): the flight goes on, but can no longer be resumed from it",
                    self.failed)
        if self._f is not None:
            try:
                self._f.close()
            except OSError:
                pass
            self._f = None

    def append(self, payload: bytes) -> None:
        if self._f is None:
            return
        try:
            self._f.write(record(payload))
            self._n += 1
            self._f.flush()
            if self._n % self.fsync_every == 0:
                os.fsync(self._f.fileno())
        except OSError as exc:
            self._fail(exc)

    def close(self) -> None:
        if self._f is None:
            return
        try:
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()
        except OSError as exc:
            self._fail(exc)


def _check_header(path: Path, head: bytes) -> None:
    if head == HEADER:
        return
    if head[:6] == HEADER[:6]:
        raise JournalError(f"{path}: journal format {head[6:8]!r}, this build reads {HEADER[6:8]!r}")
    raise JournalError(f"{path}: not a pomar journal of this version (an older ground's journal has no header and "
                       f"no checksums): move it away, or run the ground with --fresh to start the flight anew")


@dataclass
class JournalRead:
    records: list[bytes] = field(default_factory=list)
    damaged: list[tuple[int, int]] = field(default_factory=list)  # (offset, bytes) of each damaged stretch
    side_files: list[Path] = field(default_factory=list)

    @property
    def damaged_bytes(self) -> int:
        return sum(n for _, n in self.damaged)


def read_journal_report(path: Path) -> JournalRead:
    """Every intact record, in order, and where the damage was. Damaged stretches are copied to side files."""
    path = Path(path)
    out = JournalRead()
    if not path.is_file():
        return out
    data = path.read_bytes()
    if not data:
        return out
    _check_header(path, data[:len(HEADER)])
    pos, bad_from = len(HEADER), None
    while pos < len(data):
        ok = False
        if data[pos:pos + 4] == MARKER and pos + _REC.size <= len(data):
            _, n, crc = _REC.unpack_from(data, pos)
            end = pos + _REC.size + n
            if end <= len(data) and _crc(data[pos + _REC.size:end]) == crc:
                ok = True
        if ok:
            if bad_from is not None:
                _set_aside(path, data, bad_from, pos, out)
                bad_from = None
            out.records.append(data[pos + _REC.size:end])
            pos = end
        else:
            if bad_from is None:
                bad_from = pos
            nxt = data.find(MARKER, pos + 1)  # resynchronise on the next marker
            pos = len(data) if nxt < 0 else nxt
    if bad_from is not None:
        _set_aside(path, data, bad_from, len(data), out)
    return out


def _set_aside(path: Path, data: bytes, start: int, end: int, out: JournalRead) -> None:
    side = path.with_name(f"{path.name}.damaged-{start}")
    if not side.exists():
        side.write_bytes(data[start:end])
    out.damaged.append((start, end - start))
    out.side_files.append(side)
    log.warning("%s: %d damaged bytes at offset %d skipped (copied to %s)", path, end - start, start, side.name)


def read_journal(path: Path) -> list[bytes]:
    """Every intact record, in order (see :func:`read_journal_report`)."""
    return read_journal_report(path).records
