"""Telemetry from a live MAVLink link (the readers of recorded logs are in :mod:`pomar.telemetry`)."""

from __future__ import annotations

import logging
import threading
import time

from pomar.telemetry import TelemetryLog
from pomar.telemetry.tlog import MavlinkAccumulator

log = logging.getLogger(__name__)


class LiveTelemetry:
    """Telemetry from a live MAVLink link (``udpin:127.0.0.1:14550``, ``/dev/ttyUSB0,57600``, ...).

    A thread reads the link; :meth:`snapshot` gives a :class:`TelemetryLog` of everything so far. The
    node identifies itself as a companion computer (MAV_COMP_ID_ONBOARD_COMPUTER, 191) with a 1 Hz
    HEARTBEAT.
    """

    COMPONENT_ID = 191

    def __init__(self, url: str, system_id: int = 1, max_gap_s: float = 1.0, heartbeat_s: float = 1.0):
        from pomar.mavlink import dialect

        self._m = dialect()
        from pymavlink import mavutil

        self.url, self.max_gap_s = url, max_gap_s
        self._conn = mavutil.mavlink_connection(url, dialect="ardupilotmega", source_system=system_id,
                                                source_component=self.COMPONENT_ID, autoreconnect=True)
        self._acc = MavlinkAccumulator()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._read, daemon=True),
                         threading.Thread(target=self._beat, args=(heartbeat_s,), daemon=True)]
        for t in self._threads:
            t.start()

    def _read(self):
        while not self._stop.is_set():
            try:
                m = self._conn.recv_match(blocking=True, timeout=0.2)
            except Exception as exc:  # a broken link: keep what was received, say why
                log.warning("%s: %s", self.url, exc)
                time.sleep(0.2)
                continue
            if m is not None:
                with self._lock:
                    self._acc.add(m)

    def _beat(self, period):
        m = self._m
        while not self._stop.wait(period):
            try:
                self._conn.mav.heartbeat_send(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)
            except Exception as exc:  # no peer yet (udpin before the first packet): try again
                log.debug("heartbeat not sent: %s", exc)

    def snapshot(self) -> TelemetryLog:
        with self._lock:
            return self._acc.build(self.url, self.max_gap_s, quiet=True)

    def close(self):
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self._conn.close()
