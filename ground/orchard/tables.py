"""The orchard's rows and trees at one refresh: numbered by the grower's layout once the map is georeferenced, else the
map's own; what each tree's canopy showed the camera; with hand counts, each tree's and row's load; the fruit's size
per row, and the load in kilograms."""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def orchard_tables(table: dict, direction: float, snap, cams: dict, sight, growers, tree_spacing_m: float,
                   load_model: str) -> tuple[list[dict], list[dict], dict, dict | None]:
    """(rows, trees, report.json's ``orchard`` section, its ``load`` section or None) for the apples of ``table``
    (apple_table's; with a layout, each apple's row becomes its layout row, 0 outside every row) in the map ``snap``
    (ground.outputs.snapshot.MapSnapshot) with its cameras ``cams`` (pose_table's); ``sight``
    (pomar.coverage.Sight, or None: no coverage), ``growers`` (ground.orchard.files.OrchardFiles, or None)."""
    layout = growers.layout if growers is not None else None
    on_layout = table  # the apples, and the cameras, where the layout's rows are: the map shifted onto them
    if layout is not None and snap.to_enu is not None and snap.origin is not None:
        from ground.orchard.assign import OUTSIDE, apple_places, orchard_rows
        from ground.orchard.register import register_to_layout, spacing_check

        on_layout, cams, shift = register_to_layout(table, cams, layout, snap.origin)
        table["row"], rows, trees = orchard_rows(on_layout, layout, snap.origin)
        _, table["tree"], table["side"] = apple_places(on_layout, layout, snap.origin)
        on_layout["row"] = table["row"]
        info = {"numbering": "layout", "layout": str(growers.layout_path),
                "apples_outside": int((table["row"] == OUTSIDE).sum()), "layout_shift": shift,
                "row_spacing": spacing_check(shift, snap.scale_sigma_rel)}
        rs = info["row_spacing"]
        if rs is not None and not rs["agrees"] and "row_spacing" not in growers.warned:
            growers.warned.add("row_spacing")
            log.warning("%s: its rows are %.2f m apart, the map's %.2f m (+-%.2f, %.1f sigma apart): the layout, or the "
                        "map's scale, is wrong", growers.layout_path, rs["layout_m"], rs["map_m"], rs["map_sigma_m"],
                        rs["sigmas_apart"])
    else:
        from ground.orchard.map_rows import rows_summary, trees_summary

        rows = rows_summary(table, direction, snap.origin)
        trees = trees_summary(table, rows, direction, tree_spacing_m, snap.origin)
        info = {"numbering": "map", "layout": str(growers.layout_path) if layout is not None else None,
                "note": ("the map's own: the layout is applied once the map is georeferenced" if layout is not None
                         else "the map's own (no orchard layout given)")}
    info["coverage"] = None  # until the drone's camera is known
    if sight is not None and sight.camera is not None:
        from pomar.coverage import flight_coverage, row_coverage, tree_coverage

        for t, c in zip(trees, tree_coverage(trees, rows, on_layout, cams, sight)):
            t.update(c)
        row_coverage(rows, trees)
        info["coverage"] = flight_coverage(trees)
    load = None
    if growers is not None and growers.samples and info["numbering"] == "layout":
        from ground.orchard.calibration import apply_load, estimate_load

        load = apply_load(trees, rows, estimate_load(trees, growers.samples, load_model))
    from ground.orchard.size import row_sizes

    cultivars = {r.row: r.cultivar for r in layout} if info["numbering"] == "layout" else {}
    info["size"] = row_sizes(table, rows, cultivars, snap.scale_sigma_rel)
    return rows, trees, info, load
