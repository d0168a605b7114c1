"""DJI ``.SRT`` subtitle telemetry: one subtitle per video frame (newer models) or per second (older ones).

The subtitles are read with the ``srt`` library; what each one says depends on the model and firmware. The
layouts known here (``LAYOUTS``), each tested on a real file:

- ``p4p``: Phantom 4 Pro, Mavic Mini, Mavic 2 (early firmware):
  ``F/3.2, SS 160, ISO 100, EV 0, GPS (lon, lat, satellites), D 49.21m, H 45.60m, H.S 0.00m/s, V.S 0.00m/s``;
  H is the height above take-off. No date: the clock is the video's. The Phantom 4 RTK adds ``HOME (lon, lat,
  alt)`` and the vehicle's and the gimbal's angles, ``F.PRY (pitch°, roll°, yaw°), G.PRY (pitch°, roll°, yaw°)``
  (the gimbal's yaw in the earth frame).
- ``home``: Mavic Pro, older firmware: ``HOME(lon,lat) 2017.08.05 14:11:51`` then ``GPS(lon,lat,satellites)
  BAROMETER:1.9`` (or ``Hb:1.9 Hs:1.9``); the barometer gives the height above take-off.
- ``m300``: Matrice 300: ``2022.06.21 16:06:17`` then ``GPS(lat,lon,0.0M) BAROMETER:0.3M`` (latitude first).
- ``bracket``: Mavic 3, Mini 2/3, Air 2S, Mavic 2 (later firmware):
  ``2022-08-07 13:40:40,774,808`` then ``[latitude: 41.424724] [longitude: 2.234156]`` (some firmware spells it
  ``longtitude``) and ``[rel_alt: 1.3 abs_alt: 120.5]`` or ``[altitude: 117.0]`` (above what, DJI does not say: no height above
  take-off is taken from it); some add the gimbal,
  ``[gb_yaw: … gb_pitch: … gb_roll: …]``.

Times: the subtitle's start is the frame's time in the video; the date in the subtitle, where there is one, is
the camera's local clock (DJI writes no time zone). Altitudes are above take-off unless the layout gives
``abs_alt``. A subtitle of an unknown layout is an error naming the file and quoting it; a file cut short keeps
every whole subtitle before the cut (a subtitle whose brackets do not close is cut, not read). A position stands
for a 3-D GPS fix unless the subtitle counts fewer than 4 satellites; lat/lon 0, 0 is no fix.
"""

from __future__ import annotations

import logging
import re
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pomar.rotations import ned_euler_to_rotation, rotation_to_quat_wxyz
# a DJI height above take-off is barometric (written to 0.01 m): BARO_HEIGHT_SIGMA_M, weighed against the positions
# when the ground scales the map (ground.poses.mapper)
from pomar.telemetry.base import BARO_HEIGHT_SIGMA_M, UNSTATED_H_ACC_M, Series, TelemetryError, TelemetryLog, existing

log = logging.getLogger(__name__)

NUM = r"[-+]?\d+(?:\.\d+)?"
LAYOUTS = ("p4p", "home", "m300", "bracket")


def _field(text: str, *names: str) -> float | None:
    """``[name: value]`` or ``name: value`` inside brackets (with or without a space before the colon)."""
    for name in names:
        m = re.search(rf"\b{name}\s*:\s*({NUM})", text)
        if m:
            return float(m.group(1))
    return None


def _date(text: str) -> float | None:
    """The subtitle's date and time (the camera's clock, taken as UTC: DJI writes no zone), unix seconds."""
    m = re.search(r"(\d{4})[.-](\d{1,2})[.-](\d{1,2})\s+(\d{1,2}):(\d{2}):(\d{2})(?:[,.](\d{1,3}))?", text)
    if not m:
        return None
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    ms = int((m.group(7) or "0").ljust(3, "0"))
    return datetime(y, mo, d, h, mi, s, ms * 1000, tzinfo=timezone.utc).timestamp()


def _decimals(text: str, prefix: str) -> int:
    """The fewest decimals among the numbers that follow ``prefix`` (a regex) in the text."""
    found = re.findall(prefix + rf"({NUM})", text)
    return min(len((g.split(".") + [""])[1]) for g in found) if found else 0


