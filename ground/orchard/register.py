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


#: A face is told from where its camera stood only where the camera looked at it from the side: its run across the
#: row at least this share of its height above the apple (rays 19 deg or more off the vertical, about twice the lean
#: of a slender canopy's faces, 6-11 deg for 0.6-1.2 m wide over 3 m). A camera nearly above a row looks down over its
#: top and sees apples on either face: on heavy-tune-1 the row 2.4 m beside the pass showed its far face, and the
#: rows' spacing read 3.50 m for 4.00 (docs/benchmarks.md, twenty-sixth session).
FACE_MIN_RUN = 0.35
#: Apples a row's side needs for its place across the rows to count in the map's row spacing.
MIN_ROW_APPLES = 10
#: How far a canopy's face lies off its row's line varies from row to row (m, 1 sigma): vigour, pruning. It bounds how
#: well one row's apples place its line, however many there are.
FACE_SD_M = 0.1


def map_spacing(across: np.ndarray, side: np.ndarray, shift: float, spacing: float) -> dict:
    """The rows' spacing as the map has them (its own metres), with its 1-sigma: each row's apples seen from one side
    (``side`` +1 or -1; 0 unknown) give that face's place across the rows (their median, ``across`` less ``shift``);
    one line through the rows' places, a face offset for each side, is fitted by weighted least squares (each place's
    variance its median's plus FACE_SD_M squared). NaN with fewer than two rows measured."""
    a = across - shift
    k = np.rint(a / spacing)
    ks, ys, vs, sides = [], [], [], []
    for sd in (1, -1):
        for kk in np.unique(k[side == sd]):
            sel = (k == kk) & (side == sd)
            if sel.sum() < MIN_ROW_APPLES:
                continue
            y = a[sel]
            spread = 1.4826 * np.median(np.abs(y - np.median(y)))
            ks.append(kk), ys.append(np.median(y)), sides.append(sd)
            vs.append((1.2533 * spread) ** 2 / sel.sum() + FACE_SD_M ** 2)
    none = {"map_m": float("nan"), "sigma_m": float("nan"), "rows": len(set(ks))}
    if len(set(ks)) < 2:
        return none
    used = sorted(set(sides))
    X = np.column_stack([np.array(ks)] + [np.array(sides) == sd for sd in used]).astype(float)
    if np.linalg.matrix_rank(X) < X.shape[1]:  # e.g. two rows, each seen from its own side: spacing and faces confound
        return none
    W = 1.0 / np.array(vs)
    cov = np.linalg.inv(X.T @ (X * W[:, None]))
    beta = cov @ (X.T @ (W * np.array(ys)))
    return {"map_m": float(beta[0]), "sigma_m": float(np.sqrt(cov[0, 0])), "rows": len(set(ks))}


def _circular_mean(x: np.ndarray, period: float) -> tuple[float, float]:
    """(the mean of ``x`` taken modulo ``period``, in [-period/2, period/2); its resultant length, 0-1: 1 where every
    value has one phase, 0 where they are spread evenly)."""
    z = np.exp(2j * np.pi * x / period).mean()
    return float(np.angle(z) * period / (2 * np.pi)), float(abs(z))


