"""A flight plan (pomar.plan) for the apps growers fly with, one file per flight (battery):

- QGroundControl's ``.plan`` (its documented JSON: a mission of SimpleItems), for ArduPilot and PX4;
- the plain-text ``QGC WPL 110`` mission (mavlink.io's file formats), which Mission Planner, QGroundControl and
  pymavlink's ``mavwp`` load;
- Litchi's CSV mission (its documented columns), for DJI consumer drones (the Phantom 4 Pro, the Mavic);
- DJI WPML's ``.kmz`` (``wpmz/template.kml`` and ``wpmz/waylines.wpml``), for DJI Pilot 2 (DJI's enterprise drones).

Heights are above the take-off point (MAVLink's MAV_FRAME_GLOBAL_RELATIVE_ALT, Litchi's altitude mode 0), as the plan
gives them; no file claims an accuracy: the waypoints are the layout's, as precise as the grower drew it.

Each flight: take off to the plan's height; set the gimbal's pitch; for each pass, fly to its start at transit speed,
turn the camera (the aircraft's heading) to the row, start the video on the first, fly the pass at the plan's speed;
stop the video, return to launch.
"""

from __future__ import annotations

import csv
import io
import json

from pomar.plan import TRANSIT_MPS, Plan

# MAVLink commands and frames (common.xml)
NAV_WAYPOINT, NAV_RETURN_TO_LAUNCH, NAV_TAKEOFF = 16, 20, 22
CONDITION_YAW, DO_CHANGE_SPEED, DO_MOUNT_CONTROL = 115, 178, 205
VIDEO_START_CAPTURE, VIDEO_STOP_CAPTURE = 2500, 2501
FRAME_MISSION, FRAME_GLOBAL_RELATIVE_ALT = 2, 3
#: MAV_AUTOPILOT of the .plan's firmwareType: ArduPilot (3) or PX4 (12).
FIRMWARE = {"ardupilot": 3, "px4": 12}


def mission_items(plan: Plan, flight: int) -> list[tuple[int, int, list, bool]]:
    """Flight ``flight``'s (0-based) mission as (command, frame, 7 params, is a position) tuples, take-off first."""
    f = plan.as_dict()["flights"][flight]
    h, v = plan.geometry["height_m"], plan.speed["speed_mps"]
    transit = min(TRANSIT_MPS, plan.drone.max_speed_mps)
    wps = f["waypoints"]
    items = [(NAV_TAKEOFF, FRAME_GLOBAL_RELATIVE_ALT, [0, 0, 0, None, wps[0]["lat"], wps[0]["lon"], h], True),
             (DO_MOUNT_CONTROL, FRAME_MISSION, [-plan.settings.pitch_deg, 0, 0, 0, 0, 0, 2], False)]
    for k in range(0, len(wps), 2):
        a, b = wps[k], wps[k + 1]
        items += [(DO_CHANGE_SPEED, FRAME_MISSION, [1, transit, -1, 0, 0, 0, 0], False),
                  (NAV_WAYPOINT, FRAME_GLOBAL_RELATIVE_ALT, [0, 0, 0, a["heading_deg"], a["lat"], a["lon"], h], True),
                  (CONDITION_YAW, FRAME_MISSION, [a["heading_deg"], 0, 0, 0, 0, 0, 0], False)]
        if k == 0:
            items.append((VIDEO_START_CAPTURE, FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0], False))
        items += [(DO_CHANGE_SPEED, FRAME_MISSION, [1, v, -1, 0, 0, 0, 0], False),
                  (NAV_WAYPOINT, FRAME_GLOBAL_RELATIVE_ALT, [0, 0, 0, b["heading_deg"], b["lat"], b["lon"], h], True)]
    items += [(VIDEO_STOP_CAPTURE, FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0], False),
              (NAV_RETURN_TO_LAUNCH, FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0], False)]
    return items


def qgc_plan(plan: Plan, flight: int, firmware: str = "ardupilot") -> str:
    """QGroundControl's .plan (JSON, version 1) of one flight."""
    items = []
    for k, (cmd, frame, params, nav) in enumerate(mission_items(plan, flight)):
        item = {"autoContinue": True, "command": cmd, "doJumpId": k + 1, "frame": frame, "params": params,
                "type": "SimpleItem"}
        if nav:
            item.update({"AMSLAltAboveTerrain": None, "Altitude": params[6], "AltitudeMode": 1})
        items.append(item)
    first = plan.as_dict()["flights"][flight]["waypoints"][0]
    body = {"fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
            "geoFence": {"circles": [], "polygons": [], "version": 2},
            "rallyPoints": {"points": [], "version": 2},
            "mission": {"version": 2, "firmwareType": FIRMWARE[firmware], "vehicleType": 2,
                        "cruiseSpeed": min(TRANSIT_MPS, plan.drone.max_speed_mps),
                        "hoverSpeed": plan.speed["speed_mps"], "globalPlanAltitudeMode": 1,
                        "plannedHomePosition": [first["lat"], first["lon"], 0], "items": items}}
    return json.dumps(body, indent=1) + "\n"


