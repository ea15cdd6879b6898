"""Options shared by the runtime commands (info, scan, record, replay)."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING, Any

from ..errors import ParameterError
from ..validation import check_number
from ._args import check_output_path

if TYPE_CHECKING:  # numpy only where used: --help imports no numpy
    from collections.abc import Sequence

    import numpy as np

    from ..geometry import Perturbation
    from ..runtime.session import Session

    #: What the option helpers add arguments to: a parser or an argument group.
    ArgContainer = argparse.ArgumentParser | argparse._ArgumentGroup

#: Simulated seconds per wall second. Below 0.01 a sweep of a few simulated seconds takes
#: minutes (1e-9 hung for ever); above 1000 the emulator cannot keep the pace.
SIM_RATE_MIN, SIM_RATE_MAX = 0.01, 1000.0
#: Pose bounds: positions [m] (clouds are written as float32, ~1 mm resolution at 10 km)
#: and angles [deg].
POSE_MAX_M, POSE_MAX_DEG = 10_000.0, 360.0

#: Shown in help texts for the default design (:data:`nodlidar.paper.PAPER_DESIGN`).
DESIGN_HELP = "design file (default: the paper's build, design/urg04lx-paper.toml)"


def add_design_arg(p: ArgContainer) -> None:
    """``--design TOML``, defaulting to the paper's build wherever the command runs."""
    from .._light import PAPER_DESIGN  # (not paper: --help imports no numpy)

    p.add_argument("--design", metavar="TOML", default=str(PAPER_DESIGN), help=DESIGN_HELP)


def add_device_args(p: ArgContainer, *, design: bool = True, scene: str | None = None,
                    scans: bool = True) -> None:
    """--design, --port, --servo-port, --calibration, --plausibility (``scans``: the command
    reads scans) and the simulated-sensor options (``scene``: the simulated sensor's default
    scene, ``room`` if None)."""
    if design:
        add_design_arg(p)
        p.add_argument("--calibration", metavar="TOML", default=None,
                       help="calibration file of this design (mirror perturbations)")
    p.add_argument("--port", metavar="URL", default=None,
                   help="lidar port: device path or socket://host:port "
                        "(default: the built-in simulated sensor)")
    p.add_argument("--servo-port", metavar="URL", default=None,
                   help="Dynamixel bus port (default: the built-in simulated sensor)")
    if scans:
        p.add_argument("--plausibility", action="store_true",
                       help="drop ranges the lidar cannot have measured (corruptions the SCIP "
                            "checksums pass; ~3e-4 of clean values are dropped too)")
    p.add_argument("--sim-rate", type=float, default=1.0, metavar="X",
                   help="simulated sensor: simulated seconds per wall second "
                   f"(e.g. 5; {SIM_RATE_MIN:g} .. {SIM_RATE_MAX:g})")
    p.add_argument("--sim-transport", choices=("pty", "tcp"), default="pty",
                   help="simulated sensor: serve over pseudo-terminals or TCP (default pty)")
    p.add_argument("--scene", default=scene,
                   help=f"simulated sensor: scene name or TOML (default {scene or 'room'})")
    p.add_argument("--no-noise", action="store_true", help="simulated sensor: no range noise")
    p.add_argument("--perturb", choices=("none", "table1"), default="none",
                   help="simulated sensor: as-built mirror errors (table1 = the paper's Table I; "
                        "default none = built exactly as designed)")
    p.set_defaults(_scene_default=scene)


def _stderr(msg: str) -> None:
    from ._output import status  # stderr, hidden by -q

    status(msg)


def session_from_args(args: argparse.Namespace, **kw: Any) -> Session:
    """The :class:`~nodlidar.runtime.session.Session` the options describe (``kw`` go to
    it too, e.g. ``seed``); its status and progress lines go to stderr."""
    from ..runtime.session import Session

    check_sim_options(args)
    return Session(getattr(args, "design", None), port=args.port, servo_port=args.servo_port,
                   calibration=getattr(args, "calibration", None), transport=args.sim_transport,
                   sim_rate=args.sim_rate, scene=args.scene, noise=not args.no_noise,
                   sim_perturbations=sim_perturbations(args.perturb),
                   plausibility=getattr(args, "plausibility", False), log=_stderr, **kw)


