"""The simulated sensor: a SCIP 2.0 lidar and a Dynamixel bus on one clock, seeing a scene.

What runtime commands start when no hardware port is given::

    with SimulatedSensor(design, "room", transport="pty") as sim:
        with UrgDriver(sim.lidar_url) as urg: ...
        bus = DynamixelBus(sim.servo_url) ...

Each scan's ranges come from :class:`~nodlidar.sim.raycast.SceneSimulator`, with the nod
and mirror servo angles read from the Dynamixel emulator's true shaft-angle history
(:meth:`DxlEmulator.joint_angle`) at every beam's own time: whatever the runtime commands
the servos is what the scans see. The nod servo angle is the head pitch [rad]; a mirror
servo angle ``a`` lifts its side by the fraction ``clip((a - deployed)/(lifted - deployed),
0, 1)`` (:func:`nodlidar.hinge.lift_fraction`) of its lift about the side's lift axis, with
the side's ``MirrorLiftProfile``: by default the design's
(:func:`nodlidar.runtime.servo_angles.lift_profiles`: deployed 0, lifted ``LiftAxis.lift_rad``,
so one servo radian turns the carrier by one radian).

Noise is seeded per scan (``default_rng([seed, k])``), so a scan's ranges do not depend on
when or how often it is asked for.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ParameterError
from ..geometry import Perturbation
from ..hinge import lift_fraction
from ..runtime.servo_angles import MirrorLiftProfile, lift_profiles
from .clock import SimClock
from .dxl_emulator import DxlEmulator
from .faults import FaultConfig
from .raycast import ScanTruth, SceneSimulator
from .scene import Scene
from .scip_emulator import ScipEmulator

if TYPE_CHECKING:
    from ..design import Design

__all__ = ["SimulatedSensor"]

_TRUTH_KEPT = 256  # scans of ground truth kept for inspection


class SimulatedSensor:
    """Lidar + servo emulators on one :class:`SimClock`, scans ray-traced in a scene.

    Parameters
    ----------
    design : Design
        Solved design (lidar model, mirrors, nod pivot, lift angle).
    scene : Scene, str or None
        Scene or built-in name (``room``, ``paper-tracking``, ``wall``); default ``room``.
        Read a TOML scene with :func:`~nodlidar.sim.scene.load_scene` first.
    perturbations : mapping mirror name -> Perturbation, optional
        "As built" mirror errors (e.g. ``nodlidar.paper.TABLE_I_PERTURBATIONS``).
    transport : str
        ``"pty"`` (pseudo-terminals, open like /dev/ttyACM0) or ``"tcp"`` (socket:// URLs).
    rate : float
        Simulated seconds per wall second (1 = real time).
    noise : bool
        Add the URG range noise (off: exact ranges rounded to mm).
    seed : int
        Noise seed.
    faults : FaultConfig, optional
        Link faults injected on the lidar's outgoing messages.
    lift_left, lift_right : MirrorLiftProfile, optional
        The mirror servos' deployed and lifted angles [rad] of each side (default: the
        design's, :func:`~nodlidar.runtime.servo_angles.lift_profiles`).
    host : str
        TCP transport: the address both servers listen on (loopback by default).
    lidar_port, servo_port : int
        TCP transport: fixed ports (0: any free port).
    scip1 : bool
        The lidar boots in SCIP 1.1 mode (as a factory-fresh URG-04LX): a client must send
        ``SCIP2.0`` first.

    Nothing starts in the constructor; :meth:`start` (or ``with``) serves both devices.
    """

    def __init__(self, design: Design, scene: Scene | str | None = None, *,
                 perturbations: Mapping[str, Perturbation] | None = None, transport: str = "pty",
                 rate: float = 1.0, noise: bool = True, seed: int = 0,
                 faults: FaultConfig | None = None,
                 lift_left: MirrorLiftProfile | None = None,
                 lift_right: MirrorLiftProfile | None = None, host: str = "127.0.0.1",
                 lidar_port: int = 0, servo_port: int = 0, scip1: bool = False):
        if transport not in ("pty", "tcp"):
            raise ParameterError("transport", transport, "'pty' or 'tcp'")
        for name, v in (("lidar_port", lidar_port), ("servo_port", servo_port)):
            if not (isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 65535):
                raise ParameterError(name, v, "an integer 0..65535 (0 = any free port)")
        if lidar_port and lidar_port == servo_port:
            raise ParameterError("servo_port", servo_port, f"!= lidar_port ({lidar_port})")
        if not (isinstance(host, str) and host):
            raise ParameterError("host", host, "an address such as 127.0.0.1")
        self.host, self.lidar_port, self.servo_port = host, lidar_port, servo_port
        self.design = design
        self.transport = transport
        self.noise = bool(noise)
        self.seed = int(seed)
        self.faults = faults
        dl, dr = lift_profiles(design)
        #: Lift-servo profile of each side: servo angle -> lift fraction. (One pair of
        #: angles for both sides, as before, would turn one side's carrier the wrong way.)
        self.lift = {"mirror_left": lift_left or dl, "mirror_right": lift_right or dr}
        self.simulator = SceneSimulator(design, scene, perturbations)
        self.scene = self.simulator.scene
        self.clock = SimClock(rate)
        self.dxl = DxlEmulator(self.clock)
        self.scip = ScipEmulator(design.lidar, self.clock, self.range_source, faults=faults,
                                 scip1=scip1)
        self.lidar_url: str | None = None
        self.servo_url: str | None = None
        self._truth: OrderedDict[int, ScanTruth] = OrderedDict()
        self._lock = threading.Lock()

    # -- ranges ------------------------------------------------------------------------
    def simulate_scan(self, k: int, t_scan_s: float | None = None) -> ScanTruth:
        """Simulate scan ``k`` (stamped ``t_scan_s``, default ``k * period``) with the
        servo angles the emulated bus had at each beam's time; keeps its ground truth."""
        sim = self.simulator
        t_scan = k * sim.lidar.scan_period_s if t_scan_s is None else t_scan_s
        t = sim.beam_times(t_scan)
        nod = self.dxl.joint_angle("nod", t)
        fl, fr = (lift_fraction(self.dxl.joint_angle(j, t), self.lift[j].deployed_rad,
                                self.lift[j].lifted_rad) for j in ("mirror_left", "mirror_right"))
        rng = np.random.default_rng([self.seed, int(k)]) if self.noise else None
        truth = sim.scan(t_scan, nod, fl, fr, noise=self.noise, rng=rng)
        with self._lock:
            self._truth[int(k)] = truth
            while len(self._truth) > _TRUTH_KEPT:
                self._truth.popitem(last=False)
        return truth

    def range_source(self, k: int, t_scan_s: float) -> np.ndarray:
        """The SCIP emulator's range source: ``(n_steps,)`` ranges [m], NaN = no return."""
        return self.simulate_scan(k, t_scan_s).range_m

    def truth(self, k: int) -> ScanTruth | None:
        """Ground truth of scan ``k`` if it was simulated recently (last 256 scans)."""
        with self._lock:
            return self._truth.get(int(k))

    def scan_index(self, timestamp_ms: int) -> int:
        """Scan number of a SCIP timestamp (unwrapped) [ms]."""
        return self.scip.scan_index(timestamp_ms)

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> SimulatedSensor:
        """Serve the lidar and the servo bus; sets :attr:`lidar_url` and :attr:`servo_url`."""
        if self.lidar_url is not None:
            return self
        # kernels compiled before the first scan is due, not in the emulator's thread
        self.simulator.warm_up()
        if self.transport == "tcp":
            try:
                self.lidar_url = self.scip.serve_tcp(self.host, self.lidar_port)
                self.servo_url = self.dxl.serve_tcp(self.host, self.servo_port)
            except BaseException:
                self.close()
                self.lidar_url = self.servo_url = None
                raise
        else:
            self.lidar_url = self.scip.serve_pty()
            self.servo_url = self.dxl.serve_pty()
        return self

    def close(self) -> None:
        """Stop both emulators (idempotent)."""
        self.scip.stop()
        self.dxl.close()

    def __enter__(self) -> SimulatedSensor:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