def _pry(text: str, name: str) -> tuple[float, float, float] | None:
    """``F.PRY (pitch°, roll°, yaw°)`` -> (roll, pitch, yaw) in degrees, NED."""
    m = re.search(rf"\b{re.escape(name)}\s*\(\s*({NUM})°?\s*,\s*({NUM})°?\s*,\s*({NUM})°?\s*\)", text)
    return (float(m.group(2)), float(m.group(1)), float(m.group(3))) if m else None


def parse_subtitle(text: str) -> tuple[str, dict]:
    """One subtitle's content -> (layout, {lat, lon, alt, abs_alt?, sats?, date?, gimbal?, vehicle?}); ValueError if
    no known layout matches or the subtitle is cut short (its brackets do not close)."""
    if text.lstrip().startswith("<font") and "</font>" not in text:
        raise ValueError("cut short: <font> is not closed")
    text = re.sub(r"<[^>]+>", " ", text)  # <font ...> tags
    out: dict = {"date": _date(text)}
    lat = _field(text, "latitude")
    lon = _field(text, "longitude", "longtitude")
    if lat is not None and lon is not None:
        if text.count("[") != text.count("]"):
            raise ValueError("cut short: a bracket is not closed")
        out.update(lat=lat, lon=lon, decimals=_decimals(text, r"\b(?:latitude|longt?itude)\s*:\s*"))
        rel, absolute = _field(text, "rel_alt"), _field(text, "abs_alt")
        out["alt"] = rel if rel is not None else _field(text, "altitude")
        if rel is None and out["alt"] is not None:
            out["alt_unstated"] = True  # `[altitude: …]` alone: DJI does not say above what (take-off or sea)
        if absolute is not None:
            out["abs_alt"] = absolute
        yaw, pitch, roll = _field(text, "gb_yaw"), _field(text, "gb_pitch"), _field(text, "gb_roll")
        if yaw is not None and pitch is not None:
            out["gimbal"] = (roll or 0.0, pitch, yaw)
        yaw, pitch, roll = _field(text, "drone_yaw"), _field(text, "drone_pitch"), _field(text, "drone_roll")
        if yaw is not None and pitch is not None:
            out["vehicle"] = (roll or 0.0, pitch, yaw)
        return "bracket", out
    m = re.search(rf"GPS\s*\(\s*({NUM})\s*,\s*({NUM})\s*,\s*({NUM})\s*(M?)\s*\)", text)
    if m:
        a, b, c, metres = float(m.group(1)), float(m.group(2)), float(m.group(3)), m.group(4)
        out["decimals"] = min(len((g.split(".") + [""])[1]) for g in (m.group(1), m.group(2)))
        if metres:  # Matrice 300: GPS(lat, lon, altitude M)
            baro = _field(text, "BAROMETER")
            out.update(lat=a, lon=b, alt=baro if baro is not None else c)
            return "m300", out
        out.update(lon=a, lat=b, sats=c)  # the older layouts put longitude first
        for key, name in (("vehicle", "F.PRY"), ("gimbal", "G.PRY")):
            angles = _pry(text, name)
            if angles is not None:
                out[key] = angles
        h = re.search(rf"\bH\s+({NUM})m", text)
        if h:
            out["alt"] = float(h.group(1))
            return "p4p", out
        baro = _field(text, "BAROMETER", "Hb")
        out["alt"] = baro
        return "home", out
    raise ValueError("no position in a layout this reader knows")


def _subtitles(text: str, problems: list[str]) -> list[tuple[int, float | None, str]]:
    """(index, start in the video (s) or None, content) of each subtitle: the ``srt`` library for standard files;
    blocks split at blank lines for the layout whose subtitles have no timing line (``1`` then the date)."""
    import srt

    subs = []
    try:
        for s in srt.parse(text):
            subs.append((s.index, s.start.total_seconds(), s.content))
    except srt.SRTParseError as exc:
        if subs:
            problems.append(f"the file is cut short or damaged after subtitle {subs[-1][0]} ({exc}): the whole "
                            "subtitles before it are used")
    if subs:
        return subs
    out = []
    for block in re.split(r"\n\s*\n", text.strip()):
        lines = block.strip().splitlines()
        if len(lines) < 2 or not lines[0].strip().isdigit():
            continue
        out.append((int(lines[0]), None, "\n".join(lines[1:])))
    return out


