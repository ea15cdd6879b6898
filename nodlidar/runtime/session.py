"""A runtime session: the lidar and the servos (real or the simulated sensor) on one clock.

``Session(design_path, port=..., servo_port=...)`` opens a SCIP 2.0 lidar and a Dynamixel
bus from pyserial URLs; with neither port given it starts the built-in
:class:`~nodlidar.sim.sensor.SimulatedSensor` (pty or TCP) and uses its clock. Every time
in a session (scan stamps after the TM clock sync, servo samples) is in that one clock:
``time.monotonic`` on hardware, simulated seconds in simulation.

:meth:`Session.capture` nods the head (the design's ``[nod]`` ramp), samples the servos and
streams scans until told to stop; :meth:`Session.sweep` is one full ramp from the lower
to the upper pitch limit. :class:`Capture` assembles itself through
:func:`~nodlidar.runtime.assembly.assemble`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DeviceError, ParameterError, require
from ..paper import PAPER_DESIGN as DEFAULT_DESIGN
from .actuators import (
    MIRROR_LEFT_ID,
    MIRROR_RIGHT_ID,
    NOD_ID,
    DynamixelBus,
    MirrorLift,
    MirrorLiftProfile,
    NodController,
    NodProfile,
    PositionSampler,
)
from .assembly import AssemblyModel, PointCloud, ScanBatch, assemble

__all__ = ["Session", "Capture", "DEFAULT_DESIGN", "JOINT_IDS"]

JOINT_IDS = {"nod": NOD_ID, "mirror_left": MIRROR_LEFT_ID, "mirror_right": MIRROR_RIGHT_ID}


@dataclass
class Capture:
    """Scans and servo samples of one capture (all times in the session clock [s]).

    Attributes
    ----------
    scans : list of Scan
    joints : dict
        ``nod`` / ``mirror_left`` / ``mirror_right`` -> (t_s (k,), angle_rad (k,)).
    lift_left, lift_right : MirrorLiftProfile
    t_start_s, t_end_s : float
        The nod ramp captured (sweep) or the capture's span.
    """

    scans: list
    joints: dict[str, tuple[np.ndarray, np.ndarray]]
    lift_left: MirrorLiftProfile = field(default_factory=MirrorLiftProfile)
    lift_right: MirrorLiftProfile = field(default_factory=MirrorLiftProfile)
    t_start_s: float = float("nan")
    t_end_s: float = float("nan")

    def assemble(self, model: AssemblyModel, **kw) -> PointCloud:
        """Assemble every scan (``kw``: frame, robot2sensor, world2robot...)."""
        require(len(self.scans) > 0, "capture.scans", 0, "at least one scan")
        return assemble(model, ScanBatch.from_scans(self.scans), self.joints["nod"],
                        mirror_left=self.joints.get("mirror_left"),
                        mirror_right=self.joints.get("mirror_right"),
                        lift_left=self.lift_left, lift_right=self.lift_right, **kw)


class Session:
    """Open lidar + servos (or the simulated sensor).

    Parameters
    ----------
    design : str or Path
        Design TOML (default ``design/urg04lx-paper.toml``).
    port, servo_port : str, optional
        Lidar and servo-bus URLs (device path, ``socket://host:port``). Both or neither:
        neither starts the simulated sensor.
    calibration : str or Path, optional
        Calibration TOML for this design (its mirror perturbations are applied).
    transport : {"pty", "tcp"}
        Simulated sensor's link.
    sim_rate : float
        Simulated seconds per wall second.
    scene : str, optional
        Simulated scene (built-in name or TOML; default ``room``).
    noise : bool
        Simulated range noise.
    sim_perturbations : dict of str -> Perturbation, optional
        The simulated sensor's as-built mirror errors (ground truth a calibration should find).
    log : callable, optional
        Receives progress/status messages (one line each); default none (library code does
        not print - the CLI passes a stderr writer).
    """

    def __init__(self, design: str | Path | None = None, *, port: str | None = None,
                 servo_port: str | None = None, calibration: str | Path | None = None,
                 transport: str = "pty", sim_rate: float = 1.0, scene: str | None = None,
                 noise: bool = True, seed: int = 0, lidar_timeout_s: float = 1.0,
                 sim_perturbations=None,
                 log: Callable[[str], None] | None = None):
        if (port is None) != (servo_port is None):
            raise ParameterError("--port/--servo-port", (port, servo_port),
                                 "both (hardware) or neither (the simulated sensor)")
        require(sim_rate > 0, "--sim-rate", sim_rate, "> 0")
        self.design_path = Path(design) if design is not None else DEFAULT_DESIGN
        self.port, self.servo_port = port, servo_port
        self.calibration_path = Path(calibration) if calibration is not None else None
        self.transport, self.sim_rate, self.scene = transport, float(sim_rate), scene
        self.noise, self.seed = bool(noise), int(seed)
        self.sim_perturbations = sim_perturbations
        self.lidar_timeout_s = float(lidar_timeout_s)
        self.log = log or (lambda _m: None)
        self.lift_left = MirrorLiftProfile()
        self.lift_right = MirrorLiftProfile()
        self.design = None
        self.calibration = None
        self.model: AssemblyModel | None = None
        self.sim = None
        self.urg = None
        self.bus: DynamixelBus | None = None
        self.time_source: Callable[[], float] = time.monotonic
        self.last_turns: list[tuple[float, float]] = []

    @property
    def simulated(self) -> bool:
        return self.port is None

    # -- lifecycle -----------------------------------------------------------------------
    def open(self) -> Session:
        from ..solver import solve
        from ..spec import load_design
        from .urg import UrgDriver

        self.design = solve(load_design(self.design_path))
        perts, cal_id = None, "none"
        if self.calibration_path is not None:
            from ..calibration.calfile import load_calibration

            self.calibration = load_calibration(self.calibration_path, self.design)
            perts, cal_id = self.calibration.perturbations, self.calibration.id
        self.model = AssemblyModel.from_design(self.design, perts, cal_id)
        try:
            if self.simulated:
                from ..sim.scene import load_scene
                from ..sim.sensor import SimulatedSensor

                scene = load_scene(self.scene)  # a TOML scene is read here, not in a constructor
                self.sim = SimulatedSensor(self.design, scene, perturbations=self.sim_perturbations,
                                           transport=self.transport,
                                           rate=self.sim_rate, noise=self.noise, seed=self.seed)
                self.sim.start()
                self.time_source = self.sim.clock.now
                lidar_url, servo_url = self.sim.lidar_url, self.sim.servo_url
                built = "mirrors with as-built errors" if self.sim_perturbations else "mirrors as designed"
                self.log(f"using the simulated sensor (scene {self.sim.scene.name!r}, {built}, "
                         f"{self.transport} {lidar_url} + {servo_url}, {self.sim_rate:g}x real time)")
            else:
                lidar_url, servo_url = self.port, self.servo_port
            self.urg = UrgDriver(lidar_url, timeout=self.lidar_timeout_s).open()
            self.bus = DynamixelBus(servo_url, time_source=self.time_source).open()
            self.urg.sync_clock(time_source=self.time_source)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        for obj in (self.urg, self.bus):
            if obj is not None:
                try:
                    obj.close()
                except Exception:  # best effort on the way out
                    pass
        self.urg = self.bus = None
        if self.sim is not None:
            self.sim.close()
            self.sim = None

    def __enter__(self) -> Session:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- info ------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """Lidar VV/PP/II and the servos that answer a broadcast PING."""
        i = self.urg.info()
        servos = self.bus.discover()
        names = {v: k for k, v in JOINT_IDS.items()}
        return {"version": i.version, "params": i.params, "state": i.state,
                "servos": [{"id": s.id, "model_number": s.model_number,
                            "firmware": s.firmware_version, "role": names.get(s.id, "?")}
                           for s in servos]}

    def nod_profile(self) -> NodProfile:
        n = self.design.spec.nod
        return NodProfile(n.pitch_min_rad, n.pitch_max_rad, n.rate_rad_s)

    # -- capture ---------------------------------------------------------------------------
    def capture(self, stop: Callable[[list, NodController], bool], *, lift: bool = False,
                on_scan: Callable[[Any, dict[str, PositionSampler]], None] | None = None,
                nod_period_s: float = 0.002, mirror_period_s: float = 0.02) -> Capture:
        """Nod, sample the servos and stream scans until ``stop(scans, nod)`` is true.

        ``lift`` lifts both mirrors first (else they are deployed). ``on_scan(scan,
        samplers)`` runs for every scan (recording). Returns every scan and every sample.
        """
        bus = self.bus
        lifter = MirrorLift(bus, self.lift_left, self.lift_right)
        lifter.lift() if lift else lifter.reset()
        samplers = {"nod": PositionSampler(bus, NOD_ID, period_s=nod_period_s),
                    "mirror_left": PositionSampler(bus, MIRROR_LEFT_ID, period_s=mirror_period_s),
                    "mirror_right": PositionSampler(bus, MIRROR_RIGHT_ID, period_s=mirror_period_s)}
        for s in samplers.values():
            s.start()
        nod = NodController(bus, self.nod_profile())
        scans: list = []
        t0 = self.time_source()
        try:
            nod.start()
            for scan in self.urg.stream():
                scans.append(scan)
                if on_scan is not None:
                    on_scan(scan, samplers)
                if nod.error is not None:
                    nod.stop()  # raises DeviceError with the cause
                if stop(scans, nod):
                    break
        finally:
            try:
                nod.stop()
            finally:
                for s in samplers.values():
                    s.stop()
        self.last_turns = list(nod.turns)
        joints = {}
        for name, s in samplers.items():
            smp = s.samples()
            joints[name] = (smp.host_time_s, smp.angle_rad)
        if len(joints["nod"][0]) < 2:
            raise DeviceError("no nod servo samples were read; is the servo bus connected?")
        return Capture(scans, joints, self.lift_left, self.lift_right, t0, self.time_source())

    def sweep(self, *, lift: bool = False, timeout_s: float | None = None) -> Capture:
        """One full nod ramp (lower -> upper pitch limit); progress on the log.

        Keeps the scans whose beams overlap the ramp.
        """
        prof = self.nod_profile()
        period = self.design.lidar.scan_period_s
        limit = timeout_s if timeout_s is not None else 3 * prof.period_s + 10.0
        last_report = [0.0]

        def stop(scans, nod):
            now = scans[-1].stamp_s
            if now - scans[0].stamp_s > limit:
                raise DeviceError(f"nod sweep not finished within {limit:.0f} s "
                                  f"({nod.sweeps} ramps, {len(scans)} scans)")
            turns = list(nod.turns)
            if len(turns) >= 2:
                frac = min(1.0, max(0.0, (now - turns[1][0]) / prof.sweep_time_s))
                if frac - last_report[0] >= 0.2 or (frac == 1.0 and last_report[0] < 1.0):
                    last_report[0] = frac
                    # floor: "100%" only once the ramp is really complete
                    self.log(f"sweep {math.floor(100 * frac):3d}% ({len(scans)} scans)")
            return nod.sweeps >= 1 and len(turns) >= 3 and now > turns[2][0] + period

        cap = self.capture(stop, lift=lift)
        # nod.turns: (time, goal) each time the goal was set; [1] = start of the up ramp
        # (goal upper), [2] = its end (goal flipped back to lower)
        t_a, t_b = self.last_turns[1][0], self.last_turns[2][0]
        keep = [s for s in cap.scans if t_a - period <= s.stamp_s <= t_b]
        return Capture(keep, cap.joints, cap.lift_left, cap.lift_right, t_a, t_b)


def record_capture(session: Session, recorder, stop: Callable[[list, NodController], bool], *,
                   lift: bool = False, log_every: int = 10) -> Capture:
    """Capture while writing every scan and every servo sample to ``recorder`` (an open
    :class:`~nodlidar.runtime.bag.BagRecorder`), committing after each scan.

    Returns the capture exactly as recorded (so a live cloud and its replay agree).
    """
    lidar = session.design.lidar
    written = {j: float("-inf") for j in JOINT_IDS}

    def flush(samplers) -> None:
        for name, smp in samplers.items():
            s = smp.samples(since_s=written[name])
            new = s.host_time_s > written[name]
            if new.any():
                recorder.write_samples(name, s.host_time_s[new], s.angle_rad[new])
                written[name] = float(s.host_time_s[new][-1])

    def on_scan(scan, samplers) -> None:
        recorder.write_scan(scan, lidar)
        flush(samplers)
        recorder.commit()
        if log_every and recorder.scans % log_every == 0:
            session.log(f"recorded {recorder.scans} scans")

    cap = session.capture(stop, lift=lift, on_scan=on_scan)
    # the samplers have stopped: write what came after the last scan, so the bag holds
    # exactly cap.joints
    for name, (t, a) in cap.joints.items():
        new = t > written[name]
        if new.any():
            recorder.write_samples(name, t[new], a[new])
    recorder.commit()
    return cap
