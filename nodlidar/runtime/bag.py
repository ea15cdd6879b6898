"""Recording to and replaying from ROS 2 bags (``rosbags``; MCAP storage by default,
sqlite3 on request).

Stamps are nanoseconds since the Unix epoch: the session clock (``time.monotonic`` on
hardware, simulated seconds with the simulated sensor) plus ``epoch_offset_ns``, fixed
when the recording opens (host epoch time minus session clock then) and stored in the
design message, so replay recovers the session clock exactly (integer ns).

Topics:

``/nodlidar/design`` (std_msgs/msg/String, latched: transient-local QoS)
    JSON: the design TOML, the calibration TOML (or none), the lift profiles, ``dmin_mm``,
    the lidar's clock offset and ``epoch_offset_ns``, so replay rebuilds the same
    BeamModels and clock.
``/robot_description`` (std_msgs/msg/String, latched)
    URDF of the head (:func:`nodlidar.runtime.ros.urdf`).
``/tf_static`` (tf2_msgs/msg/TFMessage, latched)
    The fixed frames (``nodlidar_head -> laser``).
``/tf`` (tf2_msgs/msg/TFMessage)
    ``nodlidar_base -> nodlidar_head`` at every nod servo sample; ``laser ->
    mirror_<name>`` at every lift-servo sample (see :mod:`nodlidar.runtime.ros`).
``/scan/raw`` (std_msgs/msg/UInt8MultiArray)
    Each verified SCIP message exactly as received; bag time = the scan's step-0 stamp.
    Replay decodes these (exact mm ranges).
``/scan`` (sensor_msgs/msg/LaserScan, frame ``laser``)
    The decoded scan for ROS tools (float32 ranges [m], NaN = error code); ``header.stamp``
    is the time of the first ray (``angle_min``), as urg_node stamps it.
``/nodlidar/points`` (sensor_msgs/msg/PointCloud2, frame ``nodlidar_base``)
    The assembled cloud of each scan, fields as in the cloud files
    (:data:`nodlidar.runtime.cloud.FIELDS`; ``t`` is epoch seconds here); ``header.stamp``
    = the scan's first ray. Written once the servo samples cover the scan's last beam,
    so it is exactly the replay's cloud of that scan.
``/joint_states`` (sensor_msgs/msg/JointState)
    One message per servo sample: name ``nod``, ``mirror_left`` or ``mirror_right``,
    position [rad], header stamp = sample time.

Crash safety: rosbags' writers keep data in memory until ``close()`` (sqlite3: one open
transaction; MCAP: a 1 MiB chunk buffer, index and footer) and write ``metadata.yaml``
only then. :meth:`BagRecorder.commit` runs after every scan: sqlite3 commits, MCAP closes
the chunk and flushes it to the file, so a SIGKILL loses at most the scan being written.
:func:`recover_bag` makes such a bag readable - sqlite3: rolls back the hot journal;
MCAP: keeps every complete record and appends a footer without summary (readers then
scan the file) - and writes ``metadata.yaml``. :func:`read_bag` repairs into a temporary
copy and never writes into the bag it reads (it may be on read-only media).
"""

from __future__ import annotations

import json
import math
import shutil
import sqlite3
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from struct import error as struct_error
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import DesignFileError, NodlidarError, ParameterError
from .servo_angles import MirrorLiftProfile, lift_profiles

if TYPE_CHECKING:
    from ..design import Design
    from ..geometry import Perturbation
    from ..lidar import LidarModel
    from .assembly import PointCloud
    from .urg import Scan

__all__ = ["BagRecorder", "BagContents", "BagWriteError", "read_bag", "read_recording",
           "recover_bag", "replay_bag", "iter_messages", "design_from_header", "STORAGES",
           "JOINTS", "DESIGN_TOPIC", "RAW_TOPIC", "SCAN_TOPIC", "JOINT_TOPIC", "CLOUD_TOPIC",
           "TF_TOPIC", "TF_STATIC_TOPIC", "DESCRIPTION_TOPIC"]

DESIGN_TOPIC = "/nodlidar/design"
RAW_TOPIC = "/scan/raw"
SCAN_TOPIC = "/scan"
JOINT_TOPIC = "/joint_states"
CLOUD_TOPIC = "/nodlidar/points"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
DESCRIPTION_TOPIC = "/robot_description"
JOINTS = ("nod", "mirror_left", "mirror_right")
STORAGES = ("mcap", "sqlite3")
FORMAT = 2  # 2: epoch stamps, PointCloud2, TF, URDF, MCAP (1: sqlite3, session-clock stamps)

# a recording that holds its PointCloud2 back longer than this many scans (servo samples
# stopped arriving) writes it with the samples it has
_MAX_PENDING_SCANS = 50


class BagWriteError(NodlidarError, OSError):
    """Writing the bag failed (disk full, I/O error, database error); the scans committed
    before are kept and ``nodlidar replay`` reads them."""


def _one_line(exc: BaseException, limit: int = 300) -> str:
    """``Type: message`` of an exception on one line (a YAML parser's message spans
    several), cut to ``limit`` characters."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


def _latched():
    """Transient-local, reliable, keep-last 1: what ROS 2 latched topics offer."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    inf = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                inf, inf, QosLiveliness.AUTOMATIC, inf, False)]


