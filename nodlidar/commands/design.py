"""``nodlidar design FILE``: solve a design file, verify it by ray trace, print the mirrors."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from ._args import add_force_arg

if TYPE_CHECKING:
    from ..solver import Design


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("design", help="solve and verify a design file; print the mirror table",
                       description=__doc__)
    p.add_argument("design", help="design TOML file, e.g. design/urg04lx-paper.toml")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--method", choices=("anchor", "optimal"),
                   help="override placement.method from the file")
    p.add_argument("--out", help="also write design.json and the resolved TOML here")
    add_force_arg(p)
    p.set_defaults(func=run)


def _fmt_table(rows: list[dict]) -> str:
    head = (f"{'mirror':6} {'steps':>9} {'beams':>5} {'span cm':>8} {'len cm':>7} {'phi deg':>8} "
            f"{'OA mm':>7} {'OZ mm':>7} {'d mm':>7} {'rms deg':>8} {'max deg':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['name']:6} {r['steps'][0]:>4}..{r['steps'][1]:<4}{r['beams']:>5} "
            f"{r['beam_span_m'] * 100:8.4f} {r['length_m'] * 100:7.3f} {r['phi_deg']:8.4f} "
            f"{r['oa_m'] * 1000:7.2f} {r['oz_m'] * 1000:7.2f} {r['standoff_m'] * 1000:7.2f} "
            f"{r['rms_error_deg']:8.4f} {r['max_error_deg']:8.4f}")
    return "\n".join(lines)


def main_table(design: Design) -> str:
    """The mirror table of a solved design, as printed by ``nodlidar design``."""
    from ..designio import mirror_table

    return _fmt_table(mirror_table(design))


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..designio import mirror_table, paper_comparison
    from ..errors import InfeasibleDesignError
    from ..solver import solve
    from ..spec import design_to_toml, load_design
    from ..verify import verify

    spec = load_design(args.design)
    if args.out:  # the one overwrite policy: design.json is new or --force
        from ._args import check_output_path

        d = Path(args.out)
        if d.exists():
            check_output_path(d / "design.json", force=args.force)
    if args.method:
        spec = spec.replace(**{"placement.method": args.method})
    other_method = "optimal" if spec.placement.method == "anchor" else "anchor"
    design = solve(spec)
    try:
        alt = solve(spec.replace(**{"placement.method": other_method}))
        alt_mirrors, alt_refused = mirror_table(alt), None
    except InfeasibleDesignError as exc:
        # the alternative is for comparison only; its refusal must not hide the design
        alt_mirrors, alt_refused = [], str(exc)
    out: dict[str, Any] = {
        "name": spec.name,
        "lidar": spec.lidar,
        "design_distance_m": spec.layout.design_distance_m,
        "windows": spec.layout.windows,
        "method": spec.placement.method,
        "direct_steps": [int(design.direct_steps[0]), int(design.direct_steps[-1])],
        "mirrors": mirror_table(design),
        "paper_comparison": paper_comparison(design),
        "alternative": {"method": other_method, "mirrors": alt_mirrors},
    }
    if alt_refused:
        out["alternative"]["refused"] = alt_refused
    # beams the file gives up (placement.shadowed_steps), described as the trace finds them
    ver = verify(design)
    out["shadowed"] = ver.describe_blocked()
    # what the split buys: beams per degree across the front window at D (traced), and
    # which mirror fills each interleave slot
    out["density_gain"] = ver.density_gain()
    out["density_per_degree"] = ver.density_per_degree()
    out["interleave"] = ver.interleave_pattern()
    if args.out:
        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "design.json").write_text(json.dumps(out, indent=2))
        (d / f"{spec.name}.toml").write_text(design_to_toml(spec))
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        print()
        return 0
    blocked = ("none blocked" if not out["shadowed"] else
               f"shadowed as the file declares: {out['shadowed']}")
    print(f"{spec.name}: {spec.lidar}, D = {spec.layout.design_distance_m} m, "
          f"k = {spec.layout.windows}, placement = {spec.placement.method}; direct steps "
          f"{out['direct_steps'][0]}..{out['direct_steps'][1]}; every beam ray-traced, {blocked}")
    print(_fmt_table(out["mirrors"]))
    print(f"density across the front window at D: {out['density_gain']:.3f} x the bare lidar; "
          "interleave (direct step: slots):")
    for r in out["interleave"]:
        print(f"  {r['steps'][0]:>4}..{r['steps'][1]:<4} {' '.join(r['slots'])}")
    print("span = distance between the first and last beam's hit points (the paper's QZ); "
          "len = mirror patch incl. half-step margins;\nrms/max = bearing error against the "
          "interleave target on the arc of radius D (exact ray trace).")
    if out["paper_comparison"]:
        print("\nagainst the paper (Section III):")
        for r in out["paper_comparison"]:
            print(f"  {r['quantity']:14} paper {r['paper']:10.6g}  ours {r['ours']:10.6g}  "
                  f"diff {r['difference']:+.4g} ({r['relative'] * 100:+.2f} %)")
    print(f"\nside by side, placement = {other_method}:")
    if alt_refused:
        print(f"  refused: {alt_refused}")
    else:
        print(_fmt_table(out["alternative"]["mirrors"]))
    if args.out:
        print(f"\nwrote {Path(args.out) / 'design.json'}")
    return 0
