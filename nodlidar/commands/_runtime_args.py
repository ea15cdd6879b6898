"""Options shared by the runtime commands (info, scan, record, replay)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError

#: Shown in help texts for the default design (:data:`nodlidar.paper.PAPER_DESIGN`).
DESIGN_HELP = "design file (default: the paper's build, design/urg04lx-paper.toml)"


def add_design_arg(p) -> None:
    """``--design TOML``, defaulting to the paper's build wherever the command runs."""
    from ..paper import PAPER_DESIGN

    p.add_argument("--design", metavar="TOML", default=str(PAPER_DESIGN), help=DESIGN_HELP)


def add_device_args(p, *, design: bool = True, scene: str | None = None) -> None:
    """--design, --port, --servo-port, --calibration and the simulated-sensor options
    (``scene``: the simulated sensor's default scene, ``room`` if None)."""
    if design:
        add_design_arg(p)
        p.add_argument("--calibration", metavar="TOML", default=None,
                       help="calibration file of this design (mirror perturbations)")
    p.add_argument("--port", metavar="URL", default=None,
                   help="lidar port: device path or socket://host:port "
                        "(default: the built-in simulated sensor)")
    p.add_argument("--servo-port", metavar="URL", default=None,
                   help="Dynamixel bus port (default: the built-in simulated sensor)")
    p.add_argument("--sim-rate", type=float, default=1.0, metavar="X",
                   help="simulated sensor: simulated seconds per wall second (e.g. 5)")
    p.add_argument("--sim-transport", choices=("pty", "tcp"), default="pty",
                   help="simulated sensor: serve over pseudo-terminals or TCP (default pty)")
    p.add_argument("--scene", default=scene,
                   help=f"simulated sensor: scene name or TOML (default {scene or 'room'})")
    p.add_argument("--no-noise", action="store_true", help="simulated sensor: no range noise")
    p.add_argument("--perturb", choices=("none", "table1"), default="none",
                   help="simulated sensor: as-built mirror errors (table1 = the paper's Table I; "
                        "default none = built exactly as designed)")


def _stderr(msg: str) -> None:
    from ._output import status  # stderr, hidden by -q

    status(msg)


def session_from_args(args, **kw):
    """The :class:`~nodlidar.runtime.session.Session` the options describe (``kw`` go to
    it too, e.g. ``seed``); its status and progress lines go to stderr."""
    from ..runtime.session import Session

    return Session(getattr(args, "design", None), port=args.port, servo_port=args.servo_port,
                   calibration=getattr(args, "calibration", None), transport=args.sim_transport,
                   sim_rate=args.sim_rate, scene=args.scene, noise=not args.no_noise,
                   sim_perturbations=sim_perturbations(args.perturb), log=_stderr, **kw)


def sim_perturbations(name: str):
    """The simulated sensor's as-built mirror errors by name (``none`` or ``table1``)."""
    if name == "none":
        return None
    from ..paper import TABLE_I_PERTURBATIONS

    return dict(TABLE_I_PERTURBATIONS)


def add_frame_args(p) -> None:
    p.add_argument("--frame", choices=("sensor", "robot", "world"), default="sensor",
                   help="output frame (default sensor)")
    p.add_argument("--robot2sensor", type=float, nargs=6, metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                   default=None, help="sensor pose on the robot [m, deg] (frames robot/world)")
    p.add_argument("--world2robot", type=float, nargs=6, metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                   default=None, help="robot pose in the world [m, deg] (frame world)")


def pose_matrix(v, name: str) -> np.ndarray:
    """4x4 from x y z [m] roll pitch yaw [deg] (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    if v is None:
        return np.eye(4)
    if not all(math.isfinite(x) for x in v):
        raise ParameterError(name, v, "six finite numbers: x y z [m] roll pitch yaw [deg]")
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [v[5], v[4], v[3]], degrees=True).as_matrix()
    T[:3, 3] = v[:3]
    return T


def frame_kwargs(args) -> dict:
    return {"frame": args.frame, "robot2sensor": pose_matrix(args.robot2sensor, "--robot2sensor"),
            "world2robot": pose_matrix(args.world2robot, "--world2robot")}


def check_out(path: str, field: str = "--out") -> None:
    if not path.lower().endswith((".ply", ".pcd")):
        raise ParameterError(field, path, "a .ply or .pcd file name")