class BagRecorder:
    """Write a recording; commit after every scan.

    Parameters
    ----------
    path : str or Path
        Bag directory to create (must not exist).
    design_toml : str
        The design file's text.
    calibration_toml : str, optional
        The calibration file's text, if one is applied.
    lift_left, lift_right : MirrorLiftProfile, optional
        The lift servos' profiles, written to the header; a side not given takes the
        design's (:func:`~nodlidar.runtime.servo_angles.lift_profiles`, found at
        :meth:`open`).
    extra : dict, optional
        More JSON-serialisable metadata (e.g. the device info, ``dmin_mm``).
    storage : {"mcap", "sqlite3"}
    clock : callable, optional
        The session clock [s] (``Session.time_source``; default ``time.monotonic``): read
        once at :meth:`open` to fix ``epoch_offset_ns``.
    clouds : bool
        Write ``/nodlidar/points``, ``/tf``, ``/tf_static`` and ``/robot_description``
        (the design and calibration are solved from the recorded text at :meth:`open`, as
        replay does).

    Nothing is created before :meth:`open` (or ``with``).
    """

    def __init__(self, path: str | Path, design_toml: str, *, calibration_toml: str | None = None,
                 lift_left: MirrorLiftProfile | None = None,
                 lift_right: MirrorLiftProfile | None = None, extra: dict | None = None,
                 storage: str = "mcap", clock: Callable[[], float] | None = None,
                 clouds: bool = True):
        if storage not in STORAGES:
            raise ParameterError("--storage", storage, " or ".join(STORAGES))
        self.path = Path(path)
        self.storage = storage
        self._lift_given = (lift_left, lift_right)
        #: Each lift servo's profile (set by :meth:`open`).
        self.lift: dict[str, MirrorLiftProfile] = {}
        # lift_left/lift_right are filled in at open() (from the design if not given)
        self.header = {"format": FORMAT, "design_toml": design_toml,
                       "calibration_toml": calibration_toml, **(extra or {})}
        self.clock = clock or time.monotonic
        self.clouds = bool(clouds)
        self.scans = 0
        self.samples = 0
        self.points = 0
        self.clouds_written = 0
        self.committed_scans = 0
        self._w: Any = None
        self._pending: list[tuple[int, Any]] = []
        self._recent: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._done_until_s = -math.inf  # last beam of the last scan given its PointCloud2
        self._tmpl: dict[str, tuple] = {}

    # -- lifecycle ------------------------------------------------------------------------
    def open(self) -> BagRecorder:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.errors import WriterError

        from . import ros

        self._ts = ts = _typestore()
        if self.path.exists():
            raise NodlidarError(f"bag {self.path} exists already; choose a new --out directory")
        left, right = self._lift_given
        if self.clouds or left is None or right is None:
            # built from the recorded text exactly as replay builds it, so the per-scan
            # PointCloud2 is the replay's cloud
            design, perts, cal_id = design_from_header(self.header)
            dl, dr = lift_profiles(design)
            left, right = left or dl, right or dr
        if self.clouds:
            from .assembly import AssemblyModel

            self._model = AssemblyModel.from_design(design, perts, cal_id)
            self._design, self._patches = design, design.patches(perts)
        assert left is not None and right is not None  # given, or the design's just above
        self.lift = {"mirror_left": left, "mirror_right": right}
        self.header["lift_left"] = _lift_dict(left)
        self.header["lift_right"] = _lift_dict(right)
        now_s = float(self.clock())
        self.epoch_offset_ns = time.time_ns() - _ns(now_s)
        self.header["epoch_offset_ns"] = self.epoch_offset_ns
        self.header["storage"] = self.storage
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        w = Writer(self.path, version=9, storage_plugin=plugin)
        try:
            w.open()
        except (WriterError, OSError) as exc:
            raise NodlidarError(f"cannot create bag {self.path}: {exc}") from None
        self._w = w
        latched = _latched()
        try:
            self._c_design = w.add_connection(DESIGN_TOPIC, "std_msgs/msg/String", typestore=ts,
                                              offered_qos_profiles=latched)
            self._c_raw = w.add_connection(RAW_TOPIC, "std_msgs/msg/UInt8MultiArray", typestore=ts)
            self._c_scan = w.add_connection(SCAN_TOPIC, "sensor_msgs/msg/LaserScan", typestore=ts)
            self._c_joint = w.add_connection(JOINT_TOPIC, "sensor_msgs/msg/JointState",
                                             typestore=ts)
            t_open = _ns(now_s) + self.epoch_offset_ns
            msg = ts.types["std_msgs/msg/String"](data=json.dumps(self.header))
            w.write(self._c_design, t_open, ts.serialize_cdr(msg, "std_msgs/msg/String"))
            if self.clouds:
                self._c_cloud = w.add_connection(CLOUD_TOPIC, "sensor_msgs/msg/PointCloud2",
                                                 typestore=ts)
                self._c_tf = w.add_connection(TF_TOPIC, "tf2_msgs/msg/TFMessage", typestore=ts)
                self._c_tf_static = w.add_connection(TF_STATIC_TOPIC, "tf2_msgs/msg/TFMessage",
                                                     typestore=ts, offered_qos_profiles=latched)
                self._c_urdf = w.add_connection(DESCRIPTION_TOPIC, "std_msgs/msg/String",
                                                typestore=ts, offered_qos_profiles=latched)
                spec = self._design.spec
                self._pivot = np.asarray(spec.nod.pivot_m, float)
                urdf = ros.urdf(self._design, self._patches)
                m = ts.types["std_msgs/msg/String"](data=urdf)
                w.write(self._c_urdf, t_open, ts.serialize_cdr(m, "std_msgs/msg/String"))
                st = ros.static_transforms(self._pivot)
                m = ros.tf_message(ts, [(t_open, *x) for x in st])
                w.write(self._c_tf_static, t_open, ts.serialize_cdr(m, "tf2_msgs/msg/TFMessage"))
                # mirror joints: rest pose (quaternion) and the lift rotation per servo angle
                frames = ros.mirror_joint_frames(self._patches, self._design)
                side = {m.name: ("mirror_left" if m.side == "L" else "mirror_right")
                        for m in self._design.mirrors}
                self._mirror_frames = {
                    j: [(ros.mirror_frame(n), ros.quaternion(R), t) for n, R, t in frames
                        if side.get(n) == j] for j in ("mirror_left", "mirror_right")}
                self._hinge_z = spec.mirror.hinge_z_m
                self._lift_angle = spec.mirror.lift_angle_rad
        except (sqlite3.Error, OSError) as exc:
            raise self._failed(exc) from None
        self.commit()
        return self

    def commit(self) -> None:
        """Make everything written so far durable (survives SIGKILL): writes the
        PointCloud2 of every scan the servo samples now cover, then commits (sqlite3) or
        closes and flushes the chunk (MCAP)."""
        try:
            self._emit_clouds(final=False)
            st = self._w.storage
            if self.storage == "sqlite3":
                # rosbags' sqlite3 storage keeps one transaction open until close()
                st.conn.commit()
            else:
                # rosbags' MCAP storage buffers a chunk of up to 1 MiB in memory
                if st.chunk.bio.tell():
                    st.close_chunk()
                st.bio.flush()
        except (sqlite3.Error, OSError) as exc:
            raise self._failed(exc) from None
        self.committed_scans = self.scans

    def close(self) -> None:
        """Finish the bag (the remaining PointCloud2, index, metadata.yaml)."""
        if self._w is not None:
            w = self._w
            try:
                self._emit_clouds(final=True)
                w.close()
            except (sqlite3.Error, OSError) as exc:
                raise self._failed(exc) from None
            finally:
                self._w = None

    def abort(self) -> None:
        """Stop writing without finishing (after a write error): the file handles are
        closed, the committed scans stay readable (replay repairs the bag)."""
        w, self._w = self._w, None
        if w is None:
            return
        try:
            st = w.storage
            if self.storage == "sqlite3":
                st.conn.rollback()
                st.conn.close()
            else:
                st.bio.close()
        except (sqlite3.Error, OSError):
            pass  # the disk is what failed; nothing more to save

    def __enter__(self) -> BagRecorder:
        return self.open()

    def __exit__(self, exc_type, *exc) -> None:
        # finish the bag on any way out (Ctrl-C is how a long recording is stopped); after
        # a write error (_failed aborted it) there is nothing left to finish
        try:
            self.close()
        except BagWriteError:
            if exc_type is None:
                raise
            # the original exception says what happened; the committed scans are kept

    def _failed(self, exc: BaseException) -> BagWriteError:
        self.abort()
        return BagWriteError(
            f"writing bag {self.path} failed after {self.committed_scans} committed scans "
            f"({_one_line(exc)}); those scans are kept ('nodlidar replay "
            f"{self.path}' reads them)")

    def _write(self, conn, t_ns: int, msg, msgtype: str) -> None:
        self._w.write(conn, t_ns, self._ts.serialize_cdr(msg, msgtype))

    # -- messages -------------------------------------------------------------------------
    def write_scan(self, scan: Scan, lidar: LidarModel, stamp_s: float | None = None) -> None:
        """One driver :class:`~nodlidar.runtime.urg.Scan` (raw frame, LaserScan; its
        PointCloud2 follows once the servo samples cover it)."""
        try:
            self._write_scan(scan, lidar, stamp_s)
        except (sqlite3.Error, OSError) as exc:
            raise self._failed(exc) from None

    def _write_scan(self, scan, lidar, stamp_s: float | None) -> None:
        from . import ros

        ts = self._ts
        t = scan.stamp_s if stamp_s is None else stamp_s
        off = self.epoch_offset_ns
        ns = _ns(t) + off
        if scan.raw:
            raw = ts.types["std_msgs/msg/UInt8MultiArray"](
                layout=ts.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                data=np.frombuffer(scan.raw, dtype=np.uint8))
            self._write(self._c_raw, ns, raw, "std_msgs/msg/UInt8MultiArray")
        steps = np.asarray(scan.steps)
        cluster = int(scan.request.cluster) if scan.request is not None else 1
        inc = lidar.angular_resolution * cluster
        # urg_node's convention: the stamp is the time of the first ray (angle_min)
        first_ns = _ns(float(lidar.beam_time_s(t, steps[0]))) + off
        ls = ts.types["sensor_msgs/msg/LaserScan"](
            header=ts.types["std_msgs/msg/Header"](stamp=ros.stamp(ts, first_ns),
                                                   frame_id=ros.LASER_FRAME),
            angle_min=float(lidar.bearing_from_step(steps[0])),
            angle_max=float(lidar.bearing_from_step(steps[-1])),
            angle_increment=float(inc), time_increment=float(lidar.step_period_s * cluster),
            scan_time=float(lidar.scan_period_s), range_min=float(lidar.range_min_m),
            range_max=float(lidar.range_max_m),
            ranges=np.asarray(scan.ranges_m, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32))
        self._write(self._c_scan, first_ns, ls, "sensor_msgs/msg/LaserScan")
        if self.clouds:
            self._pending.append((self.scans, _RecScan(scan, t)))
        self.scans += 1

    def write_samples(self, joint: str, t_s: np.ndarray, angle_rad: np.ndarray) -> None:
        """Servo samples of ``joint`` (``nod``, ``mirror_left``, ``mirror_right``): t_s (k,)
        [s] session clock, angle_rad (k,) [rad]."""
        if joint not in JOINTS:
            raise NodlidarError(f"joint {joint!r}; allowed: {', '.join(JOINTS)}")
        t_s = np.atleast_1d(np.asarray(t_s, float))
        angle_rad = np.atleast_1d(np.asarray(angle_rad, float))
        try:
            self._write_samples(joint, t_s, angle_rad)
        except (sqlite3.Error, OSError) as exc:
            raise self._failed(exc) from None
        self.samples += len(t_s)
        if self.clouds and len(t_s):
            if joint in self._recent:
                t0, a0 = self._recent[joint]
                t_s, angle_rad = np.concatenate([t0, t_s]), np.concatenate([a0, angle_rad])
            self._recent[joint] = (t_s, angle_rad)

    def _templates(self, joint: str):
        """CdrTemplates of this joint's JointState and /tf messages (made once)."""
        from . import ros

        if joint in self._tmpl:
            return self._tmpl[joint]
        ts = self._ts
        T = ts.types
        empty = np.zeros(0)

        def stamp(v, i=""):
            return T["builtin_interfaces/msg/Time"](sec=v[f"sec{i}"], nanosec=v[f"nsec{i}"])

        js = ros.CdrTemplate(ts, "sensor_msgs/msg/JointState", lambda v: T[
            "sensor_msgs/msg/JointState"](
                header=T["std_msgs/msg/Header"](stamp=stamp(v), frame_id=""), name=[joint],
                position=np.array([v["pos"]]), velocity=empty, effort=empty),
            {"sec": "<i4", "nsec": "<u4", "pos": "<f8"})
        tf = None
        if self.clouds:
            if joint == "nod":
                trs = [(ros.BASE_FRAME, ros.HEAD_FRAME, self._pivot)]
            else:
                trs = [(ros.LASER_FRAME, f, p) for f, _q, p in self._mirror_frames[joint]]
            fields = {}
            for i in range(len(trs)):
                fields.update({f"sec{i}": "<i4", f"nsec{i}": "<u4", f"qx{i}": "<f8",
                               f"qy{i}": "<f8", f"qz{i}": "<f8", f"qw{i}": "<f8"})

            def build(v):
                return ros.tf_message(ts, [
                    (0, parent, child, (v[f"qx{i}"], v[f"qy{i}"], v[f"qz{i}"], v[f"qw{i}"]), p)
                    for i, (parent, child, p) in enumerate(trs)])

            def with_stamps(v):  # tf_message stamps from ns: set sec/nanosec afterwards
                m = build(v)
                for i, tr in enumerate(m.transforms):
                    tr.header.stamp = stamp(v, i)
                return m

            tf = ros.CdrTemplate(ts, "tf2_msgs/msg/TFMessage", with_stamps, fields) if trs \
                else None
        self._tmpl[joint] = (js, tf)
        return js, tf

    def _write_samples(self, joint: str, t_s: np.ndarray, angle_rad: np.ndarray) -> None:
        from . import ros

        if not len(t_s):
            return
        js, tf = self._templates(joint)
        ns = np.round(t_s * 1e9).astype(np.int64) + self.epoch_offset_ns
        sec, nsec = ns // 1_000_000_000, ns % 1_000_000_000
        rows = js.batch(sec=sec, nsec=nsec, pos=angle_rad)
        rows_tf = None
        if tf is not None:
            if joint == "nod":
                # pitch about y: (0, sin(a/2), 0, cos(a/2))
                h = angle_rad / 2
                cols: dict[str, Any] = {"sec0": sec, "nsec0": nsec, "qx0": np.zeros_like(h), "qy0": np.sin(h),
                                        "qz0": np.zeros_like(h), "qw0": np.cos(h)}
            else:
                ang = ros.mirror_joint_angle(angle_rad, self.lift[joint], self._hinge_z,
                                             self._lift_angle)
                qa = (np.sin(ang / 2), np.zeros_like(ang), np.zeros_like(ang), np.cos(ang / 2))
                cols = {}
                for i, (_f, q0, _p) in enumerate(self._mirror_frames[joint]):
                    x, y, z, w = ros.quat_mul(q0, qa)  # rest pose, then the lift about x
                    cols.update({f"sec{i}": sec, f"nsec{i}": nsec, f"qx{i}": x, f"qy{i}": y,
                                 f"qz{i}": z, f"qw{i}": w})
            rows_tf = tf.batch(**cols)
        w = self._w
        for i, t in enumerate(ns.tolist()):
            w.write(self._c_joint, t, rows[i].tobytes())
            if rows_tf is not None:
                w.write(self._c_tf, t, rows_tf[i].tobytes())

    # -- per-scan clouds --------------------------------------------------------------------
    def _emit_clouds(self, final: bool) -> None:
        """PointCloud2 of every pending scan whose last beam the samples cover (all of
        them if ``final``); then drop samples no pending scan can need."""
        if not self.clouds or not self._pending:
            return
        from . import ros
        from .assembly import ScanBatch, assemble
        from .cloud import structured

        lidar = self._model.lidar
        nod = self._recent.get("nod")
        while self._pending:
            k, rs = self._pending[0]
            t_last = float(lidar.beam_time_s(rs.stamp_s, np.asarray(rs.scan.steps)[-1]))
            covered = all(j in self._recent and self._recent[j][0][-1] >= t_last for j in JOINTS)
            if not (final or covered or len(self._pending) > _MAX_PENDING_SCANS):
                break
            self._pending.pop(0)
            self._done_until_s = max(self._done_until_s, t_last)
            if nod is None or len(nod[0]) == 0:
                continue  # no nod samples at all: replay cannot assemble this scan either
            cloud = assemble(self._model, ScanBatch.from_scans([rs.scan], [rs.stamp_s]), nod,
                             mirror_left=self._recent.get("mirror_left"),
                             mirror_right=self._recent.get("mirror_right"),
                             lift_left=self.lift["mirror_left"],
                             lift_right=self.lift["mirror_right"])
            arr = structured(cloud)
            arr["scan"] = k
            # epoch seconds: the session clock plus the recording's offset
            arr["t"] = cloud.t + self.epoch_offset_ns * 1e-9
            steps = np.asarray(rs.scan.steps)
            first_ns = _ns(float(lidar.beam_time_s(rs.stamp_s, steps[0]))) + self.epoch_offset_ns
            msg = ros.pointcloud2(self._ts, arr, ros.BASE_FRAME, first_ns)
            self._write(self._c_cloud, first_ns, msg, "sensor_msgs/msg/PointCloud2")
            self.points += len(arr)
            self.clouds_written += 1
        # keep the samples a pending scan may still interpolate from (one before its
        # start); with none pending, the next scan's beams come after the last one written
        keep_from = self._pending[0][1].stamp_s if self._pending else self._done_until_s
        for j, (t, a) in list(self._recent.items()):
            i = max(int(np.searchsorted(t, keep_from)) - 2, 0)
            if i:
                self._recent[j] = (t[i:], a[i:])


