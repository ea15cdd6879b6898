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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, TypeVar

import numpy as np

from ..errors import DeviceError, ParameterError, require
from ..paper import PAPER_DESIGN as DEFAULT_DESIGN
from ..scip import RangePlausibility
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
    lift_profiles,
)
from .assembly import AssemblyModel, PointCloud, ScanBatch, assemble, warm_up

if TYPE_CHECKING:
    from ..calibration.calfile import Calibration
    from ..design import Design
    from ..geometry import Perturbation
    from ..sim.scene import Scene
    from ..sim.sensor import SimulatedSensor
    from .bag import BagRecorder
    from .urg import Scan, UrgDriver

_T = TypeVar("_T")


def _need(x: _T | None) -> _T:
    """``x``, which :meth:`Session.open` sets: a session used before ``open()`` (or after
    ``close()``) says so in one line."""
    if x is None:
        raise DeviceError("the session is not open: use `with Session(...) as s:` or call "
                          "open() first")
    return x

__all__ = ["Session", "Capture", "DEFAULT_DESIGN", "JOINT_IDS", "LiveAssembler", "CloudSpool",
           "Recorded", "record_capture"]

JOINT_IDS = {"nod": NOD_ID, "mirror_left": MIRROR_LEFT_ID, "mirror_right": MIRROR_RIGHT_ID}


