"""Software renderer for simulated orchard frames: a ray-cast textured ground plus z-buffered splats.

Leaves, trunks and apples are spheres drawn as screen-space discs (apples shaded as spheres, with a
per-pixel depth), resolved by one z-buffer whose keys pack the quantised depth and the primitive
index, so the same buffer tells which apple covers which pixel: that gives each apple's visible
fraction exactly as rendered.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pomar.camera import Camera
from sim.orchard import APPLE, LEAF, Scene

_ID_BITS = 24
_ID_MASK = (1 << _ID_BITS) - 1
_DEPTH_SCALE = 2000.0  # depth quantum 0.5 mm
_MAX_RADIUS_PX = 24
_CHUNK = 60_000


@dataclass
class FrameTruth:
    """Apples seen in a rendered frame."""

    apple_index: np.ndarray  # rows of scene.apples
    uv: np.ndarray  # (n, 2) projected centre, OpenCV pixel convention
    r_px: np.ndarray
    visible_fraction: np.ndarray


class Renderer:
    def __init__(self, scene: Scene, camera: Camera, ambient: float = 0.45, sensor_noise: float = 2.0):
        self.scene = scene
        self.cam = camera
        self.ambient = ambient
        self.sensor_noise = sensor_noise
        h, w = camera.height, camera.width
        jj, ii = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        k = camera.K_opencv
        self._rays = np.stack([(jj - k[0, 2]) / k[0, 0], (ii - k[1, 2]) / k[1, 1], np.ones_like(jj)], -1).reshape(-1, 3)
        self._offsets = {}
        self._ground_light = ambient + (1 - ambient) * max(scene.sun_enu[2], 0.0)
        self._is_apple = scene.kind == APPLE
        self._bulge = np.where(scene.kind == APPLE, 1.0, np.where(scene.kind == LEAF, 0.5, 0.8)).astype(np.float32)

    def _offset_grid(self, r: int):
        if r not in self._offsets:
            oy, ox = np.mgrid[-r : r + 1, -r : r + 1]
            self._offsets[r] = (ox.ravel().astype(np.int32), oy.ravel().astype(np.int32))
        return self._offsets[r]

    def _ground(self, R, t):
        """Ground colour (H*W, 3) float32 and depth (H*W,) of each pixel's ray hitting z = 0."""
        sc = self.scene
        centre = -R.T @ t
        d = self._rays @ R.astype(np.float32)  # ray directions in world, camera-z normalised
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(d[:, 2] < -1e-6, -centre[2] / d[:, 2], np.inf).astype(np.float32)
        hit = np.isfinite(depth)
        xy = centre[:2].astype(np.float32) + d[:, :2] * np.where(hit, depth, 0)[:, None]
        xy_o = xy @ sc.orchard_to_enu.astype(np.float32)  # ENU -> orchard frame
        x_min, _, _, y_max = sc.ground_extent
        shape = (self.cam.height, self.cam.width)
        mapx = ((xy_o[:, 0] - x_min) / sc.ground_res - 0.5).astype(np.float32).reshape(shape)
        mapy = ((y_max - xy_o[:, 1]) / sc.ground_res - 0.5).astype(np.float32).reshape(shape)
        tex = _remap_window(sc.ground, mapx, mapy)
        colour = tex.reshape(-1, 3).astype(np.float32) / 255.0 * self._ground_light
        sky = np.array([0.62, 0.74, 0.90], np.float32)
        colour[~hit] = sky
        return colour, depth

    def render(self, R: np.ndarray, t: np.ndarray, gain: float = 1.0, blur_px: tuple[float, float] = (0.0, 0.0),
               rng: np.random.Generator | None = None) -> tuple[np.ndarray, FrameTruth]:
        """Render one frame for the world-to-camera pose (R, t): BGR uint8 image and the apples seen."""
        sc, cam = self.scene, self.cam
        h, w = cam.height, cam.width
        ground, gdepth = self._ground(R, t)
        zbuf = np.where(np.isfinite(gdepth), np.minimum(gdepth, 1e6) * _DEPTH_SCALE, 2**38).astype(np.int64)
        zbuf = (zbuf << _ID_BITS) | _ID_MASK

        xc = sc.pos @ R.T.astype(np.float32) + t.astype(np.float32)
        z = xc[:, 2]
        k = cam.K_opencv
        with np.errstate(divide="ignore", invalid="ignore"):
            u = k[0, 0] * xc[:, 0] / z + k[0, 2]
            v = k[1, 1] * xc[:, 1] / z + k[1, 2]
            r = k[0, 0] * sc.radius / z
        m = _MAX_RADIUS_PX
        vis = np.nonzero((z > 0.2) & (u > -m) & (u < w + m) & (v > -m) & (v < h + m))[0]
        u, v, z = u[vis], v[vis], z[vis]
        r = np.clip(r[vis], 0.6, _MAX_RADIUS_PX)
        depth_r = sc.radius[vis] * self._bulge[vis]
        apple_vis = self._is_apple[vis]
        total_px = np.zeros(len(vis), np.int64)

        ri = np.ceil(r).astype(np.int32)
        for rad in np.unique(ri):
            sel_all = np.nonzero(ri == rad)[0]
            ox, oy = self._offset_grid(int(rad))
            for c0 in range(0, len(sel_all), _CHUNK):
                sel = sel_all[c0 : c0 + _CHUNK]
                cu = np.rint(u[sel]).astype(np.int32)
                cv_ = np.rint(v[sel]).astype(np.int32)
                px = cu[:, None] + ox[None, :]
                py = cv_[:, None] + oy[None, :]
                d2 = ((px - u[sel, None]) ** 2 + (py - v[sel, None]) ** 2) / (r[sel, None] ** 2)
                inside = d2 <= 1.0
                a = apple_vis[sel]
                if a.any():
                    total_px[sel[a]] = inside[a].sum(axis=1)
                inside &= (px >= 0) & (px < w) & (py >= 0) & (py < h)
                rows, cols = np.nonzero(inside)
                zf = z[sel][rows] - depth_r[sel][rows] * np.sqrt(1.0 - d2[rows, cols])
                key = ((zf * _DEPTH_SCALE).astype(np.int64) << _ID_BITS) | sel[rows].astype(np.int64)
                np.minimum.at(zbuf, py[rows, cols] * w + px[rows, cols], key)

        winner = (zbuf & _ID_MASK).astype(np.int64)
        on = np.nonzero(winner != _ID_MASK)[0]
        p = winner[on]
        img = ground
        dx = (on % w) - u[p]
        dy = (on // w) - v[p]
        d2 = np.clip((dx * dx + dy * dy) / (r[p] ** 2), 0, 1)
        base = sc.colour[vis[p]]
        shade = (1.0 - 0.35 * d2)[:, None] * base
        ap = apple_vis[p]
        if ap.any():
            # apples: spheres lit by the sun, with a specular highlight
            nx, ny = dx[ap] / r[p[ap]], dy[ap] / r[p[ap]]
            nz = -np.sqrt(np.clip(1 - nx * nx - ny * ny, 0, 1))
            n = np.stack([nx, ny, nz], 1)
            s_cam = R @ sc.sun_enu
            lam = np.clip(n @ s_cam, 0, 1)
            half = s_cam + np.array([0, 0, -1.0])
            half /= np.linalg.norm(half)
            spec = 0.35 * np.clip(n @ half, 0, 1) ** 24
            shade[ap] = base[ap] * (self.ambient + (1 - self.ambient) * lam)[:, None] + spec[:, None]
        img[on] = shade
        img = img.reshape(h, w, 3) * gain

        bx, by = blur_px
        length = float(np.hypot(bx, by))
        if length > 0.75:
            n = int(np.ceil(length)) | 1
            kern = np.zeros((n, n), np.float32)
            c = n // 2
            cv2.line(kern, (int(round(c - bx / 2)), int(round(c - by / 2))),
                     (int(round(c + bx / 2)), int(round(c + by / 2))), 1.0, 1, cv2.LINE_AA)
            img = cv2.filter2D(img, -1, kern / kern.sum())
        img = img * 255.0
        if self.sensor_noise > 0 and rng is not None:
            img = img + rng.normal(0, self.sensor_noise, img.shape).astype(np.float32)
        bgr = cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)

        # apples seen: visible pixels over the pixels of their whole disc (inside the image or not)
        counts = np.bincount(p[ap], minlength=len(vis)) if ap.any() else np.zeros(len(vis), np.int64)
        seen = np.nonzero(apple_vis & (counts > 0))[0]
        aidx = sc.apple_index[vis[seen]]
        xyz = sc.apples["xyz"][aidx]
        uv, zz = cam.project(xyz, R, t)
        truth = FrameTruth(
            apple_index=aidx,
            uv=uv,
            r_px=cam.fx * sc.apples["radius_m"][aidx] / zz,
            visible_fraction=np.clip(counts[seen] / np.maximum(total_px[seen], 1), 0, 1),
        )
        return bgr, truth


def _remap_window(src: np.ndarray, mapx: np.ndarray, mapy: np.ndarray) -> np.ndarray:
    """cv2.remap (bilinear, reflected border) from the part of ``src`` the maps reach: the same pixels, and OpenCV's
    limit of 32,767 px a side then bounds a frame's footprint, not the whole orchard's ground texture."""
    h, w = src.shape[:2]
    fx, fy = mapx[np.isfinite(mapx)], mapy[np.isfinite(mapy)]
    x0 = int(np.clip(np.floor(fx.min()) - 1, 0, w)) if fx.size else 0
    x1 = int(np.clip(np.ceil(fx.max()) + 2, x0, w)) if fx.size else w
    y0 = int(np.clip(np.floor(fy.min()) - 1, 0, h)) if fy.size else 0
    y1 = int(np.clip(np.ceil(fy.max()) + 2, y0, h)) if fy.size else h
    # a window on the texture's edge reflects there as the whole texture would; inside, no pixel needs a border
    if x1 - x0 < 2 or y1 - y0 < 2:
        x0, x1, y0, y1 = 0, w, 0, h
    return cv2.remap(src[y0:y1, x0:x1], mapx - np.float32(x0), mapy - np.float32(y0), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)