@dataclass(frozen=True)
class _RecScan:
    scan: Any
    stamp_s: float


def _lift_dict(p: MirrorLiftProfile) -> dict[str, float]:
    return {"deployed_rad": p.deployed_rad, "lifted_rad": p.lifted_rad, "rate_rad_s": p.rate_rad_s}


# -- recovery ----------------------------------------------------------------------------
def _storage_file(p: Path) -> tuple[str, Path]:
    dbs, mcaps = sorted(p.glob("*.db3")), sorted(p.glob("*.mcap"))
    if len(dbs) + len(mcaps) != 1:
        raise DesignFileError(f"{p}: no metadata.yaml and {len(dbs)} .db3 + {len(mcaps)} .mcap "
                              "files; cannot recover (expected one storage file)")
    return ("sqlite3", dbs[0]) if dbs else ("mcap", mcaps[0])


def needs_recovery(path: str | Path) -> bool:
    """The bag has no metadata.yaml (its recording was killed)."""
    p = Path(path)
    if not p.is_dir():
        raise DesignFileError(
            f"recording not found: {p} (expected a bag folder written by 'nodlidar record')")
    return not (p / "metadata.yaml").exists()


def recover_bag(path: str | Path, dest: str | Path | None = None) -> bool:
    """Make a bag whose recording was killed readable; return True if it was repaired.

    ``dest`` (a directory that does not exist): the repaired bag is written there and
    ``path`` is only read. Without ``dest`` the bag is repaired in place. sqlite3: the
    transaction being written is rolled back (sqlite's hot journal; the rosbags reader
    opens the database as immutable and would not). MCAP: every complete record is kept
    and a footer without summary appended. Then ``metadata.yaml`` is written from the
    storage file. A bag that was closed normally is left alone (and not copied).
    """
    p = Path(path)
    if not needs_recovery(p):
        return False
    kind, src = _storage_file(p)
    if dest is not None:
        d = Path(dest)
        d.mkdir(parents=True)
        if kind == "sqlite3":
            for f in p.iterdir():  # the database and its journal (the journal matters)
                if f.is_file() and f.name.startswith(src.name):
                    shutil.copyfile(f, d / f.name)
        p, src = d, d / src.name
    if kind == "sqlite3":
        try:
            conn = sqlite3.connect(src)  # opening read-write rolls a hot journal back
            conn.execute("SELECT count(*) FROM messages").fetchone()
            conn.close()
        except sqlite3.Error as exc:
            raise DesignFileError(f"{src}: not a readable bag database ({exc})") from None
    else:
        out = src if dest is not None else src.with_name(src.name + ".tmp")
        _repair_mcap(Path(path) / src.name if dest is not None else src, out)
        if out != src:
            out.replace(src)
    _write_metadata(p, src, kind)
    return True


