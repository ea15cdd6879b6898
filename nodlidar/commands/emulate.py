"""``nodlidar emulate``: serve a simulated sensor (SCIP 2.0 lidar + Dynamixel bus) until Ctrl-C.

Both devices run on one simulated clock and see a ray-traced scene through the design's
mirrors; whatever a client commands the nod and mirror servos is what the scans see. Prints
the lidar and servo URLs (pty paths, or socket:// URLs with ``--tcp``) and how to connect.
"""

from __future__ import annotations

import signal
import sys
import threading

from ._runtime_args import add_design_arg


def register(sub) -> None:
    p = sub.add_parser("emulate", help="serve a simulated lidar + servo bus (pty or TCP)",
                       description=__doc__)
    add_design_arg(p)
    p.add_argument("--scene", default="room",
                   help="room | paper-tracking | wall | FILE.toml (default: room)")
    p.add_argument("--tcp", action="store_true", help="serve on TCP (socket:// URLs), not ptys")
    p.add_argument("--rate", type=float, default=1.0,
                   help="simulated seconds per wall second (default 1 = real time)")
    p.add_argument("--perturb", choices=["none", "table1"], default="none",
                   help="as-built mirror errors: table1 = the paper's Table I")
    p.add_argument("--no-noise", action="store_true", help="exact ranges (mm-rounded)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import ParameterError
    from ..paper import TABLE_I_PERTURBATIONS
    from ..sim.scene import load_scene
    from ..sim.sensor import SimulatedSensor
    from ..solver import solve
    from ..spec import load_design

    if not args.rate > 0:
        raise ParameterError("--rate", args.rate, "> 0")
    design = solve(load_design(args.design))
    perturbations = dict(TABLE_I_PERTURBATIONS) if args.perturb == "table1" else None
    sim = SimulatedSensor(design, load_scene(args.scene), perturbations=perturbations,
                          transport="tcp" if args.tcp else "pty", rate=args.rate,
                          noise=not args.no_noise, seed=args.seed)
    stop = threading.Event()

    def on_signal(signum, frame) -> None:
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with sim:
            scene = sim.scene
            print(f"simulated sensor: design {design.spec.name}, scene {scene.name!r}"
                  f" ({scene.description or 'custom'}), mirrors "
                  f"{'Table I perturbed' if perturbations else 'as designed'}, "
                  f"noise {'off' if args.no_noise else 'on'}, rate {args.rate:g}x")
            print(f"lidar URL: {sim.lidar_url}")
            print(f"servo URL: {sim.servo_url}")
            print(f"connect:   nodlidar info --port {sim.lidar_url} --servo-port {sim.servo_url}")
            print(f"           nodlidar scan --port {sim.lidar_url} --servo-port {sim.servo_url}")
            print("servos:    1 = nod (angle = head pitch), 2 = mirror_left, 3 = mirror_right "
                  "(0 deployed, pi/2 lifted); Ctrl-C to stop")
            sys.stdout.flush()
            while not stop.wait(0.2):
                pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print("stopped")
    return 0
