"""How visible the apples that ADD256's annotators circled are, against the simulator's: one colour measure on both.

    python benchmarks/label_visibility.py out/sim/detector-train [--add256 ../shared/datasets/add256]

Both datasets mark an apple by a circle (ADD256: cx, cy, r as annotated; the simulator: the whole apple's projection,
truth/detections.csv, with the share of it in view). The measure, the same on both: the share of the pixels inside
the circle's inner 80 % (radius) that are not leaf-green (HSV hue outside 30-95 deg or saturation under 25 %): about 1
for an apple in full view, less as leaves cover it. On the simulated frames it is held against the true visible share,
bin by bin; the ADD256 circles' distribution of it then says which visible share the least visible circled apples
correspond to, and so the visibility threshold V that makes training on both mean the same thing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pomar.countable import IGNORE_ABOVE  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

INNER = 0.8


def not_leaf(img_bgr: np.ndarray) -> np.ndarray:
    """Per pixel: not leaf-green (True for apple, soil, bark, sky)."""
    hsv = cv2.cvtColor(img_bgr, cv2.COLOR_BGR2HSV)
    h, s = hsv[..., 0].astype(float) * 2.0, hsv[..., 1].astype(float) / 255.0
    return ~((h >= 30) & (h <= 95) & (s >= 0.25))


def share_in_circle(mask: np.ndarray, cx: float, cy: float, r: float) -> float:
    """The share of the mask's pixels inside the circle's inner INNER (NaN if it holds fewer than 5 pixels)."""
    h, w = mask.shape
    ri = INNER * r
    x0, x1 = int(max(np.floor(cx - ri), 0)), int(min(np.ceil(cx + ri) + 1, w))
    y0, y1 = int(max(np.floor(cy - ri), 0)), int(min(np.ceil(cy + ri) + 1, h))
    if x1 <= x0 or y1 <= y0:
        return float("nan")
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inside = (xx - cx) ** 2 + (yy - cy) ** 2 <= ri ** 2
    return float(mask[y0:y1, x0:x1][inside].mean()) if inside.sum() >= 5 else float("nan")


def simulated(flight: FlightDir, every: int, variety: str = "Gala") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(visible share, colour share, radius px) of every truth apple of ``variety`` at least IGNORE_ABOVE visible, every
    ``every``-th frame. Gala only by default: the simulator's Fuji is yellow-green, leaf-coloured to this measure, and
    ADD256's apples are red."""
    d = flight.truth_detections()
    a = flight.truth_apples()
    keep = set(np.asarray(a["apple_id"])[np.asarray(a["variety"]) == variety].tolist())
    cap = cv2.VideoCapture(str(flight.video))
    vis, col, rad = [], [], []
    f = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        if f % every == 0:
            mask = not_leaf(img)
            sel = (d["frame"] == f) & (d["visible_fraction"] >= IGNORE_ABOVE) & np.isin(d["apple_id"], list(keep))
            for u, v, r, vf in zip(d["u"][sel], d["v"][sel], d["r_px"][sel], d["visible_fraction"][sel]):
                vis.append(vf)
                col.append(share_in_circle(mask, u, v, r))
                rad.append(r)
        f += 1
    return np.array(vis), np.array(col), np.array(rad)


def add256(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """(colour share, radius px) of every circle of ADD256's training and test sets."""
    col, rad = [], []
    for part in ("training.json", "test.json"):
        for name, circles in json.loads((root / part).read_text()).items():
            if not circles:
                continue
            mask = not_leaf(cv2.imread(str(root / "images" / name)))
            for c in circles:
                col.append(share_in_circle(mask, c["cx"], c["cy"], c["r"]))
                rad.append(c["r"])
    return np.array(col), np.array(rad)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flight", type=Path, help="a simulated flight (its video and truth)")
    ap.add_argument("--add256", type=Path, default=ROOT.parent / "shared" / "datasets" / "add256")
    ap.add_argument("--every", type=int, default=5, help="every n-th frame of the flight")
    a = ap.parse_args(argv)
    vis, col, rad = simulated(FlightDir(a.flight), a.every)
    ok = np.isfinite(col)
    vis, col, rad = vis[ok], col[ok], rad[ok]
    print(f"simulated ({a.flight.name}): {len(vis)} apple views, radius median {np.median(rad):.1f} px")
    print(f"{'visible share':>14} {'views':>6} {'colour share p10':>17} {'median':>7} {'p90':>6}")
    edges = np.array([IGNORE_ABOVE, 0.2, 0.35, 0.5, 0.65, 0.8, 1.01])
    for lo, hi in zip(edges[:-1], edges[1:]):
        s = (vis >= lo) & (vis < hi)
        if s.sum():
            p = np.percentile(col[s], [10, 50, 90])
            print(f"{lo:>6.2f}-{min(hi, 1):<6.2f} {s.sum():>6} {p[0]:>17.2f} {p[1]:>7.2f} {p[2]:>6.2f}")
    c_add, r_add = add256(a.add256)
    c_add = c_add[np.isfinite(c_add)]
    q = np.percentile(c_add, [5, 10, 25, 50])
    print(f"ADD256: {len(c_add)} circles, radius median {np.median(r_add):.1f} px; colour share p5 {q[0]:.2f}, "
          f"p10 {q[1]:.2f}, p25 {q[2]:.2f}, median {q[3]:.2f}")
    print("the share of each visibility threshold's simulated apples whose colour share is under ADD256's p10 "
          "(10 % expected where V matches the annotators' least visible tenth):")
    vs = np.round(np.arange(0.2, 0.81, 0.05), 2)
    under = np.array([(col[vis >= v] < q[1]).mean() for v in vs])
    for v, u in zip(vs, under):
        print(f"  V {v:.2f}: {100 * u:5.1f} % of {(vis >= v).sum()} views")
    cross = np.nonzero(under <= 0.10)[0]
    if len(cross) and cross[0] > 0:
        k = cross[0]
        v10 = vs[k - 1] + (vs[k] - vs[k - 1]) * (under[k - 1] - 0.10) / (under[k - 1] - under[k])
        print(f"V where the simulated apples' least visible tenth looks like ADD256's: {v10:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
