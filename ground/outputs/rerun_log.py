"""The rerun log of a flight: one recording, in a ``world/`` ENU frame (z up), laid out for a glance.

Entity tree::

    summary                     TextDocument (markdown): apples so far, per row, the frame being mapped, the
                                ground's delay behind the drone, drops and registration health
    world                       ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/camera                Transform3D (camera to world) + Pinhole, the current frame
    world/camera/image          the frame's image (frames that carried one)
    world/camera/image/detections       Boxes2D, that image's detections (logged only with their image)
    world/camera/image/epipolar/all     LineStrips2D: the previous image's detections' epipolar lines (hidden)
    world/camera/image/epipolar/<id>    apple <id>'s box on each image it was seen in, and the epipolar line of
                                        its previous view, on that image only (hidden; show one to follow that
                                        apple, or the group to see the apples of the image shown)
    world/trajectory            LineStrips3D, the camera centres so far
    world/points/<k>            Points3D: sub-model k's sparse structure-from-motion points, coloured by
                                height above the ground (ground grey-brown, canopy green)
    world/apples                Points3D at each apple's estimated radius, coloured by row, labelled
    world/rows                  LineStrips3D: each row's line, in its row's colour
    world/row_labels            Points3D: "row N" in white at each row's end
    world/trees, map/trees      Points3D on the ground and GeoPoints: each tree, coloured by its coverage (the share of
                                its canopy the camera saw, pomar.coverage: dark purple none, yellow all)
    world/tracks/<id>           LineStrips3D from each observing camera to the apple (hidden)
    map/apples, map/drone, map/trajectory, map/rows     GeoPoints and GeoLineStrings (WGS84)
    stats/apples                Scalars: apples so far
    stats/rows/row_<N>          Scalars: apples in row N, named "row N" in the row's colour
    stats/rate/ground, stats/rate/drone             frames/s mapped by the ground (blue), and processed by the
                                                    drone as its status heartbeat measures them (orange)
    stats/delay/behind_drone_s  capture time of the newest frame received minus that of the frame being mapped
    stats/delay/ground_latency_s   wall clock minus the mapped frame's capture time (live flights only)
    stats/delay/detector_s      the onboard detector's time per frame
    stats/link/dropped_onboard, stats/link/missing_frames   frames lost on board and on the link
    stats/rejected/<reason>     Scalars: messages the ground refused, by pomar.wire.WireError reason

Rows are numbered 1..N, left to right looking along the row direction; the colour of row N is the same in the
3-D view, the map and the plots (:data:`ground.outputs.tables.PALETTE`, colour-blind safe).

Timelines: ``frame`` (sequence) and ``capture_time`` (timestamp). Sinks: an .rrd file, a gRPC server
for a viewer elsewhere (``serve``), or a running viewer (``connect``).
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pyarrow as pa

from ground.apples.geometry import fundamental_from_projections
from ground.outputs.rrd_file import finish_rrd
from ground.outputs.tables import row_colours

# Memory stays flat over long flights only if the allocators behind the rerun SDK give back what they free. rerun's
# Rust side allocates with mimalloc, which by default keeps freed pages a while (it reads this when its library
# loads); pyarrow, which carries every logged array, keeps its own mimalloc pool, and the system pool returns to
# malloc, which the node trims.
os.environ.setdefault("MIMALLOC_PURGE_DELAY", "0")
# rerun's own warnings as usual, but not the file sink's about the chunk index it leaves out: RerunLog adds it at close
os.environ.setdefault("RUST_LOG", "warn,re_log_encoding::rrd::file_sink=error")
pa.set_memory_pool(pa.system_memory_pool())

import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402

log = logging.getLogger(__name__)

APPLICATION_ID = "pomar"
#: The panels of the default layout, by name (the tests and the README screenshot refer to them).
PANELS = ("summary", "camera", "apple map", "map", "apples per row", "ground rate (frames/s)",
          "delay behind the drone (s)")
HIDDEN = ("world/camera/image/epipolar",)
#: Every plot's data spans the flight from its first frame to the one shown; each row's series starts with a 0 at
#: the first frame (RerunLog._rows), so that the plots' time axes line up.
FROM_FIRST_FRAME = rrb.VisibleTimeRange("frame", start=rrb.TimeRangeBoundary.absolute(seq=0),
                                        end=rrb.TimeRangeBoundary.cursor_relative(seq=0))
APPLE_UI_POINTS = 4.0  # apples' radius on screen; the structure-from-motion cloud's is a quarter of it


def blueprint(ground_z: float | None = None, eye: tuple | None = None, map_zoom: float = 19.0) -> rrb.Blueprint:
    """The layout: summary and camera | 3-D apple map | map and plots. With ``ground_z`` the 3-D grid lies on
    the ground; with ``eye`` ((position, target)) the 3-D view starts there. The time panel follows the newest
    data, as a live flight needs."""
    grid = (rrb.LineGrid3D(visible=True, spacing=1.0, plane=rr.components.Plane3D((0.0, 0.0, 1.0), ground_z),
                           color=[150, 150, 150, 90]) if ground_z is not None else rrb.LineGrid3D(visible=False))
    eye_controls = (rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=eye[0], look_target=eye[1],
                                      eye_up=(0.0, 0.0, 1.0)) if eye is not None else None)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TextDocumentView(origin="summary", name="summary"),
                rrb.Spatial2DView(origin="world/camera/image", name="camera",
                                  overrides={p: rrb.EntityBehavior(visible=False) for p in HIDDEN}),
                row_shares=[3, 2],
            ),
            rrb.Spatial3DView(origin="world", name="apple map", contents=["+ world/**", "- world/tracks/**"],
                              background=[24, 26, 32], line_grid=grid, eye_controls=eye_controls,
                              overrides={p: rrb.EntityBehavior(visible=False) for p in HIDDEN}),
            rrb.Vertical(
                rrb.MapView(origin="map", name="map", zoom=map_zoom),
                *(rrb.TimeSeriesView(origin=origin, name=name, time_ranges=FROM_FIRST_FRAME,
                                     plot_legend=rrb.PlotLegend(corner=corner))
                  for origin, name, corner in (("stats/rows", "apples per row", rrb.Corner2D.LeftTop),
                                               ("stats/rate", "ground rate (frames/s)", rrb.Corner2D.LeftBottom),
                                               ("stats/delay", "delay behind the drone (s)", rrb.Corner2D.LeftTop))),
                row_shares=[4, 3, 2, 2],
            ),
            column_shares=[3, 5, 3],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", play_state="following"),
    )


def clip_segment(p: np.ndarray, q: np.ndarray, w: float, h: float) -> np.ndarray | None:
    """The part of segment p-q inside the image [0, w] x [0, h] (Liang-Barsky), or None."""
    d = q - p
    t0, t1 = 0.0, 1.0
    for num, den in ((p[0], -d[0]), (w - p[0], d[0]), (p[1], -d[1]), (h - p[1], d[1])):
        if abs(den) < 1e-12:
            if num < 0:
                return None
            continue
        t = num / den
        if den < 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return None
    return np.array([p + t0 * d, p + t1 * d])


def epipolar_segments(F: np.ndarray, xy: np.ndarray, w: float, h: float) -> list[np.ndarray]:
    """Each point's epipolar line in the second image (l = F x), clipped to the image on all four sides; lines that
    miss the image are left out."""
    x = np.column_stack([np.asarray(xy, float).reshape(-1, 2), np.ones(len(xy))])
    out = []
    for a, b, c in x @ F.T:  # a u + b v + c = 0
        n = np.hypot(a, b)
        if n < 1e-12:
            continue
        # the line's foot from the image centre, then far along it both ways; the clip keeps what is inside
        centre = np.array([w / 2, h / 2])
        foot = centre - (a * centre[0] + b * centre[1] + c) / n ** 2 * np.array([a, b])
        along = np.array([-b, a]) / n * (w + h)
        seg = clip_segment(foot - along, foot + along, w, h)
        if seg is not None:
            out.append(seg)
    return out


def height_colours(z: np.ndarray, ground_z: float) -> np.ndarray:
    """Sparse points by height above the ground: grey-brown at ground level, greener and lighter up the canopy."""
    h = np.clip((np.asarray(z) - ground_z - 0.3) / 3.0, 0.0, 1.0)[:, None]
    ground, low, high = np.array([120, 105, 85]), np.array([40, 120, 50]), np.array([150, 210, 110])
    canopy = low + h * (high - low)
    return np.where(h > 0, canopy, ground).astype(np.uint8)


#: Viridis at five stops (perceptually even, colour-blind safe): a tree's coverage 0, 0.25, ..., 1.
VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)


def coverage_colours(coverage: np.ndarray) -> np.ndarray:
    """RGB (uint8) of coverages in [0, 1] on VIRIDIS; grey where not known."""
    c = np.asarray(coverage, float)
    x = np.clip(np.nan_to_num(c, nan=0.0), 0, 1) * (len(VIRIDIS) - 1)
    out = np.stack([np.interp(x, np.arange(len(VIRIDIS)), VIRIDIS[:, k]) for k in range(3)], 1)
    out[~np.isfinite(c)] = 160
    return out.astype(np.uint8)


def ground_level(points: dict[int, np.ndarray], apples_z: np.ndarray) -> float | None:
    """The ground's height: the 5th percentile of the sparse points (most of them lie on the ground between
    rows), or 1.5 m below the lowest apples when there are too few points."""
    pts = [p[:, 2] for p in points.values() if len(p)]
    z = np.concatenate(pts) if pts else np.zeros(0)
    if len(z) >= 200:
        return float(np.percentile(z, 5))
    if len(apples_z) >= 10:
        return float(np.percentile(apples_z, 2) - 1.5)
    return None


class RerunLog:
    def __init__(self, flight_id: str, rrd: Path | None = None, serve: bool = False, connect: str | None = None,
                 apples_every: int = 5):
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=flight_id)
        self.sinks = []
        self.rrd = Path(rrd) if rrd is not None else None
        if self.rrd is not None:
            self.rrd.parent.mkdir(parents=True, exist_ok=True)
            # No chunk index (footer) while the flight goes on: the file sink would hold one entry per chunk in
            # memory until the end, so the ground's memory would grow with the flight. close() adds it.
            self.rec.save(str(self.rrd), default_blueprint=blueprint(), write_footer=False)
            self.sinks.append(str(self.rrd))
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
        # recent frames: frame -> (capture time, P (ENU, image pixels) or None, whether its image was logged)
        self._frames: OrderedDict[int, tuple[float, np.ndarray | None, bool]] = OrderedDict()
        self._prev_image: tuple[np.ndarray, np.ndarray] | None = None  # last image frame's (P, centres)
        self._tracks_logged: set[int] = set()
        self._series: set[int] = set()
        self._framed = False  # whether the blueprint with the ground grid and the eye was sent
        self._view_data = None  # what the last framing would use: apples (ENU), rows, latitude
        self.ground_z: float | None = None
        self.scale: float | None = None
        self.camera = None
        self.fps: float | None = None  # the video's, for the capture time of a frame not seen yet
        self._first: int | None = None  # the first frame logged
        # the rate series told apart by colour (Okabe & Ito: the ground blue, the drone orange)
        for name, colour in (("ground", [0, 114, 178]), ("drone", [230, 159, 0])):
            self.rec.log(f"stats/rate/{name}", rr.SeriesLines(names=f"{name} (frames/s)", colors=[colour], widths=2.0),
                         static=True)

    def _time(self, frame: int, t_capture: float):
        if self._first is None:
            self._first = int(frame)
        self.rec.set_time("frame", sequence=int(frame))
        if np.isfinite(t_capture):
            self.rec.set_time("capture_time", timestamp=float(t_capture))

    def frame(self, event, camera, stats: dict | None = None, to_enu=None):
        """A frame through the association: camera pose, and, on frames with an image, the image, its detections
        and the epipolar lines of the previous image's detections. ``stats``: entity path under ``stats/`` ->
        value; ``to_enu``: the map frame -> ENU similarity (None: they are the same)."""
        self._time(event.frame, event.t_capture)
        self.camera = camera
        msg = event.msg
        if event.keyframe is not None and self.scale is None:
            import cv2

            img = cv2.imdecode(np.frombuffer(event.keyframe, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
            if img is not None:  # the reduced decode is 1/8 of the width, rounded up
                self.scale = min(1.0, img.shape[1] * 8 / camera.width)
        # The image plane is in image pixels (images are often smaller than the camera's frames).
        s = self.scale or 1.0
        S = np.diag([s, s, 1.0])
        P = None
        if event.pose is not None:
            R, C = event.pose.R, event.pose.centre
            if to_enu is not None:
                R, C = R @ to_enu.R.T, to_enu.apply(C[None])[0]
            self.rec.log("world/camera", rr.Transform3D(translation=C, mat3x3=R.T),
                         rr.Pinhole(image_from_camera=S @ camera.K_opencv,
                                    resolution=[round(camera.width * s), round(camera.height * s)],
                                    camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=2.0))
            self._centres.append(C)
            if len(self._centres) % 5 == 1:
                self.rec.log("world/trajectory", rr.LineStrips3D([np.array(self._centres)], colors=[[220, 220, 220]]))
            P = S @ camera.K_opencv @ np.hstack([R, (-R @ C)[:, None]])
        has_image = event.keyframe is not None
        if has_image:
            # boxes only with the image they were detected in: drawn over another frame's image they would jump
            w, h = camera.width * s, camera.height * s
            self.rec.log("world/camera/image", rr.EncodedImage(contents=event.keyframe, media_type="image/jpeg"))
            boxes = np.asarray(msg.boxes, np.float32).reshape(-1, 4) * s
            self.rec.log("world/camera/image/detections",
                         rr.Boxes2D(array=boxes, array_format=rr.Box2DFormat.XYXY, colors=[[255, 60, 60]]))
            lines = []
            if P is not None and self._prev_image is not None and len(self._prev_image[1]):
                F = fundamental_from_projections(self._prev_image[0], P)
                lines = epipolar_segments(F, self._prev_image[1], w, h)
            self.rec.log("world/camera/image/epipolar/all",
                         rr.LineStrips2D(lines, colors=[[255, 220, 0]], radii=rr.Radius.ui_points(0.75)))
            if P is not None:
                self._prev_image = (P, np.asarray(msg.centres, float).reshape(-1, 2) * s)
        self._frames[event.frame] = (event.t_capture, P, has_image)
        while len(self._frames) > 600:
            self._frames.popitem(last=False)
        for k, v in (stats or {}).items():
            if v is not None and np.isfinite(v):
                self.rec.log(f"stats/{k}", rr.Scalars(float(v)))

    def apple_views(self, apple_id: int, boxes: list[tuple[int, np.ndarray]]):
        """Apple ``apple_id``'s box on each image it was seen in (``boxes``: (frame, xyxy in camera pixels)), with
        the epipolar line of its previous view, under world/camera/image/epipolar/<id> (hidden by default)."""
        if self.camera is None:
            return
        s = self.scale or 1.0
        w, h = self.camera.width * s, self.camera.height * s
        path = f"world/camera/image/epipolar/{apple_id}"
        prev = None
        frames, times, centres, halves, strips, n_strips = [], [], [], [], [], []
        seen = {f for f, _ in boxes}
        for f, box in boxes:
            t, P, has_image = self._frames.get(f, (float("nan"), None, False))
            b = np.asarray(box, float) * s
            centre = (b[:2] + b[2:]) / 2
            if has_image:
                lines = []
                if prev is not None and P is not None:
                    lines = epipolar_segments(fundamental_from_projections(prev[0], P), prev[1][None], w, h)
                frames.append(f)
                times.append(t)
                centres.append([centre])
                halves.append([(b[2:] - b[:2]) / 2])
                strips.extend(lines)
                n_strips.append(len(lines))
                if f + 1 not in seen:  # the box and line belong to this image only: the next frame clears them
                    nxt = self._frames.get(f + 1, (t + (1.0 / self.fps if self.fps else np.nan),))[0]
                    frames.append(f + 1)
                    times.append(nxt)
                    centres.append([])
                    halves.append([])
                    n_strips.append(0)
            if P is not None:
                prev = (P, centre)
        if not frames:
            return
        # one batch of rows for all of the apple's views: a log call per view is slow, and rerun keeps more per entity
        indexes = [rr.TimeColumn("frame", sequence=frames)]
        if np.isfinite(times).all():
            indexes.append(rr.TimeColumn("capture_time", timestamp=times))
        n_boxes = [len(c) for c in centres]
        nb = sum(n_boxes)
        flat_c = [c for cs in centres for c in cs]
        flat_h = [h for hs in halves for h in hs]
        columns = [*rr.Boxes2D.columns(centers=np.array(flat_c, float).reshape(-1, 2),
                                       half_sizes=np.array(flat_h, float).reshape(-1, 2),
                                       colors=[[255, 255, 255]] * nb, labels=[f"apple {apple_id}"] * nb
                                       ).partition(n_boxes),
                   *rr.LineStrips2D.columns(strips=strips, colors=[[255, 220, 0]] * len(strips),
                                            radii=[rr.Radius.ui_points(1.0)] * len(strips)).partition(n_strips)]
        rr.send_columns(path, indexes=indexes, columns=columns, recording=self.rec)

    def apples(self, frame: int, t_capture: float, table: dict, apples=None, rows: list[dict] | None = None,
               drone_latlon=None, force: bool = False, points: dict[int, np.ndarray] | None = None,
               summary: str | None = None, trajectory_latlon=None, trees: list[dict] | None = None):
        """The apple map (every ``apples_every`` frames, or when forced): apples, rows, sparse points, per-row
        counts, the map view and the summary."""
        if not force and frame % self.apples_every:
            return
        self._time(frame, t_capture)
        n = len(table["id"])
        pos = np.stack([table["x"], table["y"], table["z"]], 1) if n else np.zeros((0, 3))
        col = row_colours(table["row"]) if n else np.zeros((0, 3), np.uint8)
        labels = [f"apple {i}, row {r}" for i, r in zip(table["id"], table["row"])]
        # a fixed size on screen: at the eye's 10-20 m an apple's own radius is a pixel or two among the cloud
        self.rec.log("world/apples", rr.Points3D(pos, colors=col, radii=rr.Radius.ui_points(APPLE_UI_POINTS),
                                                 labels=labels, show_labels=False))
        ok = np.isfinite(table["lat"]) & np.isfinite(table["lon"]) if n else np.zeros(0, bool)
        self.rec.log("map/apples", rr.GeoPoints(lat_lon=np.stack([table["lat"][ok], table["lon"][ok]], 1) if ok.any()
                                                else np.zeros((0, 2)), radii=rr.Radius.ui_points(5.0), colors=col[ok]))
        if drone_latlon is not None and np.isfinite(drone_latlon).all():
            # black (the one Okabe & Ito colour no row takes), larger than an apple: seen on a blank map (no tiles
            # offline) as on an aerial photo
            self.rec.log("map/drone", rr.GeoPoints(lat_lon=[drone_latlon], radii=rr.Radius.ui_points(10.0),
                                                   colors=[[0, 0, 0]]))
        if trajectory_latlon is not None and len(trajectory_latlon) > 1:
            self.rec.log("map/trajectory", rr.GeoLineStrings(lat_lon=[trajectory_latlon], colors=[[200, 200, 200]],
                                                             radii=rr.Radius.ui_points(1.5)))
        self._rows(rows or [])
        self.rec.log("stats/apples", rr.Scalars(float(n)))
        if self.ground_z is None:
            self.ground_z = ground_level(points or {}, np.asarray(table["z"]) if n else np.zeros(0))
        self._trees(trees or [])
        for k, p in (points or {}).items():
            if self.ground_z is not None:
                self.rec.log(f"world/points/{k}", rr.Points3D(p, colors=height_colours(p[:, 2], self.ground_z),
                                                              radii=rr.Radius.ui_points(APPLE_UI_POINTS / 4)))
        if self.ground_z is not None and n >= 10:
            self._view_data = (pos, rows or [], float(np.nanmedian(table["lat"])))
            if not self._framed:
                self._frame_view()
        if summary is not None:
            self.rec.log("summary", rr.TextDocument(summary, media_type=rr.MediaType.MARKDOWN))
        if apples is not None:
            self.tracks(apples, table)

    def _rows(self, rows: list[dict]):
        """Row lines in 3-D and on the map, and the per-row counts (each series named and coloured as its row)."""
        if not rows:
            return
        col = row_colours([r["row"] for r in rows])
        self.rec.log("world/rows", rr.LineStrips3D([[[r["start_x"], r["start_y"], r["z"]], [r["end_x"], r["end_y"], r["z"]]]
                                                    for r in rows], colors=col, radii=rr.Radius.ui_points(2.0),
                                                   labels=[f"row {r['row']}" for r in rows], show_labels=False))
        # the labels apart, white at each row's end: rerun draws a label in its entity's colour on grey, which the
        # darker row colours make hard to read
        self.rec.log("world/row_labels", rr.Points3D([[r["end_x"], r["end_y"], r["z"]] for r in rows],
                                                     colors=[[255, 255, 255]] * len(rows), radii=rr.Radius.ui_points(3.0),
                                                     labels=[f"row {r['row']}" for r in rows], show_labels=True))
        geo = [r for r in rows if np.isfinite([r["start_lat"], r["start_lon"], r["end_lat"], r["end_lon"]]).all()]
        if geo:
            self.rec.log("map/rows", rr.GeoLineStrings(lat_lon=[[[r["start_lat"], r["start_lon"]],
                                                                 [r["end_lat"], r["end_lon"]]] for r in geo],
                                                       colors=row_colours([r["row"] for r in geo]),
                                                       radii=rr.Radius.ui_points(2.0)))
        for r, c in zip(rows, col):
            path = f"stats/rows/row_{r['row']}"
            if r["row"] not in self._series:
                self.rec.log(path, rr.SeriesLines(names=f"row {r['row']}", colors=[c], widths=2.0), static=True)
                self._series.add(r["row"])
                # a row's series starts at the flight's first frame, at 0, as the other plots do: their time axes
                # then line up (a plot fits its axis to its own data)
                if self._first is not None:
                    self.rec.send_columns(path, indexes=[rr.TimeColumn("frame", sequence=[self._first])],
                                          columns=rr.Scalars.columns(scalars=[0.0]))
            self.rec.log(path, rr.Scalars(float(r["count"])))

    def _trees(self, trees: list[dict]):
        """Each tree where it stands, coloured by its coverage (grey where not known yet), labelled."""
        cov = np.array([t.get("coverage", np.nan) for t in trees], float)
        if not len(trees) or not np.isfinite(cov).any():
            return
        col = coverage_colours(cov)
        z = self.ground_z if self.ground_z is not None else 0.0
        labels = [f"row {t['row']} tree {t['tree']}: coverage {c:.2f}" for t, c in zip(trees, cov)]
        self.rec.log("world/trees", rr.Points3D([[t["x"], t["y"], z] for t in trees], colors=col, labels=labels,
                                                radii=rr.Radius.ui_points(4.0), show_labels=False))
        ok = np.array([np.isfinite([t["lat"], t["lon"]]).all() for t in trees])
        if ok.any():
            self.rec.log("map/trees", rr.GeoPoints(lat_lon=[[t["lat"], t["lon"]] for t, k in zip(trees, ok) if k],
                                                   colors=col[ok], radii=rr.Radius.ui_points(4.0)))

    def _frame_view(self):
        """Send the layout again, now with the grid on the ground, the eye above the rows looking across them from
        the drone's side, and the map zoomed to the apples (once there are some, and at the end of the flight)."""
        pos, rows, lat = self._view_data
        longest = max(rows, key=lambda r: r["length_m"]) if rows else None
        u = (np.array([longest["end_x"] - longest["start_x"], longest["end_y"] - longest["start_y"]])
             if longest is not None and longest["length_m"] > 0.5 else np.array([1.0, 0.0]))
        u = u / np.linalg.norm(u)
        normal = np.array([-u[1], u[0]])
        target = np.array([*np.median(pos[:, :2], 0), self.ground_z + 1.5])
        if self._centres and (np.mean(self._centres, 0)[:2] - target[:2]) @ normal < 0:
            normal = -normal
        span = max(float(np.ptp(pos[:, :2] @ u)), float(np.ptp(pos[:, :2] @ normal)), 5.0)
        dist = max(10.0, 0.8 * span)
        eye = target + np.array([*(normal * dist * np.cos(np.radians(35))), dist * np.sin(np.radians(35))])
        # web-map zoom z shows 156543 cos(lat) / 2^z metres per pixel: the apples' span over about 180 pixels
        zoom = np.log2(156543.03 * np.cos(np.radians(lat)) * 180 / span) if np.isfinite(lat) else 19.0
        self.rec.send_blueprint(blueprint(self.ground_z, (tuple(eye), tuple(target)), float(np.clip(zoom, 14, 22))))
        self._framed = True

    def tracks(self, apples: dict, table: dict, max_rays: int = 12):
        """Each new apple's rays from its observing cameras (world/tracks/<id>; hidden by default)."""
        enu = {int(i): np.array([x, y, z]) for i, x, y, z in zip(table["id"], table["x"], table["y"], table["z"])}
        for aid, a in apples.items():
            if aid in self._tracks_logged or a.views is None or aid not in enu:
                continue
            Ps, _ = a.views
            # the views are in the map frame; their centres go through the same map as the apple
            centres = [-np.linalg.inv(P[:, :3]) @ P[:, 3] for P in Ps[:max_rays]]
            shift = enu[aid] - a.X  # map frame -> ENU is close to a translation over one apple
            strips = [np.array([c + shift, enu[aid]]) for c in centres]
            # static, and sent as columns: rerun keeps less per entity that way (one entity per apple)
            n = len(strips)
            rr.send_columns(f"world/tracks/{aid}", indexes=[], recording=self.rec,
                            columns=rr.LineStrips3D.columns(strips=strips, colors=[[255, 255, 255]] * n,
                                                            radii=[0.005] * n).partition([n]))
            self._tracks_logged.add(aid)

    def close(self, compact: bool = True):
        """Flush and close the recording; ``compact``: give the .rrd its chunk index (seconds; a ground told to stop
        leaves it as written, a valid recording without an index)."""
        if self._view_data is not None:  # framed again on the whole map
            self._frame_view()
        self.rec.flush()
        self.rec.disconnect()
        if self.rrd is not None and compact:
            finish_rrd(self.rrd)
