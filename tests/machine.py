"""How fast this machine is now, against the one the suite's figures were measured on: a fixed small workload of the
ground's kind (SIFT, linear algebra, plain Python), timed at the start of a run. Tests whose subject is a wall-clock
behaviour (a live stream played at the flight's pace) slow their clock by it, so that they assert the behaviour, not
the machine's speed."""

from __future__ import annotations

import time

#: The workload's median seconds on the development machine with nothing else running (2026-11-28).
REFERENCE_S = 0.275


def _once() -> float:
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (360, 640), np.uint8), (0, 0), 2)
    a = rng.random((150, 150))
    t = time.perf_counter()
    for _ in range(6):
        cv2.SIFT_create(1500).detectAndCompute(img, None)
        np.linalg.svd(a)
        sum(i * i for i in range(150_000))
    return time.perf_counter() - t


def workload_seconds(repeats: int = 3) -> float:
    """The workload's median seconds, on one OpenCV thread (as a busy machine gives one core)."""
    import cv2

    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return sorted(_once() for _ in range(repeats))[repeats // 2]
    finally:
        cv2.setNumThreads(n)


def slowness() -> float:
    """How many times slower than the development machine this one runs now (at least 1)."""
    return max(1.0, workload_seconds() / REFERENCE_S)