def check_sim_options(args: argparse.Namespace) -> None:
    """Refuse a ``--sim-rate`` out of bounds, and simulated-sensor options given with real
    devices (``--port``/``--servo-port``): they would be silently ignored."""
    # checked here rather than by argparse so that main() returns 2 (in-process callers)
    check_number(args.sim_rate, "--sim-rate", lo=SIM_RATE_MIN, hi=SIM_RATE_MAX,
                 unit="(simulated seconds per wall second)")
    if getattr(args, "port", None) is None and getattr(args, "servo_port", None) is None:
        return
    for opt, url in (("--port", args.port), ("--servo-port", getattr(args, "servo_port", None))):
        check_port_url(url, opt)
    given = [("--sim-rate", args.sim_rate, args.sim_rate != 1.0),
             ("--sim-transport", args.sim_transport, args.sim_transport != "pty"),
             ("--scene", args.scene, args.scene != getattr(args, "_scene_default", None)),
             ("--no-noise", True, args.no_noise),
             ("--perturb", args.perturb, args.perturb != "none")]
    for opt, value, on in given:
        if on:
            raise ParameterError(opt, value, "only with the simulated sensor (it does not apply "
                                             "with --port/--servo-port)")


def check_port_url(url: str | None, option: str) -> None:
    """Refuse a port URL whose scheme pyserial has no handler for (``foo://x``) before any
    work: pyserial would raise a bare ``ValueError`` when the port is opened."""
    if url is None or "://" not in url:
        return  # a device path: the system says whether it exists when it is opened
    import importlib.util
    import re

    scheme = url.split("://", 1)[0].lower()
    known = bool(re.fullmatch(r"[a-z][a-z0-9_]*", scheme)) and \
        importlib.util.find_spec(f"serial.urlhandler.protocol_{scheme}") is not None
    if not known:
        raise ParameterError(option, url, "a device path or a pyserial URL "
                                          "(socket://host:port, rfc2217://host:port, loop://)")


def sim_perturbations(name: str) -> dict[str, Perturbation] | None:
    """The simulated sensor's as-built mirror errors by name (``none`` or ``table1``)."""
    if name == "none":
        return None
    from ..paper import TABLE_I_PERTURBATIONS

    return dict(TABLE_I_PERTURBATIONS)


class _RenamedFlag(argparse.Action):
    """A flag that was renamed: given, it answers with a one-line hint naming the new
    spelling and what it means, and exit status 2 (it is hidden from --help)."""

    def __init__(self, option_strings, dest, **kw):
        kw.update(nargs="*", help=argparse.SUPPRESS, default=argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        from ..frames import renamed_hint  # the error path only: --help imports no numpy

        parser.error(renamed_hint(self.dest, "--"))


def add_frame_args(p: ArgContainer) -> None:
    """--frame, --robot-from-sensor and --world-from-robot (the old --robot2sensor and
    --world2robot answer with a hint)."""
    p.add_argument("--frame", choices=("sensor", "robot", "world"), default="sensor",
                   help="output frame (default sensor)")
    p.add_argument("--robot-from-sensor", type=float, nargs=6,
                   metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"), default=None,
                   help="sensor pose on the robot [m, deg]: maps sensor coordinates into the "
                        "robot frame (frames robot/world)")
    p.add_argument("--world-from-robot", type=float, nargs=6,
                   metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"), default=None,
                   help="robot pose in the world [m, deg]: maps robot coordinates into the "
                        "world frame (frame world)")
    for old in ("robot2sensor", "world2robot"):
        p.add_argument(f"--{old}", dest=old, action=_RenamedFlag)


def pose_matrix(v: Sequence[float] | None, name: str) -> np.ndarray:
    """4x4 from x y z [m] roll pitch yaw [deg] (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    import numpy as np  # here, not at module level: --help imports no numpy

    if v is None:
        return np.eye(4)
    if not (len(v) == 6 and all(math.isfinite(x) for x in v)
            and all(abs(x) <= POSE_MAX_M for x in v[:3])
            and all(abs(x) <= POSE_MAX_DEG for x in v[3:])):
        raise ParameterError(name, list(v), f"x y z [m] within +-{POSE_MAX_M:g} and roll pitch "
                                            f"yaw [deg] within +-{POSE_MAX_DEG:g}")
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [v[5], v[4], v[3]], degrees=True).as_matrix()
    T[:3, 3] = v[:3]
    return T


def frame_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The :func:`~nodlidar.runtime.assembly.assemble` keywords of the frame options."""
    return {"frame": args.frame,
            "robot_from_sensor": pose_matrix(args.robot_from_sensor, "--robot-from-sensor"),
            "world_from_robot": pose_matrix(args.world_from_robot, "--world-from-robot")}


def check_out(path: str, field: str = "--out", *, force: bool = True) -> None:
    """A cloud output: a .ply/.pcd file name in an existing writable directory, not a
    directory; an existing file only with ``force`` (pass ``force=args.force`` once the
    command has ``--force``, :func:`nodlidar.commands._args.add_force_arg`). Checked
    before the sweep, so a bad path fails at once."""
    if not str(path).lower().endswith((".ply", ".pcd")):
        raise ParameterError(field, path, "a .ply or .pcd file name")
    check_output_path(path, force=force, kind="file", option=field)
