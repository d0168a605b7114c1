"""The map on the grower's layout (issue 71): the shift across the rows that puts the map's apples on the layout's
row lines, before each apple is given its row and tree and each tree its coverage.

The map's position is the GPS track's (a one-pass flight's can lie a metre off across the rows), and the layout's is
the grower's; shifted apples land in a neighbour's strip, and the coverage, drawn from the same shifted cameras, marks
as seen the faces of other trees. Along the rows nothing is measured: every row looks the same along its length.

An apple seen from one side lies on the canopy's face towards the camera, ``face`` metres off its row's line. So its
signed offset from the nearest line (positive on the camera's side) is ``shift . side + face``. Where both sides of
the rows were seen (two passes, a serpentine), the two sides' medians give both (the shift their mean, the face half
their difference). Where one side only was seen the two cannot be told apart, and the shift centres the apples on the
line (the face's offset is left in it, at most the canopy's half-depth); of the row lines a spacing apart, theirs is
the one on the far side from the camera (a face seen faces the camera). Rows are taken as parallel (their mean
direction); a shift of about half the row spacing or more cannot be told from the next row's.
"""

from __future__ import annotations

import numpy as np

#: Apples on a side of the rows, at least, for that side's median to count.
MIN_APPLES = 20
#: Where apples seen from one side only lie off their row's line, towards the camera (m): about half a hedge's
#: half-depth (tall-spindle and super-spindle canopies stand 0.6-1.2 m wide at the fruiting height). It only picks,
#: of the row lines a spacing apart, the one a one-sided flight's apples belong to.
FACE_PRIOR_M = 0.3


def _circular_mean(x: np.ndarray, period: float) -> tuple[float, float]:
    """(the mean of ``x`` taken modulo ``period``, in [-period/2, period/2); its resultant length, 0-1: 1 where every
    value has one phase, 0 where they are spread evenly)."""
    z = np.exp(2j * np.pi * x / period).mean()
    return float(np.angle(z) * period / (2 * np.pi)), float(abs(z))


def layout_shift(apples_xy: np.ndarray, cameras_xy: np.ndarray, lines: list[dict]) -> dict:
    """The shift (ENU metres, horizontal) that moves the map onto the layout's rows, from the map's apples
    (``apples_xy``, (N, 2) ENU) and the camera that saw each (``cameras_xy``, (N, 2); NaN where unknown), about the
    layout's row ``lines`` (ground.orchard.assign's: start ``a``, unit normal ``n``). Returns ``shift`` (2,),
    ``across_m`` (its size across the rows, signed along the rows' mean normal), ``face_m`` (the seen face's offset
    from the line, NaN where one side only was seen), the apples on each side, how sharply the apples lie in rows
    (``resultant``: 1 all on lines, 0 spread evenly) and ``how``."""
    none = {"shift": np.zeros(2), "across_m": 0.0, "face_m": float("nan"), "apples": [0, 0], "resultant": 0.0,
            "how": "not shifted: fewer than two parallel rows, or too few apples seen from the cameras"}
    if len(lines) < 2 or len(apples_xy) < MIN_APPLES:
        return none
    n = np.array([L["n"] * np.sign(L["n"] @ lines[0]["n"]) for L in lines]).mean(0)
    n /= np.linalg.norm(n)
    # the rows' spacing, from their lines' offsets along the normal (rows in any order, some perhaps left out)
    offsets = np.sort([(L["a"] - lines[0]["a"]) @ n for L in lines])
    gaps = np.diff(offsets)
    spacing = float(np.median(gaps[gaps > 0.1])) if (gaps > 0.1).any() else 0.0
    if spacing <= 0 or np.ptp(np.mod(offsets / spacing + 0.5, 1.0) - 0.5) > 0.1:
        return {**none, "how": "not shifted: the layout's rows are not evenly spaced"}
    across = (apples_xy - lines[0]["a"]) @ n  # each apple across the rows, from the first row's line
    side = np.sign((cameras_xy - apples_xy) @ n)  # the side of the apple its camera saw it from
    plus, minus = across[side > 0], across[side < 0]
    face = float("nan")
    if len(plus) >= MIN_APPLES and len(minus) >= MIN_APPLES:
        mp, rp = _circular_mean(plus, spacing)
        mm, rm = _circular_mean(minus, spacing)
        half = (mp - mm) / 2  # the two faces lie face_m either side of the line: their phases' midpoint is the line
        half = (half + spacing / 4) % (spacing / 2) - spacing / 4
        shift, face, r = mm + half, float(half), (rp + rm) / 2
        how = "both sides of the rows seen: the line between the two faces' apples"
        shift = float((shift + spacing / 2) % spacing - spacing / 2)
    elif len(plus) + len(minus) >= MIN_APPLES:
        shift, r = _circular_mean(across[side != 0], spacing)
        # a face seen faces the camera: its apples lie on the camera's side of their line, about FACE_PRIOR_M out. Of
        # the lines a spacing apart, theirs is the one that puts them nearest that
        s = 1.0 if len(plus) >= len(minus) else -1.0
        shift = float(s * ((s * shift - FACE_PRIOR_M + spacing / 2) % spacing - spacing / 2 + FACE_PRIOR_M))
        how = "one side of the rows seen: the apples centred on the line (the face's offset left in)"
    else:
        return none
    return {"shift": shift * n, "across_m": shift, "face_m": face, "apples": [int(len(plus)), int(len(minus))],
            "resultant": float(r), "spacing_m": spacing, "how": how}


def register_to_layout(table: dict, cams: dict, layout, origin) -> tuple[dict, dict, dict]:
    """The map's apples (apple_table's columns) and cameras (pose_table's) shifted onto the layout's rows
    (:func:`layout_shift`; copies, the map's own positions are left as they are), and report.json's record of the
    shift."""
    from ground.orchard.assign import _lines

    lines = _lines(layout, origin)
    xy = np.column_stack([table["x"], table["y"]]) if len(table["id"]) else np.zeros((0, 2))
    cam_xy = np.full_like(xy, np.nan)
    if len(cams["frame"]) and len(xy):
        # the camera midway through each apple's frames: the side it was seen from
        frames = np.asarray(cams["frame"])
        mid = (np.asarray(table["first_frame"]) + np.asarray(table["last_frame"])) // 2
        k = np.clip(np.searchsorted(frames, mid), 0, len(frames) - 1)
        cam_xy = np.column_stack([cams["x"], cams["y"]])[k]
    found = layout_shift(xy, cam_xy, lines)
    dx, dy = found.pop("shift")
    record = {"east_m": round(float(dx), 3), "north_m": round(float(dy), 3),
              **{k: (round(v, 3) if isinstance(v, float) and np.isfinite(v) else v if not isinstance(v, float)
                     else None) for k, v in found.items()}}
    if dx == 0 and dy == 0:
        return table, cams, record
    moved = {**table, "x": np.asarray(table["x"]) - dx, "y": np.asarray(table["y"]) - dy}
    cams = {**cams, "x": np.asarray(cams["x"]) - dx, "y": np.asarray(cams["y"]) - dy}
    return moved, cams, record
