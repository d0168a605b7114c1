"""The map frame: the frame every pose and apple of the ground is expressed in while the flight goes on, the model's
coordinates taken through the first good georeferencing fit, then frozen (ENU itself while there is no model). The
association triangulates in it, the tables and rerun take it to ENU (:meth:`MapFrame.map_to_enu`), with the map's bend
and drift from the GPS taken back out (:meth:`MapFrame.correction`)."""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ground.poses.georeference import Pose, drift_offsets, georeference_poses, line_noise
from pomar.align import IDENTITY, Similarity, compose, inverse
from pomar.rotations import camera_rotations

log = logging.getLogger(__name__)


class MapFrame:
    """The frame the association works in: the model's coordinates taken through the first good georeferencing fit,
    then frozen (the frames in the association's window stay consistent while later fits move a little); ENU itself
    while there is no model. Reads the mapper's fit and registered keyframes (``model_pose``), and the frames'
    telemetry (frame -> KeyframeTelemetry) for the drift correction."""

    #: The drift correction applies once the map has drifted this many times the GPS's stated accuracy (the spread
    #: of the corrections along the flight): below, what it would follow is mostly the GPS error's own wander.
    DRIFT_MIN_GPS_SIGMAS = 4.0

    def __init__(self, mapper, telemetry: dict, camera=None, sigma_att_deg: float = 0.5):
        self.mapper = mapper
        self.tel = telemetry
        self.camera = camera  # its mount turns the gimbal's attitudes into the camera's (the bend correction)
        self.sigma_att = np.radians(sigma_att_deg)
        self.bend_deg = 0.0  # how far the map turns from the attitudes along the flight (deg), see bend
        self.bend_corrected = False
        self.frozen: Similarity | None = None  # model -> map frame (a fit frozen), or None
        self.assoc_from_enu: Similarity | None = None  # set when the map frame is ENU itself
        self.drift_m = 0.0  # how far the drift corrections spread along the flight (m), see correction
        self.drift_corrected = False
        self._key: tuple | None = None  # what the similarities below were composed from
        self._cached: tuple[Similarity | None, Similarity] = (None, IDENTITY)

    @property
    def fixed(self) -> bool:
        """Whether the map frame has been fixed (by a fit, or as ENU)."""
        return self.frozen is not None or self.assoc_from_enu is not None

    def fix(self) -> None:
        """Fix the map frame, once: the mapper's fit if there is one, else ENU."""
        if self.fixed:
            return
        fit = self.mapper.fit
        if fit is not None:
            self.frozen = fit
            log.info("map frame fixed by georeferencing %d registered keyframes (GPS residual %.2f m)",
                     len(self.mapper.model_pose), self.mapper.fit_residual_m)
        else:
            self.assoc_from_enu = IDENTITY
            log.warning("no registered model yet: the association runs on telemetry poses in ENU")

    def _similarities(self) -> tuple[Similarity | None, Similarity]:
        """(model -> map frame, None before a fit; map frame -> ENU), composed again only when the
        mapper's fit or the frame changed: every frame's pose and every table row reads them."""
        key = (self.mapper.fit, self.frozen, self.assoc_from_enu)
        if self._key is None or any(a is not b for a, b in zip(key, self._key)):
            fit, frozen, from_enu = key
            if frozen is not None:
                m2a, a2e = frozen, compose(fit, inverse(frozen))
            else:
                m2a = compose(from_enu, fit) if fit is not None and from_enu is not None else None
                a2e = inverse(from_enu) if from_enu is not None else IDENTITY
            self._key, self._cached = key, (m2a, a2e)
        return self._cached

    def model_to_map(self) -> Similarity | None:
        return self._similarities()[0]

    def map_to_enu(self) -> Similarity:
        return self._similarities()[1]

    def metres_per_unit(self) -> float:
        """The map frame's unit in metres, as the map's georeference knows it now: the frame was fixed by
        the first fit, from a few keyframes' GPS, and the later fits scale it (tens of percent with a DJI log's)."""
        return float(self.map_to_enu().scale)

    def to_enu(self, X: np.ndarray) -> np.ndarray:
        return self.map_to_enu().apply(np.asarray(X, float).reshape(-1, 3))

    def frame_pose(self, frame: int, own, between, tel, camera, sigma_att_deg: float) -> Pose | None:
        """The frame's pose in the map frame from the best source it has: its own model pose (R, t, source:
        registered or tracked), else one interpolated between the model poses of its nearest posed frames (``between``:
        a, (R, t) at a, b, (R, t) at b; rotation by slerp, centre linearly; carried on past them where the frame lies
        outside a..b: ``extrapolated``), else its telemetry (``tel``, a
        KeyframeTelemetry: GPS and gimbal, through ``camera``'s mount). The model's poses count once the model is
        georeferenced; the map frame is fixed at the first frame posed. None without a model pose or position
        telemetry."""
        self.fix()
        m2a, a2e = self._similarities()
        if m2a is not None and own is not None:
            R, t = georeference_poses(own[0][None], own[1][None], m2a)
            return Pose(frame, R[0], t[0], own[2], 0.01 if own[2] == "registered" else 0.015, 0.05)
        if m2a is not None and between is not None:
            a, pa, b, pb = between
            R2, t2 = georeference_poses(np.array([pa[0], pb[0]]), np.array([pa[1], pb[1]]), m2a)
            C = -np.einsum("nji,nj->ni", R2, t2)
            w = (frame - a) / (b - a)
            if 0.0 <= w <= 1.0:
                R = Slerp([0.0, 1.0], Rotation.from_matrix(R2))([w]).as_matrix()[0]
                c = (1 - w) * C[0] + w * C[1]
                return Pose(frame, R, -R @ c, "interpolated", 0.02, 0.1)
            # past a..b: carried on at their motion (turn and velocity), as uncertain as the step is long
            R = R2[0] @ Rotation.from_rotvec(w * Rotation.from_matrix(R2[0].T @ R2[1]).as_rotvec()).as_matrix()
            c = (1 - w) * C[0] + w * C[1]
            far = max(abs(w), abs(w - 1.0))
            return Pose(frame, R, -R @ c, "extrapolated", 0.02 * far, 0.1 * far)
        log.debug("frame %d: telemetry pose (model georeferenced: %s)", frame, m2a is not None)
        if tel is None or not np.isfinite(tel.enu).all():
            return None
        R_enu, t_enu = tel.camera_pose(camera)
        R, t = georeference_poses(R_enu[None], t_enu[None], inverse(a2e))
        return Pose(frame, R[0], t[0], "telemetry", tel.h_acc, sigma_att_deg)

    def correction(self, frames, sigma_frames: float) -> tuple[np.ndarray, np.ndarray]:
        """(ENU offsets (n, 3), ENU rotations (n, 3, 3)) at these frames, to apply to what :meth:`to_enu` gives: a
        camera's centre moves by the offset and its axes turn by the rotation; a point seen from it moves with it
        (turned about its centre). The map's turn taken back out (:meth:`_bend`), then its drift from the GPS
        (:meth:`_drift`)."""
        q = np.asarray(frames, float).reshape(-1)
        off, rot = np.zeros((len(q), 3)), np.broadcast_to(np.eye(3), (len(q), 3, 3)).copy()
        self.bend_corrected = self.drift_corrected = False
        S = self.mapper.fit
        if S is None or self.frozen is None or not sigma_frames > 0:
            return off, rot
        model_pose = self.mapper.model_pose
        kf = np.array(sorted(f for f in model_pose if f in self.tel), int)
        if len(kf) < 3:
            return off, rot
        R = np.array([model_pose[f][0] for f in kf]) @ S.R.T  # ENU-to-camera, as the map has them
        C = S.apply(-np.einsum("nji,nj->ni", np.array([model_pose[f][0] for f in kf]),
                               np.array([model_pose[f][1] for f in kf])))
        bent = self._bend(kf, R, C, q, sigma_frames)
        if bent is not None:
            (off_kf, _), (off, rot) = bent
            C = C + off_kf
        return off + self._drift(kf, C, q, sigma_frames), rot

    def _bend(self, kf, R, C, q, sigma_frames):
        """((offsets, rotations) at the keyframes, (offsets, rotations) at ``q``), or None where it does not apply.

        Incremental reconstruction along a long pass turns slowly (about 0.4 degrees at each end of a 184-m pass),
        and the map bends with it (0.25 m at the ends). The gimbal's tilt does not drift (gravity holds it): its
        disagreement with the map's cameras, fitted by a line around each frame (Gaussian, ``sigma_frames``), is the
        map's tilt there, known to the attitudes' accuracy over the keyframes the fit takes in. The turn about the
        vertical is left: a compass's heading wanders. Each stretch of the map is turned back by the share of that
        turn which stands out of its noise (a Wiener gain, 1 - noise²/turn², none where the turn is within its noise),
        and the path is laid again from the turned steps between keyframes; on keyframes whose heading the log knows.
        ``bend_deg``: the fitted turn's largest departure from its mean along the flight."""
        if self.camera is None:
            return None
        ok = np.array([np.isfinite(self.tel[f].q_gimbal).all() and self.tel[f].heading_known for f in kf])
        if ok.sum() < 10:
            return None
        kf_a, R_a = kf[ok], R[ok]
        R_tel = camera_rotations(np.array([self.tel[f].q_gimbal for f in kf_a]), self.camera)
        # the map's turn in ENU: G with R G^T = R_tel, as a rotation vector (a fraction of a degree). Its tilt only:
        # a gimbal's tilt is held to gravity, its heading to a compass that may wander as much as the map
        turn = Rotation.from_matrix(np.einsum("nji,njk->nik", R_tel, R_a)).as_rotvec() * [1.0, 1.0, 0.0]
        # the line, and its noise, on a grid an eighth of sigma apart (it bends on the scale of sigma), read between
        # its points: every map refresh computes it, and a 10-minute flight has thousands of keyframes
        grid = np.arange(kf_a[0], kf_a[-1] + sigma_frames / 8, max(sigma_frames / 8, 1.0))
        line = drift_offsets(kf_a, turn, np.ones(len(kf_a)), grid, sigma_frames)

        def at(frames):
            return np.column_stack([np.interp(frames, grid, line[:, i]) for i in range(3)])
        at_a = at(kf_a)
        mean = at_a.mean(0)  # a turn the whole flight shares is the mount's, or the similarity's: not the map's shape
        dev = np.linalg.norm(at_a - mean, axis=1)
        self.bend_deg = float(np.degrees(dev.max()))
        # each keyframe's fitted turn against its own noise (the attitudes' accuracy through the line's weights)
        noise = self.sigma_att * np.interp(kf_a, grid, line_noise(kf_a, grid, sigma_frames))
        # each stretch is turned back by the share of its fitted turn that stands out of the noise (a Wiener gain:
        # the turn's power over the turn's and the noise's), not all or nothing
        gain_a = np.clip(1.0 - (noise / np.maximum(dev, 1e-12)) ** 2, 0.0, 1.0)
        if not (gain_a > 0).any():
            return None
        self.bend_corrected = True

        def turn_at(frames):
            return (at(frames) - mean) * np.interp(frames, kf_a, gain_a)[:, None]
        G = Rotation.from_rotvec(turn_at(kf)).as_matrix()
        # the path laid again from its turned steps (each turned by its ends' mean turn), then put back where it was
        # on average: the similarity's placement stays
        steps = np.einsum("nij,nj->ni", 0.5 * (G[1:] + G[:-1]), np.diff(C, axis=0))
        off_kf = np.vstack([C[:1], C[0] + np.cumsum(steps, axis=0)]) - C
        off_kf -= off_kf.mean(0)
        off = np.column_stack([np.interp(q, kf, off_kf[:, i]) for i in range(3)])
        rot = Rotation.from_rotvec(turn_at(q)).as_matrix()
        return (off_kf, G), (off, rot)

    def _drift(self, kf, C, q, sigma_frames) -> np.ndarray:
        """ENU offsets (n, 3) at frames ``q``: where the GPS of the registered keyframes around them (Gaussian,
        ``sigma_frames``) disagrees with the map's camera centres ``C`` at keyframes ``kf`` (:func:`drift_offsets`).
        Zero while the corrections spread less than DRIFT_MIN_GPS_SIGMAS x the GPS accuracy along the flight
        (``drift_m``)."""
        ok = np.array([np.isfinite(self.tel[f].enu).all() for f in kf])
        if ok.sum() < 3:
            return np.zeros((len(q), 3))
        kf, C = kf[ok], C[ok]
        res = np.array([self.tel[f].enu for f in kf]) - C
        sigma = np.array([self.tel[f].h_acc for f in kf])
        w = 1.0 / sigma**2
        at_kf = drift_offsets(kf, res, w, kf, sigma_frames)
        self.drift_m = float(np.linalg.norm(at_kf - np.average(at_kf, axis=0, weights=w), axis=1).max())
        self.drift_corrected = self.drift_m >= self.DRIFT_MIN_GPS_SIGMAS * float(np.median(sigma))
        return drift_offsets(kf, res, w, q, sigma_frames) if self.drift_corrected else np.zeros((len(q), 3))
