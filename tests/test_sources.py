"""Frame sources: lock-step gives every frame; real time keeps only the newest and counts the rest."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from onboard.sources import ImageFolderSource, LatestFrame, SourceError, VideoSource


def test_lockstep_every_nth(small_flight):
    n = small_flight.meta().frame_count
    assert [i for i, _ in VideoSource(small_flight.video)] == list(range(n))
    assert [i for i, _ in VideoSource(small_flight.video, every=3)] == list(range(0, n, 3))


def test_realtime_takes_the_newest_frame_and_counts_drops(small_flight):
    n = small_flight.meta().frame_count
    latest = LatestFrame(VideoSource(small_flight.video), fps=40.0)  # the camera: 40 fps
    taken = []
    for i, _ in latest:  # a detector at about 10 fps
        taken.append(i)
        time.sleep(0.1)
    assert latest.read == n and taken[-1] == n - 1 and taken == sorted(taken)
    assert latest.dropped > 0 and len(taken) + latest.dropped == n


def test_a_camera_that_started_before_the_node_gives_the_frames_from_now(small_flight):
    """A node restarted mid-flight (--camera-started-at): the frames taken before it was there are skipped, not
    dropped, and the first it gets is the one its camera takes now."""
    n = small_flight.meta().frame_count
    fps = 20.0
    latest = LatestFrame(VideoSource(small_flight.video), fps=fps, started_at=time.time() - 0.5)
    taken = [i for i, _ in latest]
    assert 6 <= taken[0] <= 14 and latest.skipped == taken[0]  # 10 frames in 0.5 s at 20 fps, give or take
    assert taken[-1] == n - 1 and latest.read + latest.skipped == n
    t0 = time.monotonic()  # before the start time is set: opening the video may take a while on a busy machine
    later = LatestFrame(VideoSource(small_flight.video), fps=fps, started_at=time.time() + 0.3)  # not yet started
    first = next(iter(later))[0]
    assert first == 0 and time.monotonic() - t0 >= 0.25 and later.skipped == 0


def test_image_folder(tmp_path):
    for k in (2, 0, 1):
        cv2.imwrite(str(tmp_path / f"img_{k:03d}.png"), np.full((8, 8, 3), k * 50, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    got = [(i, int(img[0, 0, 0])) for i, img in ImageFolderSource(tmp_path)]
    assert got == [(0, 0), (1, 50), (2, 100)]
    with pytest.raises(SourceError, match="not a folder"):
        ImageFolderSource(tmp_path / "none")


def test_missing_video(tmp_path):
    with pytest.raises(SourceError, match="not found"):
        list(VideoSource(tmp_path / "none.mp4"))
