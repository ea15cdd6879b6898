"""``nodlidar study mirrors``: the paper's Section VI in simulation, mirrors deployed vs lifted.

Runs the paper-tracking scenario twice (same scans, nod ramp and noise seed), segments,
tracks and estimates the object's motion, then writes the figures (accumulated
motion-compensated cloud, convergence of v and heading) and the table (Markdown + CSV) to
``--out`` and prints the table. Definitions (traces, convergence) are in
:mod:`nodlidar.tracking.study`.

With ``--scene FILE`` (or a built-in scene name): the live tracker, online, on that scene,
mirrors deployed vs lifted over ``--seeds`` noise seeds (default 4): per mover the median
online convergence scan, how many seeds converged, the worst track purity, identity
switches, final errors and GOSPA (definitions in :mod:`nodlidar.tracking.evaluate`);
``--json`` prints every run's numbers and the summary as one JSON object.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ._args import add_force_arg
from ._runtime_args import add_design_arg


def register(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("--scene", default=None, metavar="TOML",
                   help="evaluate the live tracker on this scene (file or built-in name), "
                        "mirrors vs lifted over --seeds seeds (default 4)")
    p.add_argument("--json", action="store_true", help="--scene: print the results as JSON")
    p.add_argument("--robot-velocity", type=float, nargs=2, default=(0.0, 0.0),
                   metavar=("VX", "VY"),
                   help="the robot carrying the sensor drives at this world velocity [m/s] "
                        "(known pose; default standing still)")
    add_force_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import require
    from ..solver import solve
    from ..spec import load_design
    from ..tracking import study
    from ._args import check_output_path

    # each run simulates its scans up front: memory grows with --scans
    require(4 <= args.scans <= 20_000, "--scans", args.scans, "4 .. 20000")
    rv = tuple(args.robot_velocity)
    require(all(math.isfinite(v) and abs(v) <= 1.0 for v in rv), "--robot-velocity", rv,
            "two finite speeds within +-1 m/s")
    require(args.seeds >= 0, "--seeds", args.seeds, ">= 0")
    out = check_output_path(args.out, force=args.force, kind="directory")
    design = solve(load_design(args.design))
    if args.scene is not None:
        return _scene_study(args, design, out)
    ents = ("renyi", "voxel") if args.entropy == "both" else (args.entropy,)
    res = study.run_study(design, n_scans=args.scans, seed=args.seed, entropies=ents,
                          robot_velocity_m_s=rv)
    rows = study.study_table(res)
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


def _scene_study(args, design, out: Path) -> int:
    """``--scene``: the live tracker on a scene, mirrors vs lifted, over seeds."""
    import json

    from ..sim.scene import load_scene
    from ..tracking import evaluate

    scene = load_scene(args.scene)
    if not scene.movers:
        from ..errors import ParameterError

        raise ParameterError("--scene", args.scene, "a scene with at least one [[mover]]")
    seeds = range(args.seeds or 4)
    ents = ("renyi", "voxel") if args.entropy == "both" else (args.entropy,)
    runs = evaluate.compare_mirrors(design, scene, seeds, args.scans, ents)
    rows = evaluate.summary_rows(runs)
    md = evaluate.comparison_markdown(rows)
    out.mkdir(parents=True, exist_ok=True)
    head = (f"# Live tracker on scene {scene.name} ({args.scans} scans, seeds 0..{len(seeds) - 1}; "
            f"online convergence: first scan after which every estimate stays within "
            f"{evaluate.V_TOL_M_S} m/s and {evaluate.HEADING_TOL_DEG} deg)\n\n")
    (out / "scene_study.md").write_text(head + md + "\n")
    doc = {"scene": scene.name, "scans": args.scans, "seeds": list(seeds), "summary": rows,
           "runs": runs}
    (out / "scene_study.json").write_text(json.dumps(doc, indent=1) + "\n")
    if args.json:
        print(json.dumps(doc))
    else:
        print(md)
        print(f"wrote {out}/scene_study.md, scene_study.json")
    return 0
