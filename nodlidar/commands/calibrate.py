"""``nodlidar calibrate``: fit each mirror's mounting error from sweeps of a flat wall.

Paper Section IV: the direct (middle-window) beams give the wall plane of each capture;
each mirror's (dalpha, dbeta, dd) is the bounded least-squares fit that puts its reflected
beams on those planes (eq. 10). Needs >= 3 captures at distinct orientations.

  nodlidar calibrate --walls A B C [--design F] [--out calib.toml] [--json] [--plot fig.png]
  nodlidar calibrate --sim [--perturb table1] [--distance 1.0] [--yaw-deg -25 0 25]
  nodlidar calibrate --sim --scene design/scenes/calib-doorway.toml [--yaw-deg -25 0 25]
  nodlidar calibrate --live [--port URL --servo-port URL] [--orientations 3] [--yes]

``--walls`` takes wall captures: ``.npz`` files (steps, ranges_m, nod_rad; see
``nodlidar.calibration.walls.save_capture``) or recordings made by ``nodlidar record`` (bag
directories; the sensor nodding in front of the wall, mirrors deployed). ``--sim`` captures the walls with
the simulated sensor (embree ray tracer, finite mirrors, URG noise) built with the given
perturbations, and reports the recovered values against them; with ``--scene`` it captures
that scene (a wall with a doorway, furniture...) with the sensor turned to each ``--yaw-deg``.

The fit is robust to clutter (doorways, furniture, a second wall: rejected as outliers by
the lidar's noise model) and checked by quality gates after it. If any gate fails, each
problem is printed on stderr (one line, naming the capture or mirror and what to do), no
calibration file is written and the exit status is 2; ``--force`` writes it anyway (the
problems are recorded in the file) and the exit status is still 2. An existing ``--out``
is refused unless ``--force``.

``--fit-range-offset`` / ``--fit-range-scale`` also fit the lidar's range offset and scale
(the scale needs ``--wall-distance-m``: the measured distance of each wall from the sensor,
``nan`` where not measured).

``--live`` guides a capture on the device: for each orientation it asks you (on stderr) to
face the sensor to the wall at a new angle and press Enter (``--yes``: don't wait), then
runs one nod sweep with the mirrors deployed. Without ``--port``/``--servo-port`` the
simulated sensor stands in, facing a wall at each ``--distance``/``--yaw-deg`` in turn.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from ._args import bounded_float, bounded_int, check_output_path
from ._runtime_args import add_design_arg

#: Wall orientations the simulated captures accept [deg] (WallPose: |yaw| < 60 deg).
YAW_MAX_DEG = 59.9
#: Most orientations a guided capture asks for (each is a sweep of a few seconds).
ORIENTATIONS_MAX = 12


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate the mirrors against a flat wall",
                       description=__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--walls", nargs="+", metavar="CAPTURE",
                     help="wall captures (.npz) or recordings (bag directories), >= 3")
    src.add_argument("--sim", action="store_true",
                     help="capture three walls with the simulated sensor")
    src.add_argument("--live", action="store_true",
                     help="guided capture: one nod sweep per wall orientation, on the device "
                          "(--port/--servo-port) or the simulated sensor")
    add_design_arg(p)
    p.add_argument("--out", metavar="TOML", help="write the calibration file here")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing --out, and write it even when a quality gate "
                        "fails (the problems are recorded in the file)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--model", choices=("exact", "paper"), default="exact",
                   help="point model: the exact geometry (default) or the paper's eqs 4-8")
    p.add_argument("--plot", metavar="PNG", help="write a Figure-9 style plot here")
    p.add_argument("--fit-range-offset", action="store_true",
                   help="also fit the lidar's range offset")
    p.add_argument("--fit-range-scale", action="store_true",
                   help="also fit the lidar's range scale (needs --wall-distance-m)")
    p.add_argument("--wall-distance-m", type=float, nargs="+", default=None, metavar="M",
                   help="measured distance of each capture's wall from the sensor [m], one per "
                        "capture, nan where not measured (+-3 mm)")
    g = p.add_argument_group("simulation (--sim)")
    g.add_argument("--perturb", choices=("table1", "none"), default="table1",
                   help="as-built mirror errors of the simulated sensor (default: paper Table I)")
    g.add_argument("--scene", metavar="TOML", default=None,
                   help="capture this scene (design/scenes/calib-*.toml), the sensor turned to "
                        "each --yaw-deg, instead of a lone wall at --distance")
    g.add_argument("--distance", type=bounded_float(0.0, 20.0, lo_open=True, unit="m"), nargs="+",
                   default=[1.0], metavar="M",
                   help="wall distance [m]: one for all walls or one per --yaw-deg (default 1.0)")
    g.add_argument("--yaw-deg", type=bounded_float(-YAW_MAX_DEG, YAW_MAX_DEG, unit="deg"),
                   nargs="+", default=[-25.0, 0.0, 25.0],
                   help="wall orientations [deg] (default -25 0 25)")
    g.add_argument("--seed", type=int, default=0, help="noise seed")
    g.add_argument("--no-noise", action="store_true", help="exact ranges (mm rounding only)")
    g.add_argument("--sim-range-offset-mm", type=bounded_float(-100.0, 100.0, unit="mm"),
                   default=0.0, help="the simulated lidar's range offset [mm] (default 0)")
    g.add_argument("--sim-range-scale-pct", type=bounded_float(-5.0, 5.0, unit="%"),
                   default=0.0, help="the simulated lidar's range scale error [%%] (default 0)")
    lv = p.add_argument_group("live capture (--live)")
    lv.add_argument("--port", metavar="URL", default=None,
                    help="lidar port (default: the simulated sensor; --sim options apply)")
    lv.add_argument("--servo-port", metavar="URL", default=None, help="Dynamixel bus port")
    lv.add_argument("--orientations", type=bounded_int(3, ORIENTATIONS_MAX), default=None,
                    metavar="N",
                    help="wall orientations to capture on the device (default 3; the simulated "
                         "sensor captures one per --yaw-deg)")
    lv.add_argument("--yes", action="store_true", help="don't wait for Enter between captures")
    lv.add_argument("--sim-rate", type=float, default=1.0, metavar="X",
                    help="simulated sensor: simulated seconds per wall second")
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


def _sim_walls(args) -> list:
    import numpy as np  # here, not at module level: --help imports no numpy

    from ..calibration.synthetic import WallPose
    from ..errors import ParameterError

    d = list(args.distance)
    if len(d) == 1:
        d = d * len(args.yaw_deg)
    if len(d) != len(args.yaw_deg):
        raise ParameterError("--distance", args.distance,
                             f"one distance or one per --yaw-deg ({len(args.yaw_deg)})")
    return [WallPose(di, np.radians(y)) for di, y in zip(d, args.yaw_deg)]


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _ask(prompt: str, wait: bool) -> None:
    """Print a guided-capture prompt on stderr and wait for Enter (EOF cancels)."""
    from ..errors import CalibrationError

    print(prompt, file=sys.stderr, flush=True)
    if wait and sys.stdin.readline() == "":
        raise CalibrationError("calibration cancelled: no answer on stdin (use --yes to capture "
                               "without waiting)")


def _live_captures(args, design, truth) -> tuple[list, str]:
    """Guided capture: one nod sweep per wall orientation (device, or the simulated sensor)."""
    import numpy as np  # here, not at module level: --help imports no numpy

    from ..calibration.recordings import capture_from_capture
    from ..errors import require
    from ..runtime.session import Session

    require(args.sim_rate > 0, "--sim-rate", args.sim_rate, "> 0")
    caps = []  # (--port without --servo-port is refused by the Session)

    def sweep(session, k: int, n: int) -> None:
        cap = session.sweep()
        caps.append(capture_from_capture(design, cap, name=f"orientation {k + 1}"))
        print(f"  orientation {k + 1}/{n}: {len(cap.scans)} scans, {len(caps[-1])} beams",
              file=sys.stderr, flush=True)

    if args.port is not None:  # the device: one session, the user turns the sensor
        n = 3 if args.orientations is None else args.orientations
        with Session(args.design, port=args.port, servo_port=args.servo_port, log=_log) as s:
            for k in range(n):
                _ask(f"[{k + 1}/{n}] face the sensor to a flat wall"
                     + (" at a clearly different angle (>= 10 deg) than before" if k else "")
                     + ", the wall filling the middle and both mirror windows; press Enter to "
                       "nod once", not args.yes)
                sweep(s, k, n)
        return caps, f"live: {args.port} + {args.servo_port}, {n} orientations"
    from ..sim.scene import wall_scene

    walls = _sim_walls(args)
    n = len(walls)
    # the simulated sensor faces one wall per --yaw-deg: a different --orientations cannot
    # be honoured, so it is refused rather than ignored (issue 15)
    require(args.orientations is None or args.orientations == n, "--orientations",
            args.orientations, f"{n} (the simulated sensor captures one orientation per "
            f"--yaw-deg; give {args.orientations} --yaw-deg values to capture that many)")
    for k, w in enumerate(walls):
        _ask(f"[{k + 1}/{n}] simulated sensor: facing a wall {w.distance_m:g} m away, turned "
             f"{np.degrees(w.yaw_rad):+.0f} deg; press Enter to nod once", not args.yes)
        with Session(args.design, scene=wall_scene(w.distance_m, w.yaw_rad),
                     sim_rate=args.sim_rate, noise=not args.no_noise, seed=args.seed * 100 + k,
                     sim_perturbations=truth or None, log=_log) as s:
            sweep(s, k, n)
    return caps, (f"live simulated sensor, perturb={args.perturb}, walls "
                  + ", ".join(f"{w.distance_m:g} m/{np.degrees(w.yaw_rad):+.0f} deg" for w in walls))


def _check_options(args) -> None:
    """Refuse option combinations that cannot be honoured, before any capture."""
    from ..errors import ParameterError

    if args.orientations is not None and not args.live:
        raise ParameterError("--orientations", args.orientations, "only with --live")
    if args.scene is not None and not args.sim:
        raise ParameterError("--scene", args.scene, "only with --sim")
    if args.fit_range_scale and not args.wall_distance_m:
        raise ParameterError("--fit-range-scale", True,
                             "with --wall-distance-m (walls alone do not determine the lidar's "
                             "range scale: a uniformly scaled room looks the same)")
    for v in args.wall_distance_m or []:
        if not (math.isnan(v) or 0 < v <= 20):
            raise ParameterError("--wall-distance-m", v, "a distance in 0 .. 20 m, or nan")
    if (args.model == "paper") and (args.fit_range_offset or args.fit_range_scale):
        raise ParameterError("--model", "paper", "exact with --fit-range-offset/--fit-range-scale")


def run(args: argparse.Namespace) -> int:
    import numpy as np  # here, not at module level: --help imports no numpy

    from ..calibration.calfile import calibration_from_result, write_calibration
    from ..calibration.fit import calibrate
    from ..calibration.synthetic import with_range_error
    from ..errors import CalibrationError, ParameterError
    from ..solver import solve
    from ..spec import load_design

    _check_options(args)
    if args.out:
        check_output_path(args.out, force=args.force, option="--out")
    if args.plot:
        from ..calibration.plots import plot_formats

        kinds = plot_formats()  # checked before the fit, not by a traceback after it
        if Path(args.plot).suffix.lower().lstrip(".") not in kinds:
            raise ParameterError("--plot", args.plot, "a file name ending in ." + ", .".join(kinds))
        check_output_path(args.plot, force=args.force, option="--plot")
    design = solve(load_design(args.design))
    truth = None
    if args.sim or (args.live and args.port is None):
        from ..paper import TABLE_I_PERTURBATIONS

        truth = dict(TABLE_I_PERTURBATIONS) if args.perturb == "table1" else {}
    if args.sim:
        from ..calibration.synthetic import scene_captures, simulated_captures

        if args.scene is not None:
            from ..sim.scene import load_scene

            scene = load_scene(args.scene)
            captures = scene_captures(design, scene, np.radians(args.yaw_deg), truth,
                                      seed=args.seed, noise=not args.no_noise)
            source = (f"simulated sensor, perturb={args.perturb}, scene {args.scene}, yaw "
                      f"{args.yaw_deg} deg, seed {args.seed}")
        else:
            walls = _sim_walls(args)
            captures = simulated_captures(design, truth, walls, seed=args.seed,
                                          noise=not args.no_noise)
            source = (f"simulated sensor, perturb={args.perturb}, {len(walls)} walls at "
                      f"{[w.distance_m for w in walls]} m, yaw {args.yaw_deg} deg, seed {args.seed}")
        if args.sim_range_offset_mm or args.sim_range_scale_pct:
            captures = [with_range_error(c, args.sim_range_offset_mm * 1e-3,
                                         args.sim_range_scale_pct * 1e-2) for c in captures]
            source += (f", range error {args.sim_range_offset_mm:g} mm "
                       f"{args.sim_range_scale_pct:+g} %")
    elif args.live:
        captures, source = _live_captures(args, design, truth)
    else:
        captures = _read_walls(args.walls, design)
        source = "walls: " + ", ".join(args.walls)
    known = None
    if args.wall_distance_m:
        if len(args.wall_distance_m) != len(captures):
            raise ParameterError("--wall-distance-m", args.wall_distance_m,
                                 f"one per capture ({len(captures)}; nan where not measured)")
        known = [None if math.isnan(v) else v for v in args.wall_distance_m]
    intr = tuple(n for n, on in (("range_offset_m", args.fit_range_offset),
                                 ("range_scale", args.fit_range_scale)) if on)
    try:
        result = calibrate(design, captures, model=args.model, intrinsics=intr,
                           known_distances_m=known)
    except CalibrationError as exc:
        # one line per problem (a refusal can name several captures)
        lines = str(exc).splitlines()
        for line in lines[:-1]:
            print(f"nodlidar calibrate: {line}", file=sys.stderr)
        raise CalibrationError(lines[-1]) from None
    cal = calibration_from_result(result, source=source)
    write = args.out and (result.ok or args.force)
    if write:
        write_calibration(args.out, cal)
    if args.plot:
        from ..calibration.plots import plot_walls

        plot_walls(result).savefig(args.plot, dpi=110)
    for line in result.problems:
        print(f"nodlidar calibrate: {line}", file=sys.stderr)
    if result.problems:
        print("nodlidar calibrate: " + (f"wrote {args.out} anyway (--force)" if write else
                                        "no calibration file written (--force writes it anyway)"),
              file=sys.stderr)
    # --force writes the file (problems recorded in it) but never turns a failed gate into
    # success: the exit status still says the calibration is not vouched for
    status = 0 if result.ok else 2
    if args.json:
        out = {"id": cal.id, "source": source, **result.to_dict()}
        if truth is not None:
            for name, m in out["mirrors"].items():
                t = truth.get(name)
                if t is not None:
                    m["true"] = {"dalpha_rad": t.dalpha, "dbeta_rad": t.dbeta, "dd_m": t.dd}
        if args.out:
            out["file"] = args.out
        out["written"] = bool(write)
        json.dump(out, sys.stdout, indent=2)
        print()
        return status
    print(f"{design.spec.name}: calibration {cal.id} from {len(captures)} walls ({source}), "
          f"model {args.model}")
    print(f"{'wall':24} {'distance m':>10} {'on plane':>9} {'plane rms mm':>13} {'x noise':>8}")
    for c in result.captures:
        print(f"{c.name[:24]:24} {c.distance_m:10.3f} {c.inlier_share * 100:8.1f}% "
              f"{c.plane.rms_m * 1e3:13.2f} {c.plane.rms_m / c.expected_rms_m:8.2f}")
    print(f"{'mirror':6} {'dalpha mrad':>17} {'dbeta mrad':>17} {'dd mm':>15} "
          f"{'rms cm before->after':>21} {'in band':>8} {'used':>6}"
          + ("   true (mrad, mrad, mm)" if truth else ""))
    for name, m in result.mirrors.items():
        p, s = m.perturbation, m.sigma
        line = (f"{name:6} {p.dalpha * 1e3:8.3f} +- {s[0] * 1e3:5.3f} {p.dbeta * 1e3:8.3f} +- "
                f"{s[1] * 1e3:5.3f} {p.dd * 1e3:7.3f} +- {s[2] * 1e3:4.3f} "
                f"{m.before.rms_m * 100:9.2f} -> {m.after.rms_m * 100:5.2f} "
                f"{m.after.within_band * 100:7.1f}% {m.used_share * 100:5.1f}%")
        if truth and name in truth:
            t = truth[name]
            line += f"   {t.dalpha * 1e3:7.1f} {t.dbeta * 1e3:7.1f} {t.dd * 1e3:6.1f}"
        if m.at_bound:
            line += f"   AT BOUND: {', '.join(m.at_bound)}"
        print(line)
    if result.intrinsics:
        it = result.intrinsics
        parts = [f"range offset {it['range_offset_m'] * 1e3:.2f}"
                 + (f" +- {it['sigma_range_offset_m'] * 1e3:.2f}" if "sigma_range_offset_m" in it
                    else "") + " mm",
                 f"range scale {it['range_scale'] * 100:+.3f}"
                 + (f" +- {it['sigma_range_scale'] * 100:.3f}" if "sigma_range_scale" in it
                    else "") + " %"]
        print("lidar: " + ", ".join(parts))
    band = next(iter(result.mirrors.values())).after.band_m
    print(f"(in band: fraction of reflected points within +-{band * 100:.2f} cm of the wall after "
          "calibration; used: near-wall points kept by the noise gate; +- is 1 sigma of the "
          "joint fit)")
    print(f"{len(result.ambiguous_steps)} ambiguous beams (mirror changes within "
          "3 sigma) listed in the calibration file; the runtime drops them")
    if write:
        print(f"wrote {args.out}")
    if args.plot:
        print(f"wrote {args.plot}")
    return status
