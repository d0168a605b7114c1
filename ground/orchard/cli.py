"""The grower's commands on a finished map: `ground layout` (an orchard layout file from the map, or a check of one),
`ground choose-trees` (the trees to count by hand) and `ground load` (each tree's, row's and the flight's load from the
hand counts), each a library function's thin shell."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from ground.pipeline import GroundSettings
from pomar.settings import add_options


def _cmd_layout(args) -> int:
    from pomar.layout import layout_from_rows, read_layout, write_layout

    if args.check:
        rows = read_layout(args.check)
        print(f"{args.check}: {len(rows)} rows, fine")
        return 0
    if not args.map or not args.out:
        print("error: give a finished map's folder and --out FILE (or --check FILE)", file=sys.stderr)
        return 2
    rows = layout_from_rows(Path(args.map) / "rows.csv", args.tree_spacing_m)
    write_layout(rows, args.out)
    read_layout(args.out)  # what it wrote reads back (rows that overlap are named)
    print(f"wrote {args.out}: {len(rows)} rows, numbered as the map numbers them; check each row's number and ends, "
          "and correct them to the orchard's own")
    return 0


def _cmd_load(args) -> int:
    from ground.orchard.calibration import LOAD_COLUMNS, apply_load, check_enough, estimate_load
    from ground.orchard.size import row_kilograms
    from ground.outputs.tables import records_csv, write_atomic, write_json
    from pomar.sample_counts import read_sample_counts

    folder = Path(args.map)
    trees = _read_trees(folder, ["row", "tree", "count"] + (["coverage"] if args.load_model == "coverage" else []))
    if trees is None:
        return 2
    with open(folder / "rows.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    keys = {(t["row"], t["tree"]) for t in trees}
    samples = read_sample_counts(args.sample_counts, keys)
    check_enough(samples, args.load_model, args.sample_counts)
    load = apply_load(trees, rows, estimate_load(trees, samples, args.load_model))
    report_path = folder / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    # the kilograms carry the map scale's uncertainty, as the replay's did (ground.poses.scale)
    scale = (report.get("registration") or {}).get("georeference_scale") or {}
    row_kilograms(rows, float(scale.get("sigma_pct") or "nan") / 100.0)
    fmt = {"load": ".1f", "load_lo": ".1f", "load_hi": ".1f", "kg": ".1f", "kg_lo": ".1f", "kg_hi": ".1f"}
    write_atomic(folder / "trees.csv", records_csv(trees, [c for c in trees[0] if c not in LOAD_COLUMNS] + LOAD_COLUMNS,
                                                   fmt))
    write_atomic(folder / "rows.csv", records_csv(rows, [c for c in rows[0] if c not in fmt] + list(fmt), fmt))
    by_row = {int(r["row"]): r for r in rows}
    for r in report.get("rows", []):  # each row's load and kilograms, as rows.csv now gives them (NaN: null)
        mine = by_row.get(int(r.get("row", -1)))
        if mine is not None:
            r.update({k: float(mine[k]) if np.isfinite(mine[k]) else None for k in fmt})
    write_json(report_path, {**report, "load": load})
    fl, loo = load["flight"], load["loo"]
    print(f"load: {fl['load']:.0f} apples ({load['level']:.0%} interval {fl['load_lo']:.0f}-{fl['load_hi']:.0f}) on "
          f"{fl['trees']} trees, {fl['trees_counted']} counted by hand; the sample's leave-one-out error "
          f"{loo['median_abs_pct']:.0f} % (median), model {load['model']}")
    need, target = fl.get("trees_for_target"), fl.get("target", 0.1)
    if fl["load"] > 0 and fl["load_hi"] - fl["load"] > target * fl["load"]:
        print(f"  for an interval within {target:.0%} of the load, count about {need} trees by hand (`ground "
              f"choose-trees {folder} --trees {need} --counted {args.sample_counts} --out FILE` keeps yours)" if need else
              f"  no number of trees counted brings the interval within {target:.0%}: the trees' own scatter "
              "alone is wider")
    if load["constraints"]["held_at_0"]:
        print(f"  {load['constraints']['why']}")
    for r in rows:
        print(f"  row {r['row']}: {r['load']:.0f} ({r['load_lo']:.0f}-{r['load_hi']:.0f})")
    print(f"trees.csv and rows.csv in {folder}/ now give each tree's and row's load; report.json its 'load' and each "
          "row's")
    return 0


def _read_trees(folder: Path, need: list[str]) -> list[dict] | None:
    """A finished map's trees.csv as records (row, tree, count and coverage as numbers); None, with one line on
    stderr, where it has no trees or lacks a column in ``need`` (a map of an older version)."""
    with open(folder / "trees.csv", newline="") as f:
        trees = list(csv.DictReader(f))
    lacking = [c for c in need if trees and c not in trees[0]]
    if not trees or lacking:
        print(f"error: {folder / 'trees.csv'}: no trees" + (f" (no column {', '.join(lacking)}: a map of an older "
              "version; replay it again)" if lacking else ""), file=sys.stderr)
        return None
    for t in trees:
        t.update(row=int(t["row"]), tree=int(t["tree"]), count=int(t["count"]),
                 coverage=float(t.get("coverage") or "nan"))
    return trees


def _cmd_choose(args) -> int:
    from ground.orchard.choose import choose_trees
    from ground.outputs.tables import records_csv, write_atomic

    if args.trees < 1:
        print(f"error: --trees must be at least 1, got {args.trees}", file=sys.stderr)
        return 2
    trees = _read_trees(Path(args.map), ["row", "tree", "count", "lat", "lon", "coverage"])
    if trees is None:
        return 2
    done = {}
    if args.counted:
        from pomar.sample_counts import read_sample_counts

        done = read_sample_counts(args.counted, {(t["row"], t["tree"]) for t in trees})
        if args.trees < len(done):
            print(f"error: --trees {args.trees} is fewer than the {len(done)} trees {args.counted} has counted",
                  file=sys.stderr)
            return 2
    chosen = choose_trees(trees, args.trees, args.load_model, set(done))
    for t in chosen:
        t["apples"] = done.get((t["row"], t["tree"]), "")
    write_atomic(Path(args.out), records_csv(chosen, ["row", "tree", "apples", "lat", "lon", "count", "coverage"], {}))
    print(f"wrote {args.out}: {len(chosen)} trees to count by hand" + (f" ({len(done)} of them counted already)" if done
          else "") + ", one in every row and the rest spread over what the map saw; "
          "count every apple on each, write it in the apples column, then give the file as --sample-counts")
    for t in chosen:
        print(f"  row {t['row']} tree {t['tree']} at {t['lat']}, {t['lon']}" + (" (counted)" if t['apples'] != '' else ''))
    return 0


def _cmd_combine(args) -> int:
    from ground.orchard.combine import write_combined

    report = write_combined([Path(m) for m in args.maps], Path(args.out))
    cov = report["orchard"]["coverage"] or {}
    print(f"wrote {args.out}: {report['apples']} apples from {len(args.maps)} maps, each face of each tree from the map "
          f"that saw it best; tree coverage {cov.get('mean', float('nan')):.2f} (mean), "
          f"{cov.get('trees_both_sides', 0)} of {cov.get('trees', 0)} trees seen from both sides")
    for m in report["combined"]["maps"]:
        print(f"  {m['map']}: {m['faces_given']['left']} left and {m['faces_given']['right']} right faces, "
              f"{m['apples_given']} of its {m['apples_in_map']} apples")
    print(f"give {args.out} to `ground choose-trees` and `ground load` as one flight's map")
    return 0


def add_orchard_commands(sub) -> None:
    """The grower's commands' parsers, on `python -m ground`'s subparsers."""
    lo = sub.add_parser("layout", help="write an orchard layout file (row,start,end,tree spacing) from a finished "
                                       "map, for the grower to check and correct; or check one (--check)",
                        description=__import__("pomar.layout", fromlist=["x"]).__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    lo.add_argument("map", nargs="?", help="a finished map's folder (its rows.csv)")
    lo.add_argument("--out", help="the layout file to write (CSV)")
    lo.add_argument("--tree-spacing-m", type=float, default=1.0, help="the trees' spacing along the rows (m)")
    lo.add_argument("--check", help="read and check this layout file instead")
    lo.set_defaults(func=_cmd_layout)
    ld = sub.add_parser("load", help="each tree's, row's and the flight's load from a finished map and the trees you "
                                     "counted by hand (without replaying the flight)")
    ld.add_argument("map", help="a finished map's folder (its trees.csv and rows.csv)")
    ld.add_argument("--sample-counts", required=True, help="the trees you counted (CSV row,tree,apples, numbered as "
                                                            "the map's trees.csv)")
    add_options(ld, GroundSettings(), ["load_model"])
    ld.set_defaults(func=_cmd_load)
    ch = sub.add_parser("choose-trees", help="name the trees to count by hand, from a finished map: one in every row, "
                                             "the rest spread over what the map saw (writes the sample-count file to "
                                             "fill)")
    ch.add_argument("map", help="a finished map's folder (its trees.csv; mapped with --orchard, so that the trees' "
                                "numbers are yours)")
    ch.add_argument("--trees", type=int, default=10, help="how many trees (default 10)")
    ch.add_argument("--out", required=True, help="the sample-count file to write, its apples column empty")
    ch.add_argument("--counted", help="a sample-count file of trees counted already: kept, with their counts, among "
                                      "--trees (more trees after `ground load` asked for them)")
    add_options(ch, GroundSettings(), ["load_model"])
    ch.set_defaults(func=_cmd_choose)
    co = sub.add_parser("combine", help="several flights of one orchard as one map (a plan's split flights, or one "
                                        "flight per side): each face of each tree from the flight that saw it best",
                        description=__import__("ground.orchard.combine", fromlist=["x"]).__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    co.add_argument("maps", nargs="+", help="the finished maps' folders, each replayed with the same --orchard layout")
    co.add_argument("--out", required=True, help="the combined map's folder (rows.csv, trees.csv, apples.csv, "
                                                 "report.json)")
    co.set_defaults(func=_cmd_combine)
