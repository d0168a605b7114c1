"""Frame sources for the onboard node: a video file, a camera or stream URL, a folder of images.

``lockstep`` sources give every frame (every Nth with ``every``), none dropped: replays and tests.
:class:`LatestFrame` wraps a source for live use: a thread reads at the source's pace and keeps only
the newest frame, so a detector slower than the camera always works on the newest one and the
frames it skipped are counted, never queued.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from pomar.cli import InputError

log = logging.getLogger(__name__)


class SourceError(InputError, ValueError):
    """A frame source cannot be opened, or stopped before its end (a truncated video)."""


class VideoSource:
    """Frames of a video file (or any OpenCV URL / camera index). Yields (index, frame BGR).

    With ``expected_frames`` (from flight.json) a video that stops early raises :class:`SourceError`
    naming the file and the frame, after yielding every frame that decoded.
    """

    def __init__(self, path: str | int, every: int = 1, expected_frames: int | None = None):
        self.path, self.every, self.expected = path, max(1, every), expected_frames
        self.fps = 0.0

    def __iter__(self):
        import cv2

        if isinstance(self.path, (str, Path)) and not str(self.path).isdigit() and "://" not in str(self.path) \
                and not Path(self.path).exists():
            raise SourceError(f"{self.path}: video file not found")
        cap = cv2.VideoCapture(int(self.path) if str(self.path).isdigit() else str(self.path))
        if not cap.isOpened():
            raise SourceError(f"{self.path}: OpenCV cannot open this video or stream")
        self.fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
        i = 0
        try:
            while True:
                if i % self.every == 0:
                    ok, img = cap.read()
                    if not ok:
                        break
                    yield i, img
                elif not cap.grab():
                    break
                i += 1
        finally:
            cap.release()
        if self.expected is not None and i < self.expected:
            raise SourceError(f"{self.path}: video stops after {i} of {self.expected} frames (truncated or corrupt); "
                              f"the {i} frames before were processed")


class ImageFolderSource:
    """Images of a folder in name order (jpg, jpeg, png, bmp, tif)."""

    def __init__(self, folder: str | Path, every: int = 1):
        self.folder, self.every = Path(folder), max(1, every)
        if not self.folder.is_dir():
            raise SourceError(f"{self.folder}: not a folder of images")
        self.files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"))
        self.fps = 0.0

    def __iter__(self):
        import cv2

        for i, p in enumerate(self.files):
            if i % self.every:
                continue
            img = cv2.imread(str(p))
            if img is None:
                log.warning("%s: cannot be read as an image; skipped", p)
                continue
            yield i, img


class LatestFrame:
    """Reads a source in a thread at real time (``fps``, or as fast as it comes for a live camera) and
    hands out only the newest frame. ``dropped`` counts the frames nobody took. ``started_at`` (unix time, with
    ``fps``): the source is a camera that started then; the frames whose time has passed are skipped (``skipped``),
    not dropped: nobody was there to take them."""

    def __init__(self, source, fps: float | None = None, started_at: float | None = None):
        self.source, self.fps, self.started_at = source, fps, started_at
        self.skipped = 0
        self._latest = None
        self._cond = threading.Condition()
        self._done = False
        self.error: Exception | None = None
        self.read = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        t0 = time.monotonic()
        if self.started_at is not None and self.fps:
            t0 += self.started_at - time.time()
        try:
            for n, (i, img) in enumerate(self.source):
                if self.fps:
                    delay = t0 + n / self.fps - time.monotonic()
                    if delay < -1.0 / self.fps and self.started_at is not None:
                        self.skipped += 1  # taken before this node was there
                        continue
                    if delay > 0:
                        time.sleep(delay)
                with self._cond:
                    if self._latest is not None:
                        self.dropped += 1
                    self._latest = (i, img)
                    self.read += 1
                    self._cond.notify()
        except Exception as exc:  # reported to the consumer once the frames before it are taken
            self.error = exc
        finally:
            with self._cond:
                self._done = True
                self._cond.notify()

    def __iter__(self):
        while True:
            with self._cond:
                while self._latest is None and not self._done:
                    self._cond.wait()
                item, self._latest = self._latest, None
                if item is None and self._done:
                    break
            if item is not None:
                yield item
        if self.error is not None:
            raise self.error
