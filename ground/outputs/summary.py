"""The flight's summary as the viewer shows it (markdown): the count by row, how far behind the drone the map is, the
poses and the link, from report.json's figures and the frame being mapped."""

from __future__ import annotations

import numpy as np


def remap_advice(report: dict, journal="OUT/journal.bin") -> str | None:
    """Where the mapping process died and was restarted during the flight, the map kept what the restarted one could
    rebuild in the flight left; the flight's journal played lock-step maps every keyframe in order, as if nothing had
    died (issue 74). The command that does it, for the log and the summary; None where no restart happened."""
    n = len((report.get("registration") or {}).get("mapper_restarts") or [])
    if not n:
        return None
    times = "once" if n == 1 else f"{n} times"
    return (f"the mapping process was restarted {times} in this flight: for the map as if it had not, replay the "
            f"journal lock-step (`python -m ground replay --recorded {journal} --speed 0 --out DIR`, with this "
            f"flight's --orchard and --sample-counts, if any)")


def summary_markdown(report: dict, live: dict) -> str:
    """The glanceable summary: total, per-row table, mapping progress, delay, link and registration health."""
    head = "flight finished" if report.get("final") else "flying"
    lines = [f"# {report['apples']} apples", f"*{report.get('flight_id')}, {head}*", ""]
    rows = report.get("rows") or []
    if rows:
        lines += ["| row | apples | per m | length |", "|:---|---:|---:|---:|"]
        for r in rows:
            per_m = r.get("apples_per_m", float("nan"))
            per_m_txt = f"{per_m:.1f}" if per_m is not None and np.isfinite(per_m) else "–"  # a row too short yet
            lines.append(f"| row {r['row']} | {r['count']} | {per_m_txt} | {r['length_m']:.0f} m |")
        lines.append("")
    fr = report.get("frames", {})
    behind, fps, drone_fps = live.get("behind_s"), live.get("ground_fps"), live.get("drone_fps")
    keeping = f"{behind:.1f} s behind the drone" if behind is not None and np.isfinite(behind) else "delay unknown"
    rate = (f", mapping {fps:.1f} frames/s" if fps is not None and np.isfinite(fps) else "")
    rate += f" (drone: {drone_fps:.1f} frames/s)" if drone_fps is not None and np.isfinite(drone_fps) else ""
    lines.append(f"**Mapping** frame {live.get('frame', '–')} ({fr.get('frames', 0)} frames received): {keeping}{rate}")
    reg = report.get("registration", {})
    gps = reg.get("georeference_gps_rms_m")
    gps_txt = f", GPS fit {gps:.2f} m" if gps is not None and np.isfinite(gps) else ""
    gps_txt += {"heights": ", scaled by the heights above take-off",
                "row_spacing": ", scaled by the layout's row spacing"}.get(reg.get("georeference_scale_from"), "")
    lines.append("")
    trk = report.get("tracking", {})
    lines.append(f"**Registration** {reg.get('registered', 0)} of {reg.get('keyframes_processed', 0)} mapping "
                 f"keyframes, {reg.get('failed', 0)} failed, {reg.get('submodels', 0)} sub-model(s){gps_txt}. Frame "
                 f"poses: {fr.get('registered', 0)} registered, {fr.get('tracked', 0)} tracked "
                 f"({trk.get('failed', 0)} failed to track), {fr.get('interpolated', 0)} interpolated, "
                 f"{fr.get('extrapolated', 0)} carried past the last posed frame, "
                 f"{fr.get('apples', 0)} placed by the apples they see, {fr.get('telemetry', 0)} from telemetry alone, {fr.get('frames_without_pose', 0)} without")
    died = reg.get("mapper_died")
    restarts = reg.get("mapper_restarts") or []
    if died and not restarts:
        lines.append(f"\n**The mapping process died** (exit code {died.get('exit_code')}) after "
                     f"{died.get('keyframes_mapped', 0)} keyframes: the frames since are tracked against the map it "
                     f"left, or placed by telemetry; nothing more is mapped")
    for r in restarts:
        placed = r.get("placed")
        how = (f"its rebuilt model, placed by {placed['keyframes']} shared keyframes, became the map"
               if isinstance(placed, dict)
               else "its new model never shared keyframes with the map: the frames since are tracked against the map"
               if placed is None else placed)
        lines.append(f"\n**The mapping process died** (exit code {r.get('exit_code')}) after "
                     f"{r.get('keyframes_mapped', 0)} keyframes, {r.get('keyframes_lost', 0)} lost; **restarted** "
                     f"and given the map's {r.get('keyframes_remapped', r.get('resent', 0))} keyframes to map again: {how}")
    advice = remap_advice(report) if report.get("final") else None
    if advice:
        lines.append(f"\n{advice[0].upper()}{advice[1:]}")
    if reg.get("in_memory_from_keyframe") is not None:
        lines.append(f"\n**The mapping folder refused a write** (a full disk?) at keyframe "
                     f"{reg['in_memory_from_keyframe']}: mapping went on in memory; the model files mapped since are "
                     f"not written")
    link = report.get("link", {})
    onboard = report.get("onboard_status") or {}
    lines.append("")
    lines.append(f"**Link** {onboard.get('frames_dropped', 0)} frames dropped on board, "
                 f"{fr.get('missing_frames', 0)} missing, {fr.get('late_frames', 0)} late, "
                 f"{link.get('rejected_total', 0)} messages refused")
    if report.get("errors"):
        lines += ["", f"**Errors** {len(report['errors'])}: {report['errors'][-1]}"]
    return "\n".join(lines) + "\n"
