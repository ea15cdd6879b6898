"""``nodlidar drift DESIGN``: where each mirror's first and last beam land at several ranges.

The mirrors interleave the reflected beams with the direct ones exactly on the arc of
radius D only; this prints the actual bearing (exact ray trace) of every mirror's first
and last beam on arcs of the given radii (paper eq. 1, Figs 6-7).
"""

from __future__ import annotations

import argparse
import json
import sys

#: Largest arc radius [m]: far beyond any lidar's range, and refuses 1e308 (inf bearings).
MAX_RANGE_M = 1000.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("drift", help="bearing of each mirror's first/last beam vs range",
                       description=__doc__)
    p.add_argument("design", help="design TOML file, e.g. design/urg04lx-paper.toml")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--ranges", type=float, nargs="+", default=[0.4, 1.0, 2.0, 6.0],
                   metavar="M", help=f"arc radii [m], 0 < R <= {MAX_RANGE_M:g} "
                                     "(default: 0.4 1 2 6)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..analysis.drift import bearing_drift
    from ..solver import solve
    from ..spec import load_design
    from ..validation import check_number

    # checked here, not by argparse, so that main() returns 2 (in-process callers)
    for r in args.ranges:
        check_number(r, "--ranges", lo=0, hi=MAX_RANGE_M, lo_open=True, unit="m")
    spec = load_design(args.design)
    design = solve(spec)
    result = bearing_drift(design, args.ranges)
    rows = result.first_last_table()
    if args.json:
        json.dump({"name": spec.name, "design_distance_m": result.design_distance_m,
                   "ranges_m": [float(r) for r in result.ranges_m],
                   "eq1_max_difference_rad": result.max_closed_vs_trace,
                   "mirrors": rows}, sys.stdout, indent=2)
        print()
        return 0
    print(f"{spec.name}: actual bearing [deg] of each mirror's first and last beam where it "
          f"crosses an arc of radius R (exact trace; D = {result.design_distance_m} m)")
    head = f"{'mirror':6} {'beam':>5} {'step':>5} {'target':>9} " + " ".join(
        f"{'R=' + format(r, 'g') + ' m':>10}" for r in result.ranges_m)
    print(head)
    print("-" * len(head))
    for row in rows:
        for key in ("first", "last"):
            b = row[key]
            print(f"{row['name']:6} {key:>5} {b['step']:>5} {b['target_bearing_deg']:9.4f} "
                  + " ".join(f"{x:10.4f}" for x in b["bearing_deg"]))
    print(f"eq. 1 agrees with the trace to {result.max_closed_vs_trace:.1e} rad")
    return 0
