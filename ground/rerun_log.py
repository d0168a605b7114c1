"""The rerun log of a flight: one recording, in a ``world/`` ENU frame (z up).

Entity tree::

    world                       ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/camera                Transform3D (camera to world) + Pinhole, the current frame
    world/camera/image          the keyframe's JPEG (when the frame carried one)
    world/camera/image/detections   Boxes2D, the frame's detections
    world/camera/image/epipolar     LineStrips2D, epipolar lines of the previous frame's detections
    world/trajectory            LineStrips3D, the camera centres so far
    world/apples                Points3D coloured by row, labelled "id (row)"
    world/tracks/<id>           LineStrips3D from each observing camera to the apple (hidden in the blueprint)
    map/apples, map/drone       GeoPoints (WGS84) for the map view
    stats/rows/<r>              Scalars: apples per row
    stats/apples, stats/frames_per_s, stats/drops, stats/detector_latency_s, stats/ground_latency_s
    stats/rejected/<reason>     Scalars: messages the ground refused, by pomar.wire.WireError reason

Timelines: ``frame`` (sequence) and ``capture_time`` (timestamp). Sinks: an .rrd file, a gRPC server
for a viewer elsewhere (``serve``), or a running viewer (``connect``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ground.geometry import fundamental_from_projections
from ground.outputs import row_colours

log = logging.getLogger(__name__)

APPLICATION_ID = "pomar"


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="apple map", contents=["+ world/**", "- world/tracks/**"]),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", name="camera"),
                rrb.MapView(origin="map", name="map"),
                rrb.TimeSeriesView(origin="stats", name="counts and rates"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=False,
    )


class RerunLog:
    def __init__(self, flight_id: str, rrd: Path | None = None, serve: bool = False, connect: str | None = None,
                 apples_every: int = 5):
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=flight_id)
        self.sinks = []
        if rrd is not None:
            Path(rrd).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(rrd), default_blueprint=blueprint())
            self.sinks.append(str(rrd))
        if serve:
            uri = self.rec.serve_grpc(default_blueprint=blueprint())
            self.sinks.append(uri)
            log.info("rerun: serving on %s (open it with `rerun --connect %s`, or the web viewer)", uri, uri)
        if connect:
            self.rec.connect_grpc(connect, default_blueprint=blueprint())
            self.sinks.append(connect)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.apples_every = max(1, apples_every)
        self._centres: list[np.ndarray] = []
        self._prev: tuple[np.ndarray, np.ndarray] | None = None  # previous frame's (P, centres)
        self._frames = 0
        self._tracks_logged: set[int] = set()
        self.scale: float | None = None

    def _time(self, frame: int, t_capture: float):
        self.rec.set_time("frame", sequence=int(frame))
        if np.isfinite(t_capture):
            self.rec.set_time("capture_time", timestamp=float(t_capture))

    def frame(self, event, camera, stats: dict | None = None):
        """A frame through the association: camera, image, detections, epipolar lines, trajectory."""
        self._time(event.frame, event.t_capture)
        msg = event.msg
        if event.keyframe is not None and self.scale is None:
            import cv2

            img = cv2.imdecode(np.frombuffer(event.keyframe, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
            if img is not None:  # the reduced decode is 1/8 of the width, rounded up
                self.scale = min(1.0, img.shape[1] * 8 / camera.width)
        # The image plane is in keyframe pixels (keyframes are often smaller than the camera's frames).
        s = self.scale or 1.0
        S = np.diag([s, s, 1.0])
        boxes = np.asarray(msg.boxes, np.float32).reshape(-1, 4) * s
        if event.pose is not None:
            p = event.pose
            C = p.centre
            self.rec.log("world/camera", rr.Transform3D(translation=C, mat3x3=p.R.T),
                         rr.Pinhole(image_from_camera=S @ camera.K_opencv,
                                    resolution=[round(camera.width * s), round(camera.height * s)],
                                    camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=2.0))
            self._centres.append(C)
            if len(self._centres) % 5 == 1:
                self.rec.log("world/trajectory", rr.LineStrips3D([np.array(self._centres)], colors=[[200, 200, 200]]))
            P = camera.K_opencv @ np.hstack([p.R, p.t[:, None]])
            if self._prev is not None and len(self._prev[1]):
                F = fundamental_from_projections(self._prev[0], P)
                lines = [seg * s for seg in self._epipolar_segments(F, self._prev[1], camera.width, camera.height)]
                if len(lines):
                    self.rec.log("world/camera/image/epipolar", rr.LineStrips2D(lines, colors=[[255, 255, 0]], radii=0.5))
            self._prev = (P, msg.centres)
        if event.keyframe is not None:
            self.rec.log("world/camera/image", rr.EncodedImage(contents=event.keyframe, media_type="image/jpeg"))
        self.rec.log("world/camera/image/detections",
                     rr.Boxes2D(array=boxes, array_format=rr.Box2DFormat.XYXY, colors=[[255, 80, 80]]))
        if stats:
            for k, v in stats.items():
                if v is not None and np.isfinite(v):
                    self.rec.log(f"stats/{k}", rr.Scalars(float(v)))
        self._frames += 1

    @staticmethod
    def _epipolar_segments(F: np.ndarray, xy: np.ndarray, w: int, h: int) -> list[np.ndarray]:
        """Each point's epipolar line in the second image, clipped to the image's left and right edges."""
        x = np.column_stack([xy, np.ones(len(xy))])
        L = x @ F.T  # a u + b v + c = 0
        out = []
        for a, b, c in L:
            if abs(b) > 1e-9:
                out.append(np.array([[0.0, -c / b], [w - 1.0, -(c + a * (w - 1)) / b]]))
            elif abs(a) > 1e-9:
                out.append(np.array([[-c / a, 0.0], [-c / a, h - 1.0]]))
        return out

    def apples(self, frame: int, t_capture: float, table: dict, apples=None, rows: list[dict] | None = None,
               drone_latlon=None, force: bool = False):
        """The apple map (every ``apples_every`` frames, or when forced), per-row counts and the map view."""
        if not force and frame % self.apples_every:
            return
        self._time(frame, t_capture)
        n = len(table["id"])
        pos = np.stack([table["x"], table["y"], table["z"]], 1) if n else np.zeros((0, 3))
        col = row_colours(table["row"]) if n else np.zeros((0, 3), np.uint8)
        labels = [f"{i} (row {r})" for i, r in zip(table["id"], table["row"])]
        self.rec.log("world/apples", rr.Points3D(pos, colors=col, radii=0.04, labels=labels, show_labels=False))
        ok = np.isfinite(table["lat"]) & np.isfinite(table["lon"]) if n else np.zeros(0, bool)
        self.rec.log("map/apples", rr.GeoPoints(lat_lon=np.stack([table["lat"][ok], table["lon"][ok]], 1) if ok.any()
                                                else np.zeros((0, 2)), radii=rr.Radius.ui_points(4.0), colors=col[ok]))
        if drone_latlon is not None and np.isfinite(drone_latlon).all():
            self.rec.log("map/drone", rr.GeoPoints(lat_lon=[drone_latlon], radii=rr.Radius.ui_points(8.0),
                                                   colors=[[30, 30, 255]]))
        self.rec.log("stats/apples", rr.Scalars(float(n)))
        for r in rows or []:
            self.rec.log(f"stats/rows/{r['row']}", rr.Scalars(float(r["count"])))
        if apples is not None:
            self.tracks(apples, table)

    def tracks(self, apples: dict, table: dict, max_rays: int = 12):
        """Each new apple's rays from its observing cameras (world/tracks/<id>; hidden by default)."""
        enu = {int(i): np.array([x, y, z]) for i, x, y, z in zip(table["id"], table["x"], table["y"], table["z"])}
        for aid, a in apples.items():
            if aid in self._tracks_logged or a.views is None or aid not in enu:
                continue
            Ps, _ = a.views
            # the views are in the association frame; their centres go through the same map as the apple
            centres = [-np.linalg.inv(P[:, :3]) @ P[:, 3] for P in Ps[:max_rays]]
            shift = enu[aid] - a.X  # association frame -> ENU is close to a translation over one apple
            strips = [np.array([c + shift, enu[aid]]) for c in centres]
            self.rec.log(f"world/tracks/{aid}", rr.LineStrips3D(strips, colors=[[255, 255, 255]], radii=0.005), static=True)
            self._tracks_logged.add(aid)

    def close(self):
        self.rec.flush()
        self.rec.disconnect()


def rrd_entities(path) -> dict[str, int]:
    """Entity path -> number of rows logged, read back from an .rrd file (rerun's RrdReader)."""
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream():
        p = str(chunk.entity_path)
        counts[p] = counts.get(p, 0) + chunk.num_rows
    return counts
