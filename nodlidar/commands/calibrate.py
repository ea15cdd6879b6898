"""``nodlidar calibrate``: fit each mirror's mounting error from sweeps of a flat wall.

Paper Section IV: the direct (middle-window) beams give the wall plane of each capture;
each mirror's (dalpha, dbeta, dd) is the bounded least-squares fit that puts its reflected
beams on those planes (eq. 10). Needs >= 3 captures at distinct orientations.

  nodlidar calibrate --walls A B C [--design F] [--out calib.toml] [--json] [--plot fig.png]
  nodlidar calibrate --sim [--perturb table1] [--distance 1.0] [--yaw-deg -25 0 25]

``--walls`` takes wall captures: ``.npz`` files (steps, ranges_m, nod_rad; see
``nodlidar.calibration.walls.save_capture``) or recordings made by ``nodlidar record`` (bag
directories; the sensor nodding in front of the wall, mirrors deployed). ``--sim`` captures the walls with
the simulated sensor (embree ray tracer, finite mirrors, URG noise) built with the given
perturbations, and reports the recovered values against them.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

DEFAULT_DESIGN = "design/urg04lx-paper.toml"


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate the mirrors against a flat wall",
                       description=__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--walls", nargs="+", metavar="CAPTURE",
                     help="wall captures (.npz) or recordings (bag directories), >= 3")
    src.add_argument("--sim", action="store_true",
                     help="capture three walls with the simulated sensor")
    p.add_argument("--design", default=DEFAULT_DESIGN, help=f"design file (default {DEFAULT_DESIGN})")
    p.add_argument("--out", metavar="TOML", help="write the calibration file here")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--model", choices=("exact", "paper"), default="exact",
                   help="point model: the exact geometry (default) or the paper's eqs 4-8")
    p.add_argument("--plot", metavar="PNG", help="write a Figure-9 style plot here")
    g = p.add_argument_group("simulation (--sim)")
    g.add_argument("--perturb", choices=("table1", "none"), default="table1",
                   help="as-built mirror errors of the simulated sensor (default: paper Table I)")
    g.add_argument("--distance", type=float, default=1.0, metavar="M",
                   help="wall distance [m] (default 1.0)")
    g.add_argument("--yaw-deg", type=float, nargs="+", default=[-25.0, 0.0, 25.0],
                   help="wall orientations [deg] (default -25 0 25)")
    g.add_argument("--seed", type=int, default=0, help="noise seed")
    g.add_argument("--no-noise", action="store_true", help="exact ranges (mm rounding only)")
    p.set_defaults(func=run)


def _read_walls(paths: list[str], design) -> list:
    from ..calibration.recordings import capture_from_recording
    from ..calibration.walls import load_capture

    caps = []
    for path in paths:
        if Path(path).suffix == ".npz":
            caps.append(load_capture(path))
        else:  # a recording made by `nodlidar record`
            caps.append(capture_from_recording(path, design)[1])
    return caps


def run(args) -> int:
    import numpy as np

    from ..calibration.calfile import calibration_from_result, write_calibration
    from ..calibration.fit import calibrate
    from ..solver import solve
    from ..spec import load_design

    design = solve(load_design(args.design))
    truth = None
    if args.sim:
        from ..calibration.synthetic import WallPose, simulated_captures
        from ..paper import TABLE_I_PERTURBATIONS

        truth = dict(TABLE_I_PERTURBATIONS) if args.perturb == "table1" else {}
        walls = [WallPose(args.distance, np.radians(y)) for y in args.yaw_deg]
        captures = simulated_captures(design, truth, walls, seed=args.seed,
                                      noise=not args.no_noise)
        source = (f"simulated sensor, perturb={args.perturb}, {len(walls)} walls at "
                  f"{args.distance} m, yaw {args.yaw_deg} deg, seed {args.seed}")
    else:
        captures = _read_walls(args.walls, design)
        source = "walls: " + ", ".join(args.walls)
    result = calibrate(design, captures, model=args.model)
    cal = calibration_from_result(result, source=source)
    if args.out:
        write_calibration(args.out, cal)
    if args.plot:
        from ..calibration.plots import plot_walls

        plot_walls(result).savefig(args.plot, dpi=110)
    if args.json:
        out = {"id": cal.id, "source": source, **result.to_dict()}
        if truth is not None:
            for name, m in out["mirrors"].items():
                t = truth.get(name)
                if t is not None:
                    m["true"] = {"dalpha_rad": t.dalpha, "dbeta_rad": t.dbeta, "dd_m": t.dd}
        if args.out:
            out["file"] = args.out
        json.dump(out, sys.stdout, indent=2)
        print()
        return 0
    print(f"{design.spec.name}: calibration {cal.id} from {len(captures)} walls ({source}), "
          f"model {args.model}")
    print(f"{'mirror':6} {'dalpha mrad':>17} {'dbeta mrad':>17} {'dd mm':>15} "
          f"{'rms cm before->after':>21} {'in band':>8}" + ("   true (mrad, mrad, mm)" if truth else ""))
    for name, m in result.mirrors.items():
        p, s = m.perturbation, m.sigma
        line = (f"{name:6} {p.dalpha * 1e3:8.3f} +- {s[0] * 1e3:5.3f} {p.dbeta * 1e3:8.3f} +- "
                f"{s[1] * 1e3:5.3f} {p.dd * 1e3:7.3f} +- {s[2] * 1e3:4.3f} "
                f"{m.before.rms_m * 100:9.2f} -> {m.after.rms_m * 100:5.2f} "
                f"{m.after.within_band * 100:7.1f}%")
        if truth and name in truth:
            t = truth[name]
            line += f"   {t.dalpha * 1e3:7.1f} {t.dbeta * 1e3:7.1f} {t.dd * 1e3:6.1f}"
        if m.at_bound:
            line += f"   AT BOUND: {', '.join(m.at_bound)}"
        print(line)
    band = next(iter(result.mirrors.values())).after.band_m
    print(f"(in band: fraction of reflected points within +-{band * 100:.2f} cm of the wall after "
          "calibration; +- is 1 sigma from the Jacobian)")
    if args.out:
        print(f"wrote {args.out}")
    if args.plot:
        print(f"wrote {args.plot}")
    return 0