def _repair_mcap(src: Path, dst: Path) -> int:
    """Rewrite an MCAP file cut short (no footer, as a kill leaves it) into ``dst`` with
    the ``mcap`` library's writer: every complete record (schemas, channels with their
    QoS metadata, messages) up to the cut, then index and summary. Indexed, because the
    messages of a recording are not written in time order (servo samples arrive after
    the scan they cover) and rosbags refuses an unindexed file out of order. Returns the
    messages kept."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Header, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    n = 0
    with src.open("rb") as fh, dst.open("wb") as out:
        w: Writer | None = None
        schemas: dict[int, int] = {0: 0}
        channels: dict[int, int] = {}
        try:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Header):
                    w = Writer(out, compression=CompressionType.NONE)
                    w.start(profile=rec.profile, library=rec.library)
                elif w is None:
                    break
                elif isinstance(rec, Schema) and rec.id not in schemas:
                    schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel) and rec.id not in channels:
                    channels[rec.id] = w.register_channel(
                        rec.topic, rec.message_encoding, schemas.get(rec.schema_id, 0),
                        dict(rec.metadata))
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    w.add_message(channels[rec.channel_id], rec.log_time, rec.data,
                                  rec.publish_time, rec.sequence)
                    n += 1
        except (McapError, ValueError, EOFError, struct_error):
            pass  # the cut: a record (or chunk) not completely written
        if w is None:
            raise DesignFileError(f"{src}: not an MCAP file (no header); cannot recover")
        w.finish()
    return n


def _write_metadata(bag: Path, storage_file: Path, kind: str) -> None:
    from io import StringIO

    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.metadata import dump_qos_v9
    from ruamel.yaml import YAML

    try:
        with Reader(storage_file) as r:  # rosbags reads a storage file without metadata
            conns = list(r.connections)
            count = r.message_count
            start = r.start_time if count else 0
            duration = r.duration if count else 0
    except Exception as exc:  # noqa: BLE001 - any reader failure is one line to the user
        raise DesignFileError(f"{storage_file}: cannot recover ({_one_line(exc)})") from None
    exts: list[tuple[Any, Any]] = [(c, c.ext) for c in conns]  # rosbag2 connections
    info = {
        "version": 9, "storage_identifier": kind, "relative_file_paths": [storage_file.name],
        "duration": {"nanoseconds": int(duration)},
        "starting_time": {"nanoseconds_since_epoch": int(start)}, "message_count": int(count),
        "topics_with_message_count": [
            {"topic_metadata": {"name": c.topic, "type": c.msgtype,
                                "serialization_format": ext.serialization_format,
                                "offered_qos_profiles": dump_qos_v9(ext.offered_qos_profiles),
                                "type_description_hash": c.digest},
             "message_count": int(c.msgcount)} for c, ext in exts],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": storage_file.name,
                   "starting_time": {"nanoseconds_since_epoch": int(start)},
                   "duration": {"nanoseconds": int(duration)}, "message_count": int(count)}],
        "custom_data": {"recovered": "true"}, "ros_distro": "rosbags",
    }
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    s = StringIO()
    yaml.dump({"rosbag2_bagfile_information": info}, s)
    tmp = bag / "metadata.yaml.tmp"
    tmp.write_text(s.getvalue(), "utf8")
    tmp.replace(bag / "metadata.yaml")


# -- reading -----------------------------------------------------------------------------
@dataclass
class BagContents:
    """A recording read back.

    Attributes
    ----------
    header : dict
        The ``/nodlidar/design`` JSON (design_toml, calibration_toml, lift profiles...).
    scans : list
        :class:`RecordedScan` records (steps, ranges_m, ranges_mm, stamp_s [s, session
        clock], timestamp_ms, raw) decoded from the raw SCIP frames.
    joints : dict
        joint name -> (t_s (k,) [s, session clock], angle_rad (k,)).
    laser_scans : int
        LaserScan messages in the bag.
    recovered : bool
        The bag had not been closed; it was read through a repaired temporary copy.
    skipped : dict
        topic -> messages that could not be decoded (skipped and counted).
    clouds : int
        PointCloud2 messages in the bag.
    storage : str
        ``mcap`` or ``sqlite3``.
    """

    header: dict[str, Any]
    scans: list
    joints: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    laser_scans: int = 0
    recovered: bool = False
    skipped: dict[str, int] = field(default_factory=dict)
    clouds: int = 0
    storage: str = ""

    @property
    def epoch_offset_ns(self) -> int:
        """Bag stamps minus the session clock [ns] (0 for format-1 bags)."""
        return int(self.header.get("epoch_offset_ns", 0))

    def lift_profiles(self) -> tuple[MirrorLiftProfile, MirrorLiftProfile]:
        return (MirrorLiftProfile(**self.header["lift_left"]),
                MirrorLiftProfile(**self.header["lift_right"]))


@dataclass(frozen=True, eq=False)
class RecordedScan:
    """A scan decoded from a recorded raw SCIP frame (duck-types the driver's Scan)."""

    seq: int
    request: Any
    steps: np.ndarray
    ranges_m: np.ndarray
    ranges_mm: np.ndarray
    timestamp_ms: int
    stamp_s: float
    raw: bytes = b""


def iter_messages(path: str | Path) -> Iterator[tuple[str, int, object]]:
    """(topic, bag time [ns], deserialised message) of every message, in time order
    (rosbags' reader; the bag must be closed or recovered)."""
    from rosbags.rosbag2 import Reader

    ts = _typestore()
    with Reader(Path(path)) as r:
        for conn, t, data in r.messages():
            yield conn.topic, t, ts.deserialize_cdr(data, conn.msgtype)


def _check_header(header: Any, p: Path) -> dict:
    """The design message's JSON, checked: one line naming what is wrong."""
    if not isinstance(header, dict):
        raise DesignFileError(f"{p}: {DESIGN_TOPIC} is not a JSON object; not a nodlidar recording")
    fmt = header.get("format", 1)
    if not isinstance(fmt, int) or isinstance(fmt, bool) or not 1 <= fmt <= FORMAT:
        raise DesignFileError(f"{p}: recording format {fmt!r}; this nodlidar reads 1 .. {FORMAT}")
    if not isinstance(header.get("design_toml"), str):
        raise DesignFileError(f"{p}: {DESIGN_TOPIC} has no design_toml text")
    cal = header.get("calibration_toml")
    if cal is not None and not isinstance(cal, str):
        raise DesignFileError(f"{p}: {DESIGN_TOPIC} calibration_toml is {type(cal).__name__}; "
                              "allowed: text or null")
    for side in ("lift_left", "lift_right"):
        v = header.get(side)
        keys = {"deployed_rad", "lifted_rad", "rate_rad_s"}
        if not (isinstance(v, dict) and set(v) == keys and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v.values())):
            raise DesignFileError(f"{p}: {DESIGN_TOPIC} {side} = {v!r}; allowed: numbers "
                                  f"{', '.join(sorted(keys))}")
        try:
            MirrorLiftProfile(**v)
        except ParameterError as exc:
            raise DesignFileError(f"{p}: {DESIGN_TOPIC} {side}: {exc}") from None
    for key in ("dmin_mm", "epoch_offset_ns"):
        v = header.get(key, 0)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise DesignFileError(f"{p}: {DESIGN_TOPIC} {key} = {v!r}; allowed: an integer >= 0")
    return header


