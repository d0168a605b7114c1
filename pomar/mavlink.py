"""MAVLink 2 access shared by the simulator (writes .tlog) and the onboard node (reads it).

pymavlink picks MAVLink 1 or 2 from the MAVLINK20 environment variable when it is first imported;
this module sets it before importing, and uses the ArduPilot dialect (a superset of common, so
it also decodes PX4's messages).

A .tlog is a sequence of records: an 8-byte big-endian timestamp (microseconds since the Unix
epoch, when the ground station logged the packet) followed by one MAVLink packet.
"""

from __future__ import annotations

import os
import struct

os.environ.setdefault("MAVLINK20", "1")


def dialect():
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


class TlogWriter:
    """Writes MAVLink 2 packets into a .tlog, one sender object per (system, component)."""

    def __init__(self, path, system_id: int = 1):
        self._m = dialect()
        self._f = open(path, "wb")
        self._system_id = system_id
        self._senders = {}

    def sender(self, component_id: int):
        """The pymavlink encoder for a component (its *_encode methods build messages)."""
        if component_id not in self._senders:
            self._senders[component_id] = self._m.MAVLink(None, srcSystem=self._system_id, srcComponent=component_id)
        return self._senders[component_id]

    def write(self, t_unix: float, component_id: int, msg) -> None:
        mav = self.sender(component_id)
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self._f.write(struct.pack(">Q", int(round(t_unix * 1e6))) + buf)

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