def read_srt(path: str | Path, max_gap_s: float = 1.0) -> TelemetryLog:
    path = existing(path)
    t0 = time.perf_counter()
    text = path.read_text(encoding="utf-8-sig", errors="replace")
    problems: list[str] = []
    blocks = _subtitles(text, problems)
    if not blocks:
        raise TelemetryError(f"{path}: no subtitles could be read (not a DJI .SRT?)")
    rows, layouts, empty, bad = [], Counter(), 0, []
    for k, (index, start, content) in enumerate(blocks):
        if not content.strip():
            empty += 1
            continue
        try:
            layout, f = parse_subtitle(content)
        except ValueError:
            if not rows:  # the first subtitle tells the layout: one this reader does not know is an error
                raise TelemetryError(f"{path}: subtitle {index} has no layout this reader knows: "
                                     f"{content.strip()[:160]!r}") from None
            bad.append((k, index, content))
            continue
        layouts[layout] += 1
        rows.append((start, f))
    if bad:
        k, index, content = bad[0]
        where = ("at the end (the file is cut short)" if all(b[0] >= len(blocks) - len(bad) for b in bad)
                 else "among the others")
        problems.append(f"{len(bad)} subtitle(s) without a whole position {where}, from subtitle {index}: "
                        f"{content.strip()[:80]!r}; the {len(rows)} whole ones are used")
        if len(bad) > len(rows):
            raise TelemetryError(f"{path}: most subtitles ({len(bad)} of {len(blocks)}) hold no position in a layout "
                                 f"this reader knows, e.g. subtitle {index}: {content.strip()[:160]!r}")
    if empty:
        problems.append(f"{empty} empty subtitles (a file cut short?) skipped")
    if not rows:
        raise TelemetryError(f"{path}: no subtitle holds a position")
    layout = layouts.most_common(1)[0][0]
    if len(layouts) > 1:
        problems.append("subtitles of " + " and ".join(f"{k} ({v})" for k, v in layouts.most_common())
                        + " layouts in one file: recordings of more than one drone or firmware?")
    dates = np.array([r[1].get("date") or np.nan for r in rows], float)
    if any(r[0] is None for r in rows):  # subtitles without timing lines: one a second, or as their dates say
        first = np.nanmin(dates) if np.isfinite(dates).any() else np.nan
        video_t = np.where(np.isfinite(dates), dates - first, np.arange(len(rows), dtype=float)) \
            if np.isfinite(first) else np.arange(len(rows), dtype=float)
        problems.append("the subtitles have no timing lines: their video times come from their dates")
    else:
        video_t = np.array([r[0] for r in rows], float)
    # the log's clock: the subtitle's date where there is one (video time + the median offset), else video time
    # from an arbitrary epoch (the caller aligns it with the container's creation time)
    if np.isfinite(dates).any():
        offset = float(np.nanmedian(dates - video_t))
        clock = "DJI subtitle dates (the camera's clock, no time zone)"
    else:
        offset = 0.0
        clock = "video time (the subtitles carry no date)"
        problems.append("the subtitles carry no date: times are seconds into the video")
    t = video_t + offset
    repeated = int(len(t) - len(np.unique(t)))
    if repeated:
        problems.append(f"{repeated} subtitle(s) repeat an earlier subtitle's time"
                        + (" (their dates; the layout has no timing lines)" if any(r[0] is None for r in rows) else "")
                        + ": the first of each time is used, the others dropped")
    lat = np.array([r[1]["lat"] for r in rows])
    lon = np.array([r[1]["lon"] for r in rows])
    alt = np.array([r[1].get("abs_alt", r[1].get("alt")) if r[1].get("abs_alt", r[1].get("alt")) is not None
                    else np.nan for r in rows], float)
    absolute = any("abs_alt" in r[1] for r in rows)
    reference = "msl" if absolute else "unstated" if any(r[1].get("alt_unstated") for r in rows) else "takeoff"
    if not np.isfinite(alt).any():
        # a position needs all three coordinates on the wire: a level flight at an unknown height still places and
        # scales the map by its horizontal positions, so the height is taken as 0 and said to be unknown
        alt[:] = 0.0
        reference = "unknown"
        problems.append("the subtitles carry no altitude: heights are taken as 0 (unknown), so the map is placed and "
                        "scaled by the horizontal positions only, its heights are relative, and the apples' size "
                        "cannot be foreseen")
    elif not np.isfinite(alt).all():
        problems.append(f"{int((~np.isfinite(alt)).sum())} subtitles without an altitude: left out")
        k = np.isfinite(alt)
        rows = [r for r, keep in zip(rows, k) if keep]
        t, video_t, lat, lon, alt = t[k], video_t[k], lat[k], lon[k], alt[k]
    ok = ~((lat == 0) & (lon == 0))
    if (~ok).any():
        problems.append(f"{int((~ok).sum())} subtitles at lat/lon 0, 0 (no GPS fix yet): left out")
    position = Series.of(t[ok], np.stack([lat, lon, alt], 1)[ok], 3)
    # a position is a 3-D fix unless the subtitle counts fewer than 4 satellites; 0, 0 is no fix
    sats = np.array([r[1].get("sats", np.nan) for r in rows], float)
    fix = np.where(ok & ~(np.isfinite(sats) & (sats < 4)), 3.0, 0.0)
    step = 111_320.0 * 10.0 ** -np.array([r[1].get("decimals", 7) for r in rows], float)
    # DJI states no accuracy; where the rounding alone is worse than the accuracy assumed of an unstated position,
    # the rounding is the accuracy (a Phantom 4 Pro's 4 decimals: 3.2 m), else it stays unstated (NaN)
    h_acc = np.where(step / np.sqrt(12.0) > UNSTATED_H_ACC_M, step / np.sqrt(12.0), np.nan)
    gps = Series.of(t, np.column_stack([fix, h_acc, np.full(len(t), np.nan), sats]), 4)
    if step.max() > 2.0 * UNSTATED_H_ACC_M:
        problems.append(f"positions written to {int(min(r[1].get('decimals', 7) for r in rows))} decimals: "
                        f"{step.max():.0f} m steps, which scale a map poorly; the heights above take-off scale it "
                        "where they tell it better (the take-off point level with the orchard's floor)")

    def angles(key: str) -> Series:
        a = [(ti, r[1][key]) for ti, r in zip(t, rows) if key in r[1]]
        if not a:
            return Series.empty(4)
        ang = np.array([x for _, x in a], float)
        return Series.of([ti for ti, _ in a],
                         rotation_to_quat_wxyz(ned_euler_to_rotation(ang[:, 0], ang[:, 1], ang[:, 2])), 4)

    gimbal, attitude = angles("gimbal"), angles("vehicle")
    g = len(gimbal)
    # rel_alt beside abs_alt gives the take-off point's altitude
    home = [r[1]["abs_alt"] - r[1]["alt"] for r in rows if "abs_alt" in r[1] and r[1].get("alt") is not None]
    tl = TelemetryLog(str(path), position, gps, attitude, gimbal, {}, None, clock, None,
                      Counter({f"subtitles ({k})": v for k, v in layouts.items()}), max_gap_s=max_gap_s, format="srt",
                      altitude_reference=reference, problems=problems,
                      video_clock=Series.of(video_t, t[:, None], 1),
                      home_alt=float(np.median(home)) if home else None,
                      # the height above take-off is barometric wherever the layout gives it (H, BAROMETER, rel_alt)
                      height_sigma_m=BARO_HEIGHT_SIGMA_M if reference == "takeoff" or home else None,
                      height_from="baro, the SRT's height above take-off" if reference == "takeoff" or home else None)
    if not g and not len(attitude):
        problems.append("no gimbal or vehicle attitude in the subtitles: the camera's attitude needs a fixed mount "
                        "tilt (--camera-tilt-deg), and its heading from the track (--camera-yaw-deg)")
    elif not g:
        problems.append("no gimbal attitude in the subtitles: the camera's attitude needs a fixed mount tilt "
                        "(--camera-tilt-deg) on the vehicle's attitude")
    if g and g < len(rows) or len(attitude) and len(attitude) < len(rows):
        problems.append(f"attitudes on {g} (gimbal) and {len(attitude)} (vehicle) of {len(rows)} subtitles: "
                        "frames away from them are flagged")
    tl.parse_seconds = time.perf_counter() - t0
    log.info("%s: %d subtitles, layout %s", path, len(rows), layout)
    return tl