def read_bag(path: str | Path, dmin_mm: int | None = None) -> BagContents:
    """Read a recording (MCAP or sqlite3, format 1 or 2).

    A bag whose recording was killed is repaired into a temporary copy (the bag itself
    is never written: it may be on read-only media). Scans come from the raw SCIP frames
    (exact millimetres, as the driver decoded them live); ``dmin_mm`` (default: the
    recorded one) marks the error codes. Messages that cannot be decoded (a corrupted
    frame) are skipped and counted in :attr:`BagContents.skipped`.

    Raises
    ------
    DesignFileError
        Missing or unreadable bag, malformed metadata or design message (one line).
    """
    p = Path(path)
    if p.is_file() and p.suffix in (".mcap", ".db3"):
        p = p.parent  # the storage file was given: read its bag folder
    if needs_recovery(p):
        with tempfile.TemporaryDirectory(prefix="nodlidar-recover-") as tmp:
            copy = Path(tmp) / "bag"
            recover_bag(p, copy)
            out = _read_bag(copy, dmin_mm, p)
        out.recovered = True
        return out
    return _read_bag(p, dmin_mm, p)


def _read_bag(p: Path, dmin_mm: int | None, name: Path) -> BagContents:
    from .. import scip

    ts = _typestore()
    header: dict | None = None
    scans: list[RecordedScan] = []
    jt: dict[str, list[int]] = {j: [] for j in JOINTS}
    ja: dict[str, list[float]] = {j: [] for j in JOINTS}
    n_ls = n_cloud = 0
    skipped: Counter[str] = Counter()
    raws: list[tuple[int, bytes]] = []
    from rosbags.rosbag2 import Reader

    try:
        with Reader(p) as r:
            wanted = {DESIGN_TOPIC, RAW_TOPIC, SCAN_TOPIC, JOINT_TOPIC, CLOUD_TOPIC}
            for conn, t_ns, data in r.messages():
                if conn.topic not in wanted:
                    continue
                if conn.topic == SCAN_TOPIC:
                    n_ls += 1
                    continue
                if conn.topic == CLOUD_TOPIC:
                    n_cloud += 1
                    continue
                try:
                    msg = ts.deserialize_cdr(data, conn.msgtype)
                except Exception:  # noqa: BLE001 - a corrupted message: skip and count
                    skipped[conn.topic] += 1
                    continue
                if conn.topic == DESIGN_TOPIC:
                    if header is None:
                        try:
                            header = json.loads(msg.data)
                        except ValueError:
                            raise DesignFileError(f"{name}: {DESIGN_TOPIC} is not JSON; not a "
                                                  "nodlidar recording") from None
                        header = _check_header(header, name)
                elif conn.topic == RAW_TOPIC:
                    raws.append((t_ns, bytes(np.asarray(msg.data, dtype=np.uint8))))
                elif conn.topic == JOINT_TOPIC:
                    st = msg.header.stamp
                    for jn, pos in zip(msg.name, msg.position):
                        if jn in jt:
                            jt[jn].append(int(st.sec) * 1_000_000_000 + int(st.nanosec))
                            ja[jn].append(float(pos))
    except NodlidarError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises many types for a broken bag
        raise DesignFileError(f"{name}: cannot read bag ({_one_line(exc)})") from None
    if header is None:
        raise DesignFileError(f"{name}: no {DESIGN_TOPIC} message; not a nodlidar recording")
    storage = "mcap" if any(p.glob("*.mcap")) else "sqlite3"
    off = int(header.get("epoch_offset_ns", 0))
    if dmin_mm is None:
        dmin_mm = int(header.get("dmin_mm", 20))
    for t_ns, raw in raws:
        try:
            fr = scip.decode_scan(raw)
            ranges_m = scip.ranges_mm_to_m(fr.ranges_mm, dmin_mm)
        except Exception:  # noqa: BLE001 - an undecodable frame: skip and count
            skipped[RAW_TOPIC] += 1
            continue
        scans.append(RecordedScan(len(scans), fr.request, fr.steps, ranges_m, fr.ranges_mm,
                                  fr.timestamp_ms, (t_ns - off) * 1e-9, raw))
    joints = {}
    for j in JOINTS:
        if jt[j]:
            joints[j] = ((np.array(jt[j], dtype=np.int64) - off) * 1e-9, np.array(ja[j]))
    return BagContents(header, scans, joints, n_ls, False, dict(skipped), n_cloud, storage)


