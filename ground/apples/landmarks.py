"""Placing a frame by the apples it sees, where no image placed it (the drone stopped sending keyframes): the apples
already mapped are landmarks, and the frame's detections are their images.

The frame's pose is predicted from the two frames before it (constant velocity over a frame's time), the landmarks
are projected there, each detection is paired with the mutually nearest projection within GATE_PX, and the pose is
the perspective-n-point fit to the pairs (RANSAC, then refined on its inliers). Frames placed so feed the
association, whose apples then place the frames after them: the map goes on where the images stopped, drifting
with the apples' own error over the distance flown instead of jumping with the GPS's error from frame to frame.

    R, t = place_by_apples(camera, centres, landmarks, before, last)   # or None
"""

from __future__ import annotations

import cv2
import numpy as np

#: Pairs a fit needs, at least, and inliers it keeps: fewer and it is left to the pose it had.
MIN_PAIRS = 8
#: How far from its predicted image a detection may lie to be paired (px).
GATE_PX = 25.0
#: An inlier's reprojection error (px) in the fit.
REPROJECTION_PX = 3.0
#: A pose placed so is stated to this uncertainty (m, degrees): as a tracked frame's.
SIGMA = (0.02, 0.1)


def predict(before, last) -> tuple[np.ndarray, np.ndarray]:
    """The next frame's world-to-camera (R, t) at the same velocity and turn rate as from ``before`` to ``last`` (the
    two frames' poses: ``R``, ``centre``)."""
    dR = last.R @ before.R.T  # the turn over a frame, in the camera's frame
    R = dR @ last.R
    c = 2 * last.centre - before.centre
    return R, -R @ c


def place_by_apples(camera, centres: np.ndarray, landmarks: np.ndarray, before, last) -> tuple | None:
    """The frame's world-to-camera (R, t) from its detection centres (n, 2; OpenCV pixels) and the mapped apples
    (m, 3; map frame), given the poses of the two frames placed before it; None where too few pairs
    agree."""
    if len(centres) < MIN_PAIRS or len(landmarks) < MIN_PAIRS:
        return None
    R0, t0 = predict(before, last)
    uv, z = camera.project(landmarks, R0, t0)
    inside = (z > 0) & (uv[:, 0] > -GATE_PX) & (uv[:, 0] < camera.width + GATE_PX) & (uv[:, 1] > -GATE_PX) & \
        (uv[:, 1] < camera.height + GATE_PX)
    if inside.sum() < MIN_PAIRS:
        return None
    L, uv = landmarks[inside], uv[inside]
    d = np.linalg.norm(centres[:, None, :] - uv[None, :, :], axis=2)
    near_l, near_c = d.argmin(1), d.argmin(0)
    pairs = [(i, j) for i, j in enumerate(near_l) if near_c[j] == i and d[i, j] <= GATE_PX]
    if len(pairs) < MIN_PAIRS:
        return None
    obj = L[[j for _, j in pairs]].astype(np.float64)
    img = centres[[i for i, _ in pairs]].astype(np.float64)
    K = camera.K_opencv
    rvec0 = cv2.Rodrigues(R0)[0]
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, rvec=rvec0.copy(), tvec=t0.reshape(3, 1).copy(),
                                             useExtrinsicGuess=True, reprojectionError=REPROJECTION_PX,
                                             iterationsCount=200, confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or inl is None or len(inl) < MIN_PAIRS:
        return None
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    return cv2.Rodrigues(rvec)[0], tvec.ravel()
