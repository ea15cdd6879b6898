"""``nodlidar study mirrors``: the paper's Section VI in simulation, mirrors deployed vs lifted.

Runs the paper-tracking scenario twice (same scans, nod ramp and noise seed), segments,
tracks and estimates the object's motion, then writes the figures (accumulated
motion-compensated cloud, convergence of v and heading) and the table (Markdown + CSV) to
``--out`` and prints the table. Definitions (traces, convergence) are in
:mod:`nodlidar.tracking.study`.
"""

from __future__ import annotations

import math
from pathlib import Path

from ._runtime_args import add_design_arg


def register(sub) -> None:
    p = sub.add_parser("study", help="mirror vs no-mirror tracking study (paper Section VI)",
                       description=__doc__)
    p.add_argument("which", choices=["mirrors"], help="the study to run")
    add_design_arg(p)
    p.add_argument("--out", default="study_out", help="output directory (default study_out)")
    p.add_argument("--scans", type=int, default=38, help="lidar scans per run (paper: 38)")
    p.add_argument("--entropy", choices=("voxel", "renyi", "both"), default="both")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, default=0, metavar="N",
                   help="also repeat the comparison over noise seeds 0..N-1 (convergence table)")
    p.add_argument("--robot-velocity", type=float, nargs=2, default=(0.0, 0.0),
                   metavar=("VX", "VY"),
                   help="the robot carrying the sensor drives at this world velocity [m/s] "
                        "(known pose; default standing still)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import require
    from ..solver import solve
    from ..spec import load_design
    from ..tracking import study

    require(args.scans >= 4, "--scans", args.scans, ">= 4")
    rv = tuple(args.robot_velocity)
    require(all(math.isfinite(v) and abs(v) <= 1.0 for v in rv), "--robot-velocity", rv,
            "two finite speeds within +-1 m/s")
    design = solve(load_design(args.design))
    ents = ("renyi", "voxel") if args.entropy == "both" else (args.entropy,)
    res = study.run_study(design, n_scans=args.scans, seed=args.seed, entropies=ents,
                          robot_velocity_m_s=rv)
    rows = study.study_table(res)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    md = study.table_markdown(rows)
    (out / "study_mirrors.md").write_text(
        f"# Mirror vs no-mirror study ({args.scans} scans, seed {args.seed}, robot velocity "
        f"{rv[0]:g}, {rv[1]:g} m/s; truth v = {res.truth_v_m_s} m/s, heading = "
        f"{res.truth_heading_deg} deg)\n\n{md}\n")
    (out / "study_mirrors.csv").write_text(study.table_csv(rows))
    study.plot_clouds(res).savefig(out / "accumulated_clouds.png", dpi=120)
    study.plot_convergence(res).savefig(out / "convergence.png", dpi=120)
    seg_files = []
    for c in res.configs:
        name = f"segmentation_{c.label.replace(' ', '_')}.png"
        study.plot_segmentation(c.segments, title=f"{c.label}: all {c.n_scans} scans, top view "
                                f"(precision {c.precision:.3f}, recall {c.recall:.3f})"
                                ).savefig(out / name, dpi=120)
        seg_files.append(name)
    print(md)
    print(f"convergence: first scan (counted among scans with the object) from which every "
          f"estimate stays within {study.V_TOL_M_S} m/s and {study.HEADING_TOL_DEG} deg of the truth")
    print(f"wrote {out}/study_mirrors.md, study_mirrors.csv, accumulated_clouds.png, "
          f"convergence.png, {', '.join(seg_files)}")
    if args.seeds > 0:
        sweep = study.seed_sweep(design, range(args.seeds), args.scans, ents,
                                 robot_velocity_m_s=rv)
        md2 = study.table_markdown(sweep)
        (out / "study_mirrors_seeds.md").write_text(md2 + "\n")
        (out / "study_mirrors_seeds.csv").write_text(study.table_csv(sweep))
        print(md2)
        print(f"wrote {out}/study_mirrors_seeds.md, study_mirrors_seeds.csv")
    return 0