def design_from_header(header: dict[str, Any]
                       ) -> tuple[Design, dict[str, Perturbation] | None, str]:
    """The solved Design (and the calibration's perturbations and id) a recording used."""
    import tomllib

    from ..solver import solve
    from ..spec import design_from_dict

    try:
        doc = tomllib.loads(header["design_toml"])
    except tomllib.TOMLDecodeError as exc:
        raise DesignFileError(f"the recording's design is not valid TOML ({exc})") from None
    design = solve(design_from_dict(doc, source="<bag>"))
    perts, cal_id = None, "none"
    if header.get("calibration_toml"):
        from ..calibration.calfile import load_calibration

        # the calibration owner's loader reads files; give it the recorded text as one
        with tempfile.TemporaryDirectory() as d:
            f = Path(d) / "calibration.toml"
            f.write_text(header["calibration_toml"])
            cal = load_calibration(f, design)
        perts, cal_id = cal.perturbations, cal.id
    return design, perts, cal_id


def read_recording(path: str | Path) -> BagContents:
    """:func:`read_bag` for consumers that assemble a recording (replay, tracking,
    calibration): the bag must hold at least one scan and the nod servo's samples.

    Raises
    ------
    DesignFileError
        The bag is missing or unreadable, or has no scans or no nod samples.
    """
    contents = read_bag(path)
    if not contents.scans:
        raise DesignFileError(f"{path}: the recording has no scans")
    if "nod" not in contents.joints:
        raise DesignFileError(f"{path}: the recording has no nod servo samples")
    return contents


def replay_bag(path: str | Path, **assemble_kw: Any) -> tuple[BagContents, PointCloud]:
    """Read a recording and assemble it like the live session did.

    Returns ``(BagContents, PointCloud)``; ``assemble_kw`` go to
    :func:`~nodlidar.runtime.assembly.assemble` (frame, robot_from_sensor, world_from_robot...).
    """
    from .assembly import AssemblyModel, ScanBatch, assemble

    contents = read_recording(path)
    design, perts, cal_id = design_from_header(contents.header)
    model = AssemblyModel.from_design(design, perts, cal_id)
    left, right = contents.lift_profiles()
    cloud = assemble(model, ScanBatch.from_scans(contents.scans), contents.joints["nod"],
                     mirror_left=contents.joints.get("mirror_left"),
                     mirror_right=contents.joints.get("mirror_right"),
                     lift_left=left, lift_right=right, **assemble_kw)
    return contents, cloud
