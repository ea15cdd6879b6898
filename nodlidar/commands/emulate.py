"""``nodlidar emulate``: serve a simulated sensor (SCIP 2.0 lidar + Dynamixel bus) until Ctrl-C.

Both devices run on one simulated clock and see a ray-traced scene through the design's
mirrors; whatever a client commands the nod and mirror servos is what the scans see. Prints
the lidar and servo URLs (pty paths, or socket:// URLs with ``--tcp``) and how to connect;
``--json`` prints them as one JSON object instead. Over TCP both servers listen on
loopback unless ``--host`` says otherwise, on free ports unless ``--port`` /
``--servo-port`` fix them. ``--scip1`` boots the lidar in SCIP 1.1 mode, as a URG-04LX
fresh from the factory (clients switch it with ``SCIP2.0``).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from ._args import bounded_float, bounded_int
from ._runtime_args import add_design_arg

MAX_RATE = 1000.0  # simulated seconds per wall second: beyond, scans come faster than any host reads


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("emulate", help="serve a simulated lidar + servo bus (pty or TCP)",
                       description=__doc__)
    add_design_arg(p)
    p.add_argument("--scene", default="room",
                   help="room | paper-tracking | wall | FILE.toml (default: room)")
    p.add_argument("--tcp", action="store_true", help="serve on TCP (socket:// URLs), not ptys")
    p.add_argument("--host", default=None, metavar="ADDR",
                   help="with --tcp: address to listen on (default 127.0.0.1, loopback only)")
    p.add_argument("--port", type=bounded_int(1, 65535), default=None, metavar="N",
                   help="with --tcp: the lidar's TCP port (default: any free port)")
    p.add_argument("--servo-port", type=bounded_int(1, 65535), default=None, metavar="N",
                   help="with --tcp: the servo bus's TCP port (default: any free port)")
    p.add_argument("--rate", type=bounded_float(0.0, MAX_RATE, lo_open=True), default=1.0,
                   help=f"simulated seconds per wall second, up to {MAX_RATE:g} "
                        "(default 1 = real time)")
    p.add_argument("--perturb", choices=["none", "table1"], default="none",
                   help="as-built mirror errors: table1 = the paper's Table I")
    p.add_argument("--no-noise", action="store_true", help="exact ranges (mm-rounded)")
    p.add_argument("--seed", type=bounded_int(0, 2**32 - 1), default=0,
                   help="noise seed (default 0)")
    p.add_argument("--scip1", action="store_true",
                   help="boot the lidar in SCIP 1.1 mode (clients send SCIP2.0 first)")
    p.add_argument("--json", action="store_true",
                   help="print the URLs and settings as one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from ..errors import ParameterError
    from ..paper import TABLE_I_PERTURBATIONS
    from ..sim.scene import load_scene
    from ..sim.sensor import SimulatedSensor
    from ..solver import solve
    from ..spec import load_design

    if not args.tcp:
        for opt, v in (("--host", args.host), ("--port", args.port),
                       ("--servo-port", args.servo_port)):
            if v is not None:
                raise ParameterError(opt, v, "only with --tcp (pty ports have no address)")
    if args.port is not None and args.port == args.servo_port:
        raise ParameterError("--servo-port", args.servo_port, f"a port other than --port {args.port}")
    design = solve(load_design(args.design))
    perturbations = dict(TABLE_I_PERTURBATIONS) if args.perturb == "table1" else None
    sim = SimulatedSensor(design, load_scene(args.scene), perturbations=perturbations,
                          transport="tcp" if args.tcp else "pty", rate=args.rate,
                          noise=not args.no_noise, seed=args.seed,
                          host=args.host or "127.0.0.1", lidar_port=args.port or 0,
                          servo_port=args.servo_port or 0, scip1=args.scip1)
    stop = threading.Event()

    def on_signal(signum, frame) -> None:
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with sim:
            scene = sim.scene
            if args.json:
                print(json.dumps({
                    "lidar_url": sim.lidar_url, "servo_url": sim.servo_url,
                    "transport": sim.transport, "design": design.spec.name,
                    "scene": scene.name, "perturbed": bool(perturbations),
                    "noise": not args.no_noise, "seed": args.seed, "rate": args.rate,
                    "scip": "1.1" if args.scip1 else "2.0",
                    "servos": {"nod": 1, "mirror_left": 2, "mirror_right": 3},
                    # each lift servo's deployed / lifted angle [rad], from the design
                    "lift": {j: {"deployed_rad": p.deployed_rad, "lifted_rad": p.lifted_rad}
                             for j, p in sim.lift.items()}}))
            else:
                print(f"simulated sensor: design {design.spec.name}, scene {scene.name!r}"
                      f" ({scene.description or 'custom'}), mirrors "
                      f"{'Table I perturbed' if perturbations else 'as designed'}, "
                      f"noise {'off' if args.no_noise else 'on'}, rate {args.rate:g}x"
                      f"{', SCIP 1.1 at boot' if args.scip1 else ''}")
                print(f"lidar URL: {sim.lidar_url}")
                print(f"servo URL: {sim.servo_url}")
                print(f"connect:   nodlidar info --port {sim.lidar_url} --servo-port {sim.servo_url}")
                print(f"           nodlidar scan --port {sim.lidar_url} --servo-port {sim.servo_url}")
                lo, ro = sim.lift["mirror_left"], sim.lift["mirror_right"]
                print("servos:    1 = nod (angle = head pitch), 2 = mirror_left, 3 = mirror_right "
                      f"(deployed {lo.deployed_rad:g} / {ro.deployed_rad:g} rad, lifted "
                      f"{lo.lifted_rad:+.4f} / {ro.lifted_rad:+.4f} rad); Ctrl-C to stop")
            sys.stdout.flush()
            while not stop.wait(0.2):
                pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if not args.json:
        print("stopped")
    return 0