def layout_shift(apples_xy: np.ndarray, cameras_xy: np.ndarray, lines: list[dict],
                 drop_m: np.ndarray | None = None) -> dict:
    """The shift (ENU metres, horizontal) that moves the map onto the layout's rows, from the map's apples
    (``apples_xy``, (N, 2) ENU) and the camera that saw each (``cameras_xy``, (N, 2); NaN where unknown), about the
    layout's row ``lines`` (ground.orchard.assign's: start ``a``, unit normal ``n``). Returns ``shift`` (2,),
    ``across_m`` (its size across the rows, signed along the rows' mean normal), ``face_m`` (the seen face's offset
    from the line, NaN where one side only was seen), the apples on each side, how sharply the apples lie in rows
    (``resultant``: 1 all on lines, 0 spread evenly) and ``how``. ``drop_m``: each camera's height above its apple
    (m; NaN unknown): an apple seen from nearly above tells no side (FACE_MIN_RUN)."""
    none = {"shift": np.zeros(2), "across_m": 0.0, "face_m": float("nan"), "apples": [0, 0], "resultant": 0.0,
            "how": "not shifted: fewer than two parallel rows, or too few apples seen from the cameras"}
    if len(lines) < 2 or len(apples_xy) < MIN_APPLES:
        return none
    u = _mean_direction(lines)
    n = np.array([-u[1], u[0]])  # the rows' mean normal, turned from their mean direction as each row's is
    # the rows' spacing, from their lines' offsets along the normal (rows in any order, some perhaps left out)
    offsets = np.sort([(L["a"] - lines[0]["a"]) @ n for L in lines])
    gaps = np.diff(offsets)
    spacing = float(np.median(gaps[gaps > 0.1])) if (gaps > 0.1).any() else 0.0
    if spacing <= 0 or np.ptp(np.mod(offsets / spacing + 0.5, 1.0) - 0.5) > 0.1:
        return {**none, "how": "not shifted: the layout's rows are not evenly spaced"}
    across = (apples_xy - lines[0]["a"]) @ n  # each apple across the rows, from the first row's line
    run = (cameras_xy - apples_xy) @ n
    side = np.sign(run)  # the side of the apple its camera saw it from
    if drop_m is not None:
        side[np.abs(run) < FACE_MIN_RUN * np.asarray(drop_m, float)] = 0.0
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
    measured = map_spacing(across, side, shift, spacing)
    return {"shift": shift * n, "across_m": shift, "face_m": face, "apples": [int(len(plus)), int(len(minus))],
            "resultant": float(r), "spacing_m": spacing, "map_spacing_m": measured["map_m"],
            "map_spacing_sigma_m": measured["sigma_m"], "rows_measured": measured["rows"], "how": how}


def register_to_layout(table: dict, cams: dict, layout, origin) -> tuple[dict, dict, dict]:
    """The map's apples (apple_table's columns) and cameras (pose_table's) shifted onto the layout's rows: across them
    by one shift (:func:`layout_shift`), along them pass by pass where a pass filmed the rows' ends
    (:func:`pass_shifts`); copies, the map's own positions are left as they are. And report.json's record of the
    shift (``passes``: each pass's first and last frame, the rows that placed it and its shift along them)."""
    from ground.orchard.assign import _lines

    lines = _lines(layout, origin)
    xy = np.column_stack([table["x"], table["y"]]) if len(table["id"]) else np.zeros((0, 2))
    cam_xy = np.full_like(xy, np.nan)
    drop = np.full(len(xy), np.nan)
    k = np.zeros(len(xy), int)
    if len(cams["frame"]) and len(xy):
        # the camera midway through each apple's frames: the side it was seen from
        frames = np.asarray(cams["frame"])
        mid = (np.asarray(table["first_frame"]) + np.asarray(table["last_frame"])) // 2
        k = np.clip(np.searchsorted(frames, mid), 0, len(frames) - 1)
        cam_xy = np.column_stack([cams["x"], cams["y"]])[k]
        drop = np.asarray(cams["z"], float)[k] - np.asarray(table["z"], float)
    found = layout_shift(xy, cam_xy, lines, drop)
    dx, dy = found.pop("shift")
    record = {"east_m": round(float(dx), 3), "north_m": round(float(dy), 3),
              **{k: (round(v, 3) if isinstance(v, float) and np.isfinite(v) else v if not isinstance(v, float)
                     else None) for k, v in found.items()}}
    moved_xy = xy - np.array([dx, dy])
    cams_xy = np.column_stack([cams["x"], cams["y"]]) - np.array([dx, dy]) if len(cams["frame"]) else np.zeros((0, 2))
    if len(cams["frame"]) and len(xy):
        along = pass_shifts(moved_xy, k, cams_xy, lines)
        record["passes"] = [{"first_frame": int(frames[p["first"]]), "last_frame": int(frames[p["last"]]),
                             "rows": p["rows"], "along_m": p["along_m"]} for p in along]
        u = _mean_direction(lines)
        for p in along:
            if p["along_m"] is not None:
                moved_xy[np.isin(k, p["cams"])] -= p["along_m"] * u
                cams_xy[p["cams"]] -= p["along_m"] * u
    if not len(xy) or (dx == 0 and dy == 0 and not any(p["along_m"] for p in record.get("passes", []))):
        return table, cams, record
    moved = {**table, "x": moved_xy[:, 0], "y": moved_xy[:, 1]}
    if len(cams["frame"]):
        cams = {**cams, "x": cams_xy[:, 0], "y": cams_xy[:, 1]}
    return moved, cams, record