@dataclass
class Capture:
    """Scans and servo samples of one capture (all times in the session clock [s]).

    Attributes
    ----------
    scans : list of Scan
    joints : dict
        ``nod`` / ``mirror_left`` / ``mirror_right`` -> (t_s (k,), angle_rad (k,)).
    lift_left, lift_right : MirrorLiftProfile or None
        The lift servos' profiles (None: the design's, as :func:`assemble` takes them).
    t_start_s, t_end_s : float
        The nod ramp captured (sweep) or the capture's span.
    ticks_ms : dict
        ``nod`` / ... -> (k,) int: each sample's servo realtime tick [ms, modulo 32768],
        the servo's own time of the READ (the joints' ``t_s`` is the host's stamp, the
        middle of the transaction) - what a check of the stamps compares with.
    """

    scans: list
    joints: dict[str, tuple[np.ndarray, np.ndarray]]
    lift_left: MirrorLiftProfile | None = None
    lift_right: MirrorLiftProfile | None = None
    t_start_s: float = float("nan")
    t_end_s: float = float("nan")
    ticks_ms: dict[str, np.ndarray] = field(default_factory=dict)

    def assemble(self, model: AssemblyModel, **kw: Any) -> PointCloud:
        """Assemble every scan (``kw``: frame, robot_from_sensor, world_from_robot...)."""
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
    scene : Scene or str, optional
        Simulated scene (a :class:`~nodlidar.sim.scene.Scene`, a built-in name or a TOML file;
        default ``room``).
    noise : bool
        Simulated range noise.
    sim_perturbations : mapping str -> Perturbation, optional
        The simulated sensor's as-built mirror errors (ground truth a calibration should find).
    plausibility : bool
        Drop decoded ranges the sensor cannot have measured (values corrupted in a way the
        6-bit checksums pass): :class:`nodlidar.scip.RangePlausibility` in the lidar driver.
        Off by default (about 3 in 10 000 clean values are flagged too).
    log : callable, optional
        Receives progress/status messages (one line each); default none (library code does
        not print - the CLI passes a stderr writer).
    """

    def __init__(self, design: str | Path | None = None, *, port: str | None = None,
                 servo_port: str | None = None, calibration: str | Path | None = None,
                 transport: str = "pty", sim_rate: float = 1.0, scene: Scene | str | None = None,
                 noise: bool = True, seed: int = 0, lidar_timeout_s: float = 1.0,
                 sim_perturbations: Mapping[str, Perturbation] | None = None,
                 plausibility: bool = False,
                 log: Callable[[str], None] | None = None) -> None:
        if (port is None) != (servo_port is None):
            raise ParameterError("--port/--servo-port", (port, servo_port),
                                 "both (hardware) or neither (the simulated sensor)")
        require(math.isfinite(sim_rate) and sim_rate > 0, "--sim-rate", sim_rate,
                "a finite number > 0")
        self.design_path = Path(design) if design is not None else DEFAULT_DESIGN
        self.port, self.servo_port = port, servo_port
        self.calibration_path = Path(calibration) if calibration is not None else None
        self.transport, self.sim_rate, self.scene = transport, float(sim_rate), scene
        self.noise, self.seed = bool(noise), int(seed)
        self.sim_perturbations = sim_perturbations
        self.lidar_timeout_s = float(lidar_timeout_s)
        self.plausibility = bool(plausibility)
        self.log = log or (lambda _m: None)
        # the lift servos' profiles come from the design (lift_profiles), set by open()
        self.lift_left: MirrorLiftProfile | None = None
        self.lift_right: MirrorLiftProfile | None = None
        # set by open()
        self.design: Design | None = None
        self.calibration: Calibration | None = None
        self.model: AssemblyModel | None = None
        self.sim: SimulatedSensor | None = None
        self.urg: UrgDriver | None = None
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

        self.design = design = solve(load_design(self.design_path))
        perts, cal_id = None, "none"
        if self.calibration_path is not None:
            from ..calibration.calfile import load_calibration

            self.calibration = cal = load_calibration(self.calibration_path, design)
            perts, cal_id = cal.perturbations, cal.id
        self.model = AssemblyModel.from_design(design, perts, cal_id)
        self.lift_left, self.lift_right = lift_profiles(design)
        # the compiled kernel ready before the first scan streams in (not in its loop)
        warm_up(self.model)
        try:
            if self.simulated:
                from ..sim.scene import load_scene
                from ..sim.sensor import SimulatedSensor

                scene = load_scene(self.scene)  # a TOML scene is read here, not in a constructor
                self.sim = sim = SimulatedSensor(design, scene,
                                                 perturbations=self.sim_perturbations,
                                                 transport=self.transport,
                                                 rate=self.sim_rate, noise=self.noise,
                                                 seed=self.seed, lift_left=self.lift_left,
                                                 lift_right=self.lift_right)
                sim.start()
                self.time_source = sim.clock.now
                lidar_url, servo_url = _need(sim.lidar_url), _need(sim.servo_url)
                built = "mirrors with as-built errors" if self.sim_perturbations else "mirrors as designed"
                self.log(f"using the simulated sensor (scene {sim.scene.name!r}, {built}, "
                         f"{self.transport} {lidar_url} + {servo_url}, {self.sim_rate:g}x real time)")
            else:
                # the constructor took both ports or neither
                assert self.port is not None and self.servo_port is not None
                lidar_url, servo_url = self.port, self.servo_port
            self.urg = urg = UrgDriver(
                lidar_url, timeout=self.lidar_timeout_s,
                plausibility=RangePlausibility() if self.plausibility else None).open()
            # the simulated bus shares this machine's cores: give its replies more time
            self.bus = DynamixelBus(servo_url, time_source=self.time_source,
                                    timeout_s=0.5 if self.simulated else 0.1).open()
            urg.sync_clock(time_source=self.time_source)
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
        i = _need(self.urg).info()
        servos = _need(self.bus).discover()
        names = {v: k for k, v in JOINT_IDS.items()}
        return {"version": i.version, "params": i.params, "state": i.state,
                "servos": [{"id": s.id, "model_number": s.model_number,
                            "firmware": s.firmware_version, "role": names.get(s.id, "?")}
                           for s in servos]}

    def nod_profile(self) -> NodProfile:
        n = _need(self.design).spec.nod
        return NodProfile(n.pitch_min_rad, n.pitch_max_rad, n.rate_rad_s)

    # -- capture ---------------------------------------------------------------------------
    def capture(self, stop: Callable[[list, NodController], bool], *, lift: bool = False,
                on_scan: Callable[[Any, dict[str, PositionSampler]], None] | None = None,
                nod_period_s: float = 0.002, mirror_period_s: float = 0.02,
                keep: bool = True) -> Capture:
        """Nod, sample the servos and stream scans until ``stop(scans, nod)`` is true.

        ``lift`` lifts both mirrors first (else they are deployed). ``on_scan(scan,
        samplers)`` runs for every scan (recording). Returns every scan and the samples
        still buffered (``keep=True``: the newest 65 536 of each servo).

        ``keep=False`` (long captures whose ``on_scan`` consumes the scans): the scans are
        not kept; ``stop`` gets a window with ``len()``, the first and the last scan, and
        the returned capture has no scans; the samplers keep every sample until
        ``on_scan`` prunes them (``samplers[k].prune(t)``, see :class:`LiveAssembler`) -
        memory stays flat however long it runs, and no sample is lost.

        Raises
        ------
        DeviceError
            Once, for the first thing that failed: the nod controller, a sampler whose
            line failed (the servo bus vanished), or the lidar stream.
        """
        bus, urg = _need(self.bus), _need(self.urg)
        lifter = MirrorLift(bus, self.lift_left, self.lift_right)
        lifter.lift() if lift else lifter.reset()
        # keep=False (a consumer that prunes, as record_capture): every sample until
        # pruned, nothing lost. keep=True: the capture returns every scan with the
        # samples; a consumer that snapshots the samplers on every scan without pruning
        # (track live) must not copy an ever-growing buffer, so those keep the newest
        # 65 536 samples (> 2 min of nod samples at the 2 ms poll) as before.
        cap_n = None if not keep else 65536
        samplers = {"nod": PositionSampler(bus, NOD_ID, period_s=nod_period_s, capacity=cap_n),
                    "mirror_left": PositionSampler(bus, MIRROR_LEFT_ID, period_s=mirror_period_s,
                                                   capacity=cap_n),
                    "mirror_right": PositionSampler(bus, MIRROR_RIGHT_ID,
                                                    period_s=mirror_period_s, capacity=cap_n)}
        for s in samplers.values():
            s.start()
        # a wall-clock hiccup of the simulated sensor's host lasts sim_rate times longer
        # in simulated seconds
        stall_s = 2.0 * max(1.0, self.sim_rate) if self.simulated else 2.0
        nod = NodController(bus, self.nod_profile(), stall_timeout_s=stall_s)
        scans: Any = [] if keep else _ScanWindow()
        t0 = self.time_source()
        failed = False
        try:
            nod.start()
            for scan in urg.stream():
                scans.append(scan)
                _raise_sampler_error(samplers)
                if on_scan is not None:
                    on_scan(scan, samplers)
                if nod.error is not None:
                    nod.stop()  # raises DeviceError with the cause
                if stop(scans, nod):
                    break
        except BaseException:
            failed = True
            raise
        finally:
            try:
                if failed:  # report the first failure only: stopping may fail the same way
                    try:
                        nod.stop()
                    except DeviceError:
                        pass
                else:
                    nod.stop()
            finally:
                for s in samplers.values():
                    s.stop()
        _raise_sampler_error(samplers)
        self.last_turns = list(nod.turns)
        joints, ticks = {}, {}
        for name, s in samplers.items():
            smp = s.samples()
            joints[name] = (smp.host_time_s, smp.angle_rad)
            ticks[name] = smp.tick_ms
        if samplers["nod"].buffer.total < 2:
            raise DeviceError("no nod servo samples were read; is the servo bus connected?")
        return Capture(scans if keep else [], joints, self.lift_left, self.lift_right, t0,
                       self.time_source(), ticks)

    def sweep(self, *, lift: bool = False, timeout_s: float | None = None) -> Capture:
        """One full nod ramp (lower -> upper pitch limit); progress on the log.

        Keeps the scans whose beams overlap the ramp.
        """
        prof = self.nod_profile()
        period = _need(self.design).lidar.scan_period_s
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
        return Capture(keep, cap.joints, cap.lift_left, cap.lift_right, t_a, t_b, cap.ticks_ms)


class _ScanWindow:
    """What ``stop(scans, nod)`` sees of a capture that does not keep its scans: the
    number of scans, the first and the last (``len(w)``, ``w[0]``, ``w[-1]``)."""

    def __init__(self) -> None:
        self.n = 0
        self.first = self.last = None

    def append(self, scan) -> None:
        if self.n == 0:
            self.first = scan
        self.last = scan
        self.n += 1

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int):
        if self.n and i in (0, -self.n):
            return self.first
        if self.n and i in (-1, self.n - 1):
            return self.last
        raise IndexError(f"a capture with keep=False holds only its first and last scan, not {i}")


def _raise_sampler_error(samplers: Mapping[str, PositionSampler]) -> None:
    for name, smp in samplers.items():
        if smp.error is not None:
            raise DeviceError(f"{name} servo sampling stopped: {smp.error}") from smp.error


_STATS = ("beams", "error_codes", "no_nod", "mirror_moving", "blocked", "points")


class LiveAssembler:
    """Assemble scans while they stream in, each as soon as the servo samples cover it.

    A scan is assembled once every joint has a sample newer than its last beam; the
    samples it used are then pruned from the samplers behind the oldest scan not yet
    assembled (see :meth:`need_since_s`), so memory stays flat however long the capture
    runs and no scan ever lacks its samples. Interpolating on the covering samples gives
    each beam the same angles as assembling the whole capture at once (linear
    interpolation only looks at the two samples around a beam), so the points equal
    those of :meth:`Capture.assemble` / ``nodlidar replay`` of the same recording.

    Parameters
    ----------
    model : AssemblyModel
    lift_left, lift_right : MirrorLiftProfile
    sink : callable
        Receives each assembled :class:`PointCloud` chunk (``scan`` numbered from the
        first scan of the capture).
    batch_scans : int
        Assemble in batches of at least this many ready scans (vectorised work).
    assemble_kw
        Passed to :func:`~nodlidar.runtime.assembly.assemble` (frame, robot_from_sensor...).
    """

    def __init__(self, model: AssemblyModel, lift_left: MirrorLiftProfile,
                 lift_right: MirrorLiftProfile, sink: Callable[[PointCloud], None], *,
                 batch_scans: int = 20, **assemble_kw: Any) -> None:
        require(batch_scans >= 1, "batch_scans", batch_scans, ">= 1")
        self.model, self.sink = model, sink
        self.lift_left, self.lift_right = lift_left, lift_right
        self.batch_scans = int(batch_scans)
        self.assemble_kw = assemble_kw
        self.pending: list = []
        self.n_in = 0
        self.n_done = 0
        self.stats = dict.fromkeys(_STATS, 0)
        self.max_pending = 0
        self._span: list[tuple[float, float]] = []  # first/last beam time of each pending
        self._done_until = -math.inf

    def need_since_s(self) -> float:
        """Earliest time [s] a scan not yet assembled may need samples for: the oldest
        pending scan's first beam, or (none pending) the last assembled beam - the next
        scan's beams come after it (-inf before the first scan)."""
        if not self.pending:
            return self._done_until
        return self._span[0][0]

    def add(self, scan: Scan, samplers: Mapping[str, PositionSampler]) -> int:
        """Queue ``scan``; assemble the queued scans the samples cover. Returns how many
        scans were assembled now."""
        steps = np.asarray(scan.steps)
        t = self.model.lidar.beam_time_s(float(scan.stamp_s), [steps.min(), steps.max()])
        self.pending.append(scan)
        self._span.append((float(t[0]), float(t[1])))
        self.n_in += 1
        self.max_pending = max(self.max_pending, len(self.pending))
        if len(self.pending) < self.batch_scans:
            return 0
        joints = {k: smp.buffer.snapshot_around(self.need_since_s()) for k, smp in samplers.items()}
        return self._assemble(joints, final=False)

    def finish(self, joints: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> int:
        """Assemble every scan still queued with the capture's final samples."""
        return self._assemble(joints, final=True) if self.pending else 0

    def _assemble(self, joints, final: bool) -> int:
        def times(j):
            return j.host_time_s if hasattr(j, "host_time_s") else j[0]

        if final:
            n = len(self.pending)
        else:
            # every joint must have a sample past a scan's last beam
            cover = min((float(times(j)[-1]) if len(times(j)) else -math.inf)
                        for j in joints.values())
            n = 0
            while n < len(self._span) and self._span[n][1] < cover:
                n += 1
            if n == 0:
                return 0
        batch, self.pending = self.pending[:n], self.pending[n:]
        self._done_until = max(self._done_until, max(t1 for _, t1 in self._span[:n]))
        self._span = self._span[n:]
        cloud = assemble(self.model, ScanBatch.from_scans(batch), joints["nod"],
                         mirror_left=joints.get("mirror_left"),
                         mirror_right=joints.get("mirror_right"),
                         lift_left=self.lift_left, lift_right=self.lift_right, **self.assemble_kw)
        cloud = replace(cloud, scan=(cloud.scan + self.n_done).astype(np.int32))
        for k in _STATS:
            self.stats[k] += int(cloud.meta.get(k, 0))
        self.n_done += n
        self.sink(cloud)
        return n


_XYZ_DTYPE = {"float32": "<f4", "float64": "<f8"}


class CloudSpool:
    """Write a point cloud chunk by chunk (bounded memory) to ``path`` (.ply or .pcd,
    binary, ``xyz_type`` coordinates as :func:`~nodlidar.runtime.cloud.write_cloud`).

    Chunks go to ``path + '.part'`` as they come; :meth:`close` writes the header (the
    point count and the summed assembly counters are known only then) and moves the rows
    behind it, then removes the part file. The file equals :func:`write_cloud` of the
    concatenated chunks.
    """

    def __init__(self, path: str | Path, *, xyz_type: str = "float32"):
        require(xyz_type in _XYZ_DTYPE, "xyz_type", xyz_type, "'float32' or 'float64'")
        self.xyz_type = xyz_type
        self.path = Path(path)
        require(self.path.suffix.lower() in (".ply", ".pcd"), "--cloud", str(path),
                "a .ply or .pcd file name")
        self.part = self.path.with_name(self.path.name + ".part")
        self.n = 0
        self.first: PointCloud | None = None
        self._fh: IO[bytes] | None = None

    def __call__(self, cloud: PointCloud) -> None:
        from . import cloud as cloud_io

        structured = getattr(cloud_io, "structured", None) or cloud_io._structured

        if self._fh is None:
            self._fh = self.part.open("wb")
        if self.first is None:
            self.first = cloud.select(np.zeros(0, dtype=int))
        if len(cloud):
            self._fh.write(structured(cloud, _XYZ_DTYPE[self.xyz_type]).tobytes())
            self.n += len(cloud)

    def close(self, model: AssemblyModel, stats: Mapping[str, int], frame: str = "sensor") -> Path:
        """Finish the file: header with ``n`` points and ``stats`` as the cloud's meta."""
        from .assembly import PointCloud as _PC
        from .cloud import write_cloud

        fh = self._fh if self._fh is not None else self.part.open("wb")
        fh.close()
        if self.first is not None:
            empty = replace(self.first, meta=dict(stats))
        else:
            z = np.zeros(0)
            empty = _PC(np.zeros((0, 3)), z, z.astype(np.int32), z.astype(np.int16),
                        z.astype(np.int32), z, frame, model.design_name, model.design_hash,
                        model.calibration_id, model.deployed.mirror_names, dict(stats))
        head_file = self.path.with_name(self.path.name + ".head" + self.path.suffix)
        try:
            write_cloud(head_file, empty, xyz_type=self.xyz_type)
            head = head_file.read_bytes()
        finally:
            head_file.unlink(missing_ok=True)
        # the empty cloud's header says 0 points; the counts are whole header lines
        for key in (b"element vertex", b"WIDTH", b"POINTS"):
            head = head.replace(key + b" 0\n", key + b" %d\n" % self.n)
        with self.path.open("wb") as out, self.part.open("rb") as body:
            out.write(head)
            while chunk := body.read(1 << 22):
                out.write(chunk)
        self.part.unlink()
        return self.path

    def discard(self) -> None:
        if self._fh is not None:
            self._fh.close()
        self.part.unlink(missing_ok=True)


@dataclass
class Recorded:
    """What :func:`record_capture` recorded.

    Attributes
    ----------
    scans, samples : int
        Scans and servo samples written to the bag.
    t_start_s, t_end_s : float
        The capture's span (session clock [s]).
    cloud_points : int or None
        Points of the live cloud (None without ``cloud``).
    cloud_path : Path or None
    stats : dict
        Summed assembly counters of the live cloud (``beams``, ``no_nod``...).
    max_pending_scans : int
        Most scans ever waiting for their samples (the live assembly's lag).
    max_buffered_samples : int
        Most samples ever buffered by one sampler (bounded: flat memory).
    """

    scans: int
    samples: int
    t_start_s: float
    t_end_s: float
    cloud_points: int | None = None
    cloud_path: Path | None = None
    stats: dict = field(default_factory=dict)
    max_pending_scans: int = 0
    max_buffered_samples: int = 0


def record_capture(session: Session, recorder: BagRecorder, stop: Callable[[list, NodController], bool], *,
                   lift: bool = False, log_every: int = 10, cloud: str | Path | None = None,
                   assemble_kw: Mapping[str, Any] | None = None,
                   on_progress: Callable[[Recorded], None] | None = None) -> Recorded:
    """Capture while writing every scan and every servo sample to ``recorder`` (an open
    :class:`~nodlidar.runtime.bag.BagRecorder`), committing after each scan.

    With ``cloud`` (a .ply/.pcd path) the capture is also assembled live
    (:class:`LiveAssembler`, ``assemble_kw``: frame, robot_from_sensor...) and streamed to
    that file. Scans are not kept and samples are pruned once they are in the bag and no
    pending scan needs them: memory stays flat over hours, and the live cloud equals
    ``nodlidar replay`` of the bag. ``on_progress(Recorded)`` runs after every scan.
    """
    lidar = _need(session.design).lidar
    model = _need(session.model)
    written = {j: float("-inf") for j in JOINT_IDS}
    spool = CloudSpool(cloud) if cloud is not None else None
    live = (LiveAssembler(model, _need(session.lift_left), _need(session.lift_right), spool,
                          **dict(assemble_kw or {})) if spool is not None else None)
    info = Recorded(0, 0, float("nan"), float("nan"), cloud_path=spool.path if spool else None)

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
        if live is not None:
            live.add(scan, samplers)
        need = live.need_since_s() if live is not None else math.inf
        for name, smp in samplers.items():
            info.max_buffered_samples = max(info.max_buffered_samples, len(smp.buffer))
            # a sample may go once it is in the bag and no pending scan needs it
            smp.prune(min(need, written[name]))
        info.scans = recorder.scans
        if on_progress is not None:
            on_progress(info)
        if log_every and recorder.scans % log_every == 0:
            session.log(f"recorded {recorder.scans} scans")

    try:
        cap = session.capture(stop, lift=lift, on_scan=on_scan, keep=False)
        # the samplers have stopped: write what came after the last scan, so the bag
        # holds every sample the capture read
        for name, (t, a) in cap.joints.items():
            new = t > written[name]
            if new.any():
                recorder.write_samples(name, t[new], a[new])
        recorder.commit()
        info.scans, info.samples = recorder.scans, recorder.samples
        info.t_start_s, info.t_end_s = cap.t_start_s, cap.t_end_s
        if live is not None and spool is not None:
            live.finish(cap.joints)
            info.stats = dict(live.stats)
            info.max_pending_scans = live.max_pending
            info.cloud_points = spool.n
            spool.close(model, live.stats, (assemble_kw or {}).get("frame", "sensor"))
    except BaseException:
        if spool is not None:
            spool.discard()
        raise
    return info