def wpl(plan: Plan, flight: int) -> str:
    """The plain-text mission ``QGC WPL 110`` of one flight: line 0 the home (the first pass's start, at 0 m)."""
    first = plan.as_dict()["flights"][flight]["waypoints"][0]
    rows = [[0, 1, 0, NAV_WAYPOINT, 0, 0, 0, 0, first["lat"], first["lon"], 0, 1]]
    for k, (cmd, frame, params, _) in enumerate(mission_items(plan, flight)):
        rows.append([k + 1, 0, frame, cmd, *[0 if p is None else p for p in params], 1])
    fmt = lambda x: f"{x:.8f}" if isinstance(x, float) else str(x)  # noqa: E731
    return "QGC WPL 110\n" + "".join("\t".join(fmt(x) for x in r) + "\n" for r in rows)


#: Litchi's mission CSV columns (its documented header), 15 actions a waypoint.
LITCHI_COLUMNS = (["latitude", "longitude", "altitude(m)", "heading(deg)", "curvesize(m)", "rotationdir", "gimbalmode",
                   "gimbalpitchangle"] + [f"action{k}{s}" for k in range(1, 16) for s in ("type", "param")]
                  + ["altitudemode", "speed(m/s)", "poi_latitude", "poi_longitude", "poi_altitude(m)",
                     "poi_altitudemode", "photo_timeinterval", "photo_distinterval"])
LITCHI_START_RECORDING, LITCHI_STOP_RECORDING, LITCHI_NO_ACTION = 2, 3, -1


def litchi_csv(plan: Plan, flight: int) -> str:
    """Litchi's CSV mission of one flight: each pass's start and end, heights above take-off (altitude mode 0), the
    gimbal's pitch at every waypoint (gimbal mode 2), the video started at the first and stopped at the last; the
    speed given at a waypoint holds to the next (the pass's at its start, the transit's at its end)."""
    wps = plan.as_dict()["flights"][flight]["waypoints"]
    v = plan.speed["speed_mps"]
    transit = min(TRANSIT_MPS, plan.drone.max_speed_mps)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(LITCHI_COLUMNS)
    for k, p in enumerate(wps):
        actions = [LITCHI_NO_ACTION, 0] * 15
        if k == 0:
            actions[:2] = [LITCHI_START_RECORDING, 0]
        elif k == len(wps) - 1:
            actions[:2] = [LITCHI_STOP_RECORDING, 0]
        speed = v if k % 2 == 0 else transit
        w.writerow([f"{p['lat']:.9f}", f"{p['lon']:.9f}", f"{plan.geometry['height_m']:.2f}",
                    f"{p['heading_deg']:.1f}", 0, 0, 2, f"{-plan.settings.pitch_deg:.1f}", *actions, 0,
                    f"{speed:.2f}", 0, 0, 0, 0, -1, -1])
    return buf.getvalue()


#: DJI WPML's namespaces (DJI Cloud API, WPML 1.0.2).
KML_NS, WPML_NS = "http://www.opengis.net/kml/2.2", "http://www.dji.com/wpmz/1.0.2"
#: WPML's drone enumeration (droneEnumValue, droneSubEnumValue) of the drones DJI Pilot 2 flies: the Mavic 3
#: Enterprise series for the Mavic 3; the others have none (DJI Pilot 2 asks for the drone on import).
WPML_DRONES = {"mavic-3": (77, 0)}