#: Frames either side over which a camera's run along the rows tells which way it flies (passes turn back at the ends).
PASS_SMOOTH_FRAMES = 5
#: Frames a pass has at least; shorter runs (turns, hops between passes) are in none.
MIN_PASS_FRAMES = 10
#: Apples a pass saw on a row, at least, for where they start and stop to place the pass along the rows.
MIN_END_APPLES = 20
#: A row places a pass where the pass saw at least this share of the apples of the row it saw most of (the row whose
#: face it filmed; on plan-eval b the rows further off showed 10-11 m of their 19).
NEAR_ROW_SHARE = 0.5


def _mean_direction(lines: list[dict]) -> np.ndarray:
    """The rows' mean direction (unit, ENU), each row's taken the way the first row's runs."""
    u = np.array([L["u"] * np.sign(L["u"] @ lines[0]["u"]) for L in lines]).mean(0)
    return u / np.linalg.norm(u)


def pass_shifts(xy: np.ndarray, k: np.ndarray, cams_xy: np.ndarray, lines: list[dict]) -> list[dict]:
    """Each pass's shift along the rows (issue 72): a sub-model, placed by its own stretch of GPS, can lie metres off
    along the rows, where every row looks the same, except at its ends. A pass is a run of cameras (``cams_xy``, in
    frame order) flying one way along the rows; where its cameras run past both ends of a row whose apples (``xy``,
    each seen midway by camera ``k``) it saw, the middle of those apples' extent (their 2nd to 98th percentile along
    the row) against the middle of the row's strip (where its apples belong, ground.orchard.assign: its ends, or half
    a spacing past its end trees where those stand that close; the trees' middle, where they stand evenly, and a layout
    made from a map's rows, which ends at its outermost apples, alike) is its offset; the pass's shift is the median
    over such rows that hold at least NEAR_ROW_SHARE of the apples of the one it saw most of
    (``along_m``; None where no row's ends were filmed). Each pass: ``first`` and ``last`` camera index, ``rows``,
    ``along_m`` and its cameras (``cams``)."""
    if len(cams_xy) < MIN_PASS_FRAMES or not lines:
        return []
    u = _mean_direction(lines)
    s = cams_xy @ u
    w = PASS_SMOOTH_FRAMES
    ahead = np.concatenate([s[w:], np.repeat(s[-1], w)]) - np.concatenate([np.repeat(s[0], w), s[:-w]])
    way = np.sign(ahead)
    cuts = np.nonzero(np.diff(way) != 0)[0] + 1
    out = []
    for run in np.split(np.arange(len(s)), cuts):
        if len(run) < MIN_PASS_FRAMES or way[run[0]] == 0:
            continue
        mine = np.isin(k, run)
        seen = []  # (apples, offset) of each row the pass filmed end to end
        for L in lines:
            t_cam = (cams_xy[run] - L["a"]) @ L["u"]
            if not (t_cam.min() <= L["along"][0] and t_cam.max() >= L["along"][-1]):
                continue
            on = mine & (np.abs((xy - L["a"]) @ L["n"]) < L["half_width"])
            if on.sum() < MIN_END_APPLES:
                continue
            lo, hi = np.percentile((xy[on] - L["a"]) @ L["u"], [2, 98])
            seen.append((int(on.sum()), ((lo + hi) / 2 - sum(L["span"]) / 2) * float(L["u"] @ u)))
        # the rows whose face the pass filmed: a row further off shows over the near one's top in part only, and its
        # apples stop short of its ends
        most = max((n for n, _ in seen), default=0)
        offsets = [o for n, o in seen if n >= NEAR_ROW_SHARE * most]
        out.append({"first": int(run[0]), "last": int(run[-1]), "rows": len(offsets),
                    "along_m": round(float(np.median(offsets)), 3) if offsets else None, "cams": run})
    return out


