"""SIGTERM handled as Ctrl-C (KeyboardInterrupt in the main thread), so that ``kill PID`` stops a process the way an
operator's Ctrl-C does: the ground finishes and writes its map, and a replay stops the processes it started.
Python's default for SIGTERM ends the process at once, with no ``finally`` run."""

from __future__ import annotations

import signal
import threading


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def stop_on_sigterm() -> None:
    """Make SIGTERM raise KeyboardInterrupt in the main thread (a no-op outside it, where signals cannot be set)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _interrupt)
