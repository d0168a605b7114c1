"""A picture of a flight plan over the orchard's rows (plan.png), to check at a glance before take-off: the rows in
grey, each tree coloured by the coverage the plan expects (the ground's colours: dark purple none, yellow all), each
pass an arrow in its flight's colour, numbered in the order flown, the take-off point, a scale bar and north. Drawn
with OpenCV (the onboard and ground extras); without it, no picture is written and the plan says so."""

from __future__ import annotations

import numpy as np

#: The picture's longer side (px) and its margin.
SIZE_PX, MARGIN_PX = 1400, 60
#: Each flight's colour (BGR), in turn: Okabe and Ito's colour-blind-safe palette.
FLIGHT_COLOURS = [(178, 114, 0), (0, 94, 213), (115, 158, 0), (167, 121, 204), (233, 180, 86), (66, 228, 240)]


def _viridis(x: float) -> tuple[int, int, int]:
    """A coverage 0-1 as a BGR colour from dark purple to yellow (viridis' ends and middle)."""
    stops = np.array([[84, 1, 68], [140, 145, 33], [37, 231, 253]], float)  # BGR: 0, 0.5, 1
    x = float(np.clip(x, 0.0, 1.0)) * 2
    k = min(int(x), 1)
    c = stops[k] + (x - k) * (stops[k + 1] - stops[k])
    return tuple(int(v) for v in c)


def draw_plan(plan) -> np.ndarray | None:
    """The picture (BGR) of ``plan`` (pomar.plan.Plan); None without OpenCV."""
    try:
        import cv2
    except ImportError:
        return None
    pts = [p.start for f in plan.flights for p in f] + [p.end for f in plan.flights for p in f]
    pts += [np.array([t["x"], t["y"]]) for t in plan.trees]
    P = np.array(pts)
    lo, hi = P.min(0) - 2.0, P.max(0) + 2.0
    scale = (SIZE_PX - 2 * MARGIN_PX) / max(hi - lo)
    w, h = (np.ceil((hi - lo) * scale) + 2 * MARGIN_PX).astype(int)
    img = np.full((h + 40, w, 3), 255, np.uint8)

    def px(xy) -> tuple[int, int]:  # ENU (north up) -> image
        return int(MARGIN_PX + (xy[0] - lo[0]) * scale), int(h - MARGIN_PX - (xy[1] - lo[1]) * scale)

    by_row: dict[int, list] = {}
    for t in plan.trees:
        by_row.setdefault(t["row"], []).append(np.array([t["x"], t["y"]]))
    for row, trees in by_row.items():
        cv2.line(img, px(trees[0]), px(trees[-1]), (200, 200, 200), max(2, int(0.8 * scale)), cv2.LINE_AA)
        cv2.putText(img, str(row), px(trees[0] - 1.5 * (trees[-1] - trees[0]) / np.linalg.norm(trees[-1] - trees[0])),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (60, 60, 60), 1, cv2.LINE_AA)
    for t in plan.trees:
        cv2.circle(img, px((t["x"], t["y"])), max(2, int(0.3 * scale)), _viridis(t["coverage"]), -1, cv2.LINE_AA)
    k = 0
    for i, passes in enumerate(plan.flights):
        colour = FLIGHT_COLOURS[i % len(FLIGHT_COLOURS)]
        for p in passes:
            k += 1
            cv2.arrowedLine(img, px(p.start), px(p.end), colour, 2, cv2.LINE_AA, tipLength=12 / max(1, p.length_m * scale))
            cv2.putText(img, str(k), px(p.start), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    cv2.drawMarker(img, px(plan.flights[0][0].start), (0, 0, 0), cv2.MARKER_TRIANGLE_UP, 18, 2)
    bar = 10.0 if (hi - lo).max() < 150 else 50.0  # a scale bar and north
    cv2.line(img, (MARGIN_PX, h + 10), (int(MARGIN_PX + bar * scale), h + 10), (0, 0, 0), 3)
    cv2.putText(img, f"{bar:g} m", (MARGIN_PX, h + 32), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.arrowedLine(img, (w - 30, 60), (w - 30, 20), (0, 0, 0), 2, cv2.LINE_AA, tipLength=0.3)
    cv2.putText(img, "N", (w - 36, 78), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    d = plan.as_dict()
    text = (f"{d['batteries']} flight(s), {d['minutes']:.1f} min; {d['height_m']:.1f} m above take-off, "
            f"{d['speed_mps']:.1f} m/s; coverage {d['coverage']['mean']:.2f} (trees: purple none, yellow all)")
    cv2.putText(img, text, (MARGIN_PX + int(bar * scale) + 20, h + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                cv2.LINE_AA)
    return img


def plan_png(plan) -> bytes | None:
    """plan.png's bytes; None without OpenCV."""
    img = draw_plan(plan)
    if img is None:
        return None
    import cv2

    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes() if ok else None