def _wpml_document(plan: Plan, flight: int, template: bool) -> str:
    """template.kml (``template``: the route as drawn, heights relative to the start point) or waylines.wpml (what
    the aircraft executes) of one flight."""
    from xml.sax.saxutils import escape

    f = plan.as_dict()["flights"][flight]
    wps = f["waypoints"]
    h, v = plan.geometry["height_m"], plan.speed["speed_mps"]
    transit = min(TRANSIT_MPS, plan.drone.max_speed_mps)
    drone = WPML_DRONES.get(plan.drone.name)
    info = (f"<wpml:droneInfo><wpml:droneEnumValue>{drone[0]}</wpml:droneEnumValue>"
            f"<wpml:droneSubEnumValue>{drone[1]}</wpml:droneSubEnumValue></wpml:droneInfo>" if drone else "")
    out = ['<?xml version="1.0" encoding="UTF-8"?>', f'<kml xmlns="{KML_NS}" xmlns:wpml="{WPML_NS}">', "<Document>"]
    if template:
        out += [f"<wpml:author>pomar plan</wpml:author>",
                f"<wpml:createTime>0</wpml:createTime><wpml:updateTime>0</wpml:updateTime>"]
    out += ["<wpml:missionConfig>", "<wpml:flyToWaylineMode>safely</wpml:flyToWaylineMode>",
            "<wpml:finishAction>goHome</wpml:finishAction>", "<wpml:exitOnRCLost>executeLostAction</wpml:exitOnRCLost>",
            "<wpml:executeRCLostAction>goBack</wpml:executeRCLostAction>",
            f"<wpml:takeOffSecurityHeight>{max(h, 20.0):.1f}</wpml:takeOffSecurityHeight>",
            f"<wpml:globalTransitionalSpeed>{transit:.2f}</wpml:globalTransitionalSpeed>", info,
            "</wpml:missionConfig>", "<Folder>", "<wpml:templateId>0</wpml:templateId>"]
    if template:
        out += ["<wpml:templateType>waypoint</wpml:templateType>",
                "<wpml:waylineCoordinateSysParam><wpml:coordinateMode>WGS84</wpml:coordinateMode>"
                "<wpml:heightMode>relativeToStartPoint</wpml:heightMode></wpml:waylineCoordinateSysParam>",
                f"<wpml:autoFlightSpeed>{v:.2f}</wpml:autoFlightSpeed>"]
    else:
        out += ["<wpml:executeHeightMode>relativeToStartPoint</wpml:executeHeightMode>",
                "<wpml:waylineId>0</wpml:waylineId>", f"<wpml:autoFlightSpeed>{v:.2f}</wpml:autoFlightSpeed>"]
    for k, p in enumerate(wps):
        speed = v if k % 2 == 0 else transit  # a pass from its start; the hop to the next from its end
        actions = [f"<wpml:action><wpml:actionId>0</wpml:actionId><wpml:actionActuatorFunc>gimbalRotate"
                   f"</wpml:actionActuatorFunc><wpml:actionActuatorFuncParam><wpml:gimbalPitchRotateEnable>1"
                   f"</wpml:gimbalPitchRotateEnable><wpml:gimbalPitchRotateAngle>{-plan.settings.pitch_deg:.1f}"
                   f"</wpml:gimbalPitchRotateAngle><wpml:payloadPositionIndex>0</wpml:payloadPositionIndex>"
                   f"</wpml:actionActuatorFuncParam></wpml:action>"]
        if k in (0, len(wps) - 1):
            func = "startRecord" if k == 0 else "stopRecord"
            actions.append(f"<wpml:action><wpml:actionId>1</wpml:actionId><wpml:actionActuatorFunc>{func}"
                           f"</wpml:actionActuatorFunc><wpml:actionActuatorFuncParam><wpml:payloadPositionIndex>0"
                           f"</wpml:payloadPositionIndex></wpml:actionActuatorFuncParam></wpml:action>")
        height = f"<wpml:height>{h:.2f}</wpml:height>" if template else f"<wpml:executeHeight>{h:.2f}</wpml:executeHeight>"
        out += ["<Placemark>", f"<Point><coordinates>{p['lon']:.9f},{p['lat']:.9f}</coordinates></Point>",
                f"<wpml:index>{k}</wpml:index>", height, f"<wpml:waypointSpeed>{speed:.2f}</wpml:waypointSpeed>",
                f"<wpml:waypointHeadingParam><wpml:waypointHeadingMode>fixed</wpml:waypointHeadingMode>"
                f"<wpml:waypointHeadingAngle>{((p['heading_deg'] + 180) % 360) - 180:.1f}</wpml:waypointHeadingAngle>"
                f"</wpml:waypointHeadingParam>",
                "<wpml:waypointTurnParam><wpml:waypointTurnMode>toPointAndStopWithDiscontinuityCurvature"
                "</wpml:waypointTurnMode><wpml:waypointTurnDampingDist>0</wpml:waypointTurnDampingDist>"
                "</wpml:waypointTurnParam>",
                f"<wpml:actionGroup><wpml:actionGroupId>{k}</wpml:actionGroupId><wpml:actionGroupStartIndex>{k}"
                f"</wpml:actionGroupStartIndex><wpml:actionGroupEndIndex>{k}</wpml:actionGroupEndIndex>"
                f"<wpml:actionGroupMode>sequence</wpml:actionGroupMode><wpml:actionTrigger><wpml:actionTriggerType>"
                f"reachPoint</wpml:actionTriggerType></wpml:actionTrigger>{''.join(actions)}</wpml:actionGroup>",
                f"<ExtendedData><name>{escape('row %d side %d' % (p['row'], p['side']))}</name></ExtendedData>",
                "</Placemark>"]
    out += ["</Folder>", "</Document>", "</kml>"]
    return "\n".join(x for x in out if x) + "\n"


def wpml_kmz(plan: Plan, flight: int) -> bytes:
    """DJI Pilot 2's .kmz of one flight: a zip of wpmz/template.kml and wpmz/waylines.wpml."""
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("wpmz/template.kml", _wpml_document(plan, flight, template=True))
        z.writestr("wpmz/waylines.wpml", _wpml_document(plan, flight, template=False))
    return buf.getvalue()


#: The files each flight is written as: suffix -> writer (text, or bytes).
WRITERS = {".plan": qgc_plan, ".waypoints": wpl, ".litchi.csv": litchi_csv, ".kmz": wpml_kmz}
