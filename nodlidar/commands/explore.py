"""``nodlidar explore DESIGN --sweep KEY=LO:HI:STEP [--sweep ...]``: the design space.

Solves and ray-traces every combination of the swept design-file parameters (e.g.
``--sweep layout.design_distance_m=0.5:5:0.25 --sweep placement.standoff_m=0.015:0.04:0.0025``)
and writes ``explore.csv``, ``explore.json`` and Pareto plots (``figures/``) to ``--out``:
RMS and max interleave error at D and at 1, 2 and 6 m, density gain, blocked beams, mount
footprint and glass area per design, and the Pareto front. Small sweeps run in this
process, large ones on a local Dask cluster (``--workers``) or an existing one
(``--scheduler``); the table is the same however it is run. ``nodlidar report DESIGN
--explore OUT/explore.json`` puts it into the design report.
"""

from __future__ import annotations

import argparse
import json
import sys

from ._args import add_force_arg, bounded_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("explore", help="solve and verify a sweep of designs; Pareto plots",
                       description=__doc__)
    p.add_argument("design", help="base design TOML file, e.g. design/urg04lx-paper.toml")
    p.add_argument("--sweep", action="append", required=True, metavar="KEY=LO:HI:STEP",
                   help="a design-file field and its values: LO:HI:STEP (both ends) or A,B,C; "
                        "repeat for a grid")
    p.add_argument("--out", help="output directory (default out/explore/<design name>/)")
    p.add_argument("--workers", type=bounded_int(0, 256),
                   help="0: in process; N: local Dask cluster of N workers (default: in "
                        "process up to 2000 designs)")
    p.add_argument("--scheduler", metavar="ADDR",
                   help="an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object: files written, counts and the Pareto rows")
    add_force_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..analysis.explore import Sweep, explore
    from ..analysis.tolerance import check_scheduler
    from ..errors import ParameterError
    from ..spec import load_design
    from ._args import check_output_path
    from .report import tqdm_progress

    spec = load_design(args.design)
    sweeps = [Sweep.parse(s, spec) for s in args.sweep]
    out = Path(args.out) if args.out else Path("out") / "explore" / spec.name
    if args.out:
        check_output_path(out, force=args.force, kind="directory")
    elif out.exists() and not args.force:
        raise ParameterError("--out", str(out), "a directory that does not exist yet (or "
                             "--force to overwrite it)")
    if args.scheduler is not None:
        try:  # before any work: one line within a few seconds
            check_scheduler(args.scheduler)
        except ParameterError as exc:
            raise ParameterError("--scheduler", exc.value, exc.allowed) from None
    progress, close = tqdm_progress("designs")
    try:
        res = explore(spec, sweeps, workers=args.workers, scheduler=args.scheduler,
                      progress=progress)
    except ParameterError as exc:
        if exc.field != "scheduler":
            raise
        raise ParameterError("--scheduler", exc.value, exc.allowed) from None
    finally:
        close()
    out.mkdir(parents=True, exist_ok=True)
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    csv_path = res.write_csv(out / "explore.csv")
    json_path = res.write_json(out / "explore.json")
    figs = []
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy: only when plots are written)

    for stem, _, fig in res.figures():
        path = fig_dir / f"{stem}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        figs.append(path)
    front = [r for r in res.rows if r["pareto"]]
    front.sort(key=lambda r: r["rms_error_deg"])
    if args.json:
        from ..analysis.explore import nan_to_none

        json.dump(nan_to_none({"csv": str(csv_path), "json": str(json_path),
                                "figures": [str(f) for f in figs], "n_designs": res.n_designs,
                                "n_feasible": res.n_feasible, "pareto": front}),
                  sys.stdout, indent=2)
        print()
        return 0
    keys = [s.key for s in sweeps]
    print(f"{spec.name}: {res.n_designs} designs, {res.n_feasible} feasible, "
          f"{len(front)} on the Pareto front (RMS error at D, footprint, glass down; density up)")
    head = "  ".join(f"{k:>26}" for k in keys) + (f"  {'rms D deg':>9}  {'max D deg':>9}  "
                                                   f"{'rms 6m':>7}  {'density':>7}  "
                                                   f"{'footprint mm':>13}  {'glass cm2':>9}")
    print(head)
    for r in front:
        print("  ".join(f"{r[k]:>26g}" for k in keys)
              + f"  {r['rms_error_deg']:9.4f}  {r['max_error_deg']:9.4f}  "
                f"{r['rms_error_6m_deg']:7.4f}  {r['density_gain']:7.3f}  "
                f"{r['footprint_w_mm']:6.0f}x{r['footprint_d_mm']:<6.0f}  "
                f"{r['glass_area_cm2']:9.2f}")
    print(f"wrote {csv_path}\nwrote {json_path}\nwrote {len(figs)} Pareto plots in {fig_dir}")
    return 0