def scaled_to_layout(snap, table: dict, cams: dict, layout):
    """The map ``snap`` (ground.outputs.snapshot.MapSnapshot, whose apples and cameras are ``table`` and ``cams``,
    apple_table's and pose_table's) with the layout's row spacing as one more source of its scale: the spacing between
    the map's rows (:func:`register_to_layout`) against the layout's, combined with the map's own sources by their
    variances (ground.poses.scale), and the map stretched by what that changes (left out where it disagrees with
    them, and said so in the scale's sources). ``snap`` as it is where the spacing was not measured or the map has no
    scale yet."""
    from ground.outputs.snapshot import rescaled
    from ground.poses.scale import row_spacing_source, with_source

    if not snap.scale or snap.to_enu is None or snap.origin is None:
        return snap
    _, _, shift = register_to_layout(table, cams, layout, snap.origin)
    src = row_spacing_source(snap.scale["scale"], shift.get("spacing_m") or 0.0,
                             *(float("nan") if shift.get(k) is None else float(shift[k])
                               for k in ("map_spacing_m", "map_spacing_sigma_m")))
    est = with_source(snap.scale, src) if src is not None else None
    return rescaled(snap, est.as_dict()) if est is not None else snap


#: The map's row spacing disagrees with the layout's beyond this many sigmas of their joint uncertainty (the
#: measurement's and the map scale's): the layout, or the map's scale, is wrong.
SPACING_SIGMAS = 3.0


def spacing_check(shift: dict, scale_sigma_rel: float) -> dict | None:
    """report.json's ``orchard.row_spacing``: the layout's row spacing against the map's (``shift``: the record
    :func:`register_to_layout` gives), the factor the map would take to match the layout alone (``layout / map``)
    and its relative 1-sigma, and whether the two agree within SPACING_SIGMAS of their joint uncertainty (the map
    scale's ``scale_sigma_rel``, NaN: not known, taken as 0). Measured on the map as scaled with the spacing
    (:func:`scaled_to_layout`), so where the two agree what is left is small. None where the map's spacing was not
    measured."""
    layout_m, map_m, sd = (shift.get(k) for k in ("spacing_m", "map_spacing_m", "map_spacing_sigma_m"))
    if not layout_m or map_m is None or sd is None or not np.isfinite(map_m) or map_m <= 0:
        return None
    rel = float(np.hypot(sd / map_m, np.nan_to_num(scale_sigma_rel)))
    z = abs(np.log(layout_m / map_m)) / rel if rel > 0 else float("inf")
    return {"layout_m": round(float(layout_m), 3), "map_m": round(float(map_m), 3),
            "map_sigma_m": round(float(sd), 3), "rows": shift.get("rows_measured"),
            "factor": round(float(layout_m / map_m), 4), "factor_sigma_pct": round(100.0 * sd / map_m, 2),
            "sigmas_apart": round(float(z), 2), "agrees": bool(z <= SPACING_SIGMAS)}
