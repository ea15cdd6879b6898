"""Recording to and replaying from ROS 2 bags (``rosbags``, sqlite3 storage).

Topics (times are the session clock: ``time.monotonic`` on hardware, simulated seconds with
the simulated sensor; stamps = that clock, not wall time):

``/nodlidar/design`` (std_msgs/msg/String, once, first)
    JSON: the design TOML, the calibration TOML (or none), the lift profiles and the
    lidar's clock offset, so replay rebuilds the same BeamModels.
``/scan/raw`` (std_msgs/msg/UInt8MultiArray)
    Each verified SCIP message exactly as received; bag time = the scan's step-0 stamp
    [ns]. Replay decodes these (exact mm ranges).
``/scan`` (sensor_msgs/msg/LaserScan)
    The decoded scan for ROS tools (float32 ranges [m], NaN = error code).
``/joint_states`` (sensor_msgs/msg/JointState)
    One message per servo sample: name ``nod``, ``mirror_left`` or ``mirror_right``,
    position [rad], header stamp = sample time.

SIGKILL safety: rosbags' sqlite3 writer holds one transaction open until ``close()`` and
writes ``metadata.yaml`` only then, so a killed recording would lose everything. The
:class:`BagRecorder` commits after every scan (so a kill loses at most the scan being
written); :func:`recover_bag` rolls back the half-written transaction (sqlite's hot
journal) and writes the missing ``metadata.yaml`` from the database, after which the bag
opens with the rosbags reader. MCAP was rejected: rosbags' MCAP writer keeps its index
and footer until close and its reader refuses a file without them ("File end magic is
invalid", tested in tests/test_bag.py).
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DesignFileError, NodlidarError
from .actuators import MirrorLiftProfile

__all__ = ["BagRecorder", "BagContents", "read_bag", "read_recording", "recover_bag", "replay_bag",
           "JOINTS", "DESIGN_TOPIC", "RAW_TOPIC", "SCAN_TOPIC", "JOINT_TOPIC"]

DESIGN_TOPIC = "/nodlidar/design"
RAW_TOPIC = "/scan/raw"
SCAN_TOPIC = "/scan"
JOINT_TOPIC = "/joint_states"
JOINTS = ("nod", "mirror_left", "mirror_right")
FORMAT = 1


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


def _stamp(ts, t_s: float):
    ns = _ns(t_s)
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000,
                                                    nanosec=ns % 1_000_000_000)


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
    lift_left, lift_right : MirrorLiftProfile
    extra : dict, optional
        More JSON-serialisable metadata (e.g. the device info).

    Nothing is created before :meth:`open` (or ``with``).
    """

    def __init__(self, path: str | Path, design_toml: str, *, calibration_toml: str | None = None,
                 lift_left: MirrorLiftProfile | None = None,
                 lift_right: MirrorLiftProfile | None = None, extra: dict | None = None):
        self.path = Path(path)
        lift_left = lift_left or MirrorLiftProfile()
        lift_right = lift_right or lift_left
        self.header = {"format": FORMAT, "design_toml": design_toml,
                       "calibration_toml": calibration_toml,
                       "lift_left": _lift_dict(lift_left), "lift_right": _lift_dict(lift_right),
                       **(extra or {})}
        self.scans = 0
        self.samples = 0
        self._w = None

    def open(self) -> BagRecorder:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.errors import WriterError

        self._ts = ts = _typestore()
        if self.path.exists():
            raise NodlidarError(f"bag {self.path} exists already; choose a new --out directory")
        w = Writer(self.path, version=9, storage_plugin=StoragePlugin.SQLITE3)
        try:
            w.open()
        except WriterError as exc:
            raise NodlidarError(f"cannot create bag {self.path}: {exc}") from None
        self._w = w
        self._c_design = w.add_connection(DESIGN_TOPIC, "std_msgs/msg/String", typestore=ts)
        self._c_raw = w.add_connection(RAW_TOPIC, "std_msgs/msg/UInt8MultiArray", typestore=ts)
        self._c_scan = w.add_connection(SCAN_TOPIC, "sensor_msgs/msg/LaserScan", typestore=ts)
        self._c_joint = w.add_connection(JOINT_TOPIC, "sensor_msgs/msg/JointState", typestore=ts)
        msg = ts.types["std_msgs/msg/String"](data=json.dumps(self.header))
        w.write(self._c_design, 0, ts.serialize_cdr(msg, "std_msgs/msg/String"))
        self.commit()
        return self

    def commit(self) -> None:
        """Make everything written so far durable (survives SIGKILL)."""
        # rosbags' sqlite3 storage keeps one transaction open until close(); committing it
        # here is what makes a killed recording keep its scans.
        self._w.storage.conn.commit()

    def write_scan(self, scan, lidar, stamp_s: float | None = None) -> None:
        """One driver :class:`~nodlidar.runtime.urg.Scan` (raw frame + LaserScan)."""
        ts = self._ts
        t = scan.stamp_s if stamp_s is None else stamp_s
        ns = _ns(t)
        if scan.raw:
            raw = ts.types["std_msgs/msg/UInt8MultiArray"](
                layout=ts.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                data=np.frombuffer(scan.raw, dtype=np.uint8))
            self._w.write(self._c_raw, ns, ts.serialize_cdr(raw, "std_msgs/msg/UInt8MultiArray"))
        steps = np.asarray(scan.steps)
        cluster = int(scan.request.cluster) if scan.request is not None else 1
        inc = lidar.angular_resolution * cluster
        ls = ts.types["sensor_msgs/msg/LaserScan"](
            header=ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, t), frame_id="laser"),
            angle_min=float(lidar.bearing_from_step(steps[0])),
            angle_max=float(lidar.bearing_from_step(steps[-1])),
            angle_increment=float(inc), time_increment=float(lidar.step_period_s * cluster),
            scan_time=float(lidar.scan_period_s), range_min=float(lidar.range_min_m),
            range_max=float(lidar.range_max_m),
            ranges=np.asarray(scan.ranges_m, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32))
        self._w.write(self._c_scan, ns, ts.serialize_cdr(ls, "sensor_msgs/msg/LaserScan"))
        self.scans += 1

    def write_samples(self, joint: str, t_s: np.ndarray, angle_rad: np.ndarray) -> None:
        """Servo samples of ``joint`` (``nod``, ``mirror_left``, ``mirror_right``)."""
        if joint not in JOINTS:
            raise NodlidarError(f"joint {joint!r}; allowed: {', '.join(JOINTS)}")
        ts = self._ts
        JointState = ts.types["sensor_msgs/msg/JointState"]
        Header = ts.types["std_msgs/msg/Header"]
        empty = np.zeros(0)
        for t, a in zip(np.asarray(t_s, float), np.asarray(angle_rad, float)):
            m = JointState(header=Header(stamp=_stamp(ts, t), frame_id=""), name=[joint],
                           position=np.array([a]), velocity=empty, effort=empty)
            self._w.write(self._c_joint, _ns(t), ts.serialize_cdr(m, "sensor_msgs/msg/JointState"))
        self.samples += len(np.atleast_1d(t_s))

    def close(self) -> None:
        """Finish the bag (writes metadata.yaml)."""
        if self._w is not None:
            w, self._w = self._w, None
            w.close()

    def __enter__(self) -> BagRecorder:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


def _lift_dict(p: MirrorLiftProfile) -> dict[str, float]:
    return {"deployed_rad": p.deployed_rad, "lifted_rad": p.lifted_rad, "rate_rad_s": p.rate_rad_s}


# -- recovery ----------------------------------------------------------------------------
def recover_bag(path: str | Path) -> bool:
    """Make a bag whose recording was killed readable; return True if it was repaired.

    Rolls back the transaction that was being written (sqlite's hot journal; the rosbags
    reader opens the database as immutable and would not) and writes ``metadata.yaml``
    from the database's topics and messages. A bag that was closed normally is untouched.
    """
    p = Path(path)
    if not p.is_dir():
        raise DesignFileError(
            f"recording not found: {p} (expected a bag folder written by 'nodlidar record')")
    if (p / "metadata.yaml").exists():
        return False
    dbs = sorted(p.glob("*.db3"))
    if len(dbs) != 1:
        raise DesignFileError(f"{p}: no metadata.yaml and {len(dbs)} .db3 files; cannot recover")
    db = dbs[0]
    try:
        conn = sqlite3.connect(db)  # opening read-write rolls a hot journal back
        conn.execute("SELECT count(*) FROM messages").fetchone()
        conn.close()
    except sqlite3.DatabaseError as exc:
        raise DesignFileError(f"{db}: not a readable bag database ({exc})") from None
    _write_metadata(p, db)
    return True


def _write_metadata(bag: Path, db: Path) -> None:
    from io import StringIO

    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.metadata import dump_qos_v9
    from ruamel.yaml import YAML

    conn = sqlite3.connect(db)
    counts = dict(conn.execute("SELECT topic_id, count(*) FROM messages GROUP BY topic_id"))
    t0, t1 = conn.execute("SELECT min(timestamp), max(timestamp) FROM messages").fetchone()
    conn.close()
    with Reader(db) as r:
        conns = list(r.connections)
    count = sum(counts.values())
    start = int(t0) if t0 is not None else 0
    duration = int(t1 - t0) if t0 is not None else 0
    info = {
        "version": 9, "storage_identifier": "sqlite3", "relative_file_paths": [db.name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start}, "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": c.topic, "type": c.msgtype,
                                "serialization_format": c.ext.serialization_format,
                                "offered_qos_profiles": dump_qos_v9(c.ext.offered_qos_profiles),
                                "type_description_hash": c.digest},
             "message_count": counts.get(c.id, 0)} for c in conns],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": db.name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": count}],
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
        :class:`~nodlidar.runtime.urg.Scan`-like records (steps, ranges_m, ranges_mm,
        stamp_s, timestamp_ms, raw) decoded from the raw SCIP frames.
    joints : dict
        joint name -> (t_s (k,), angle_rad (k,)).
    laser_scans : int
        LaserScan messages in the bag.
    recovered : bool
        The bag had not been closed and was repaired by :func:`recover_bag`.
    """

    header: dict[str, Any]
    scans: list
    joints: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    laser_scans: int = 0
    recovered: bool = False

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
    """(topic, bag time [ns], deserialised message) of every message, in time order."""
    from rosbags.rosbag2 import Reader

    ts = _typestore()
    with Reader(Path(path)) as r:
        for conn, t, data in r.messages():
            yield conn.topic, t, ts.deserialize_cdr(data, conn.msgtype)


def read_bag(path: str | Path, dmin_mm: int | None = None) -> BagContents:
    """Read a recording (recovering it first if it was not closed).

    Scans come from the raw SCIP frames (exact millimetres, as the driver decoded them
    live); ``dmin_mm`` (default: the design's lidar) marks the error codes.
    """
    from rosbags.rosbag2.errors import ReaderError

    from .. import scip

    p = Path(path)
    recovered = recover_bag(p)
    header: dict | None = None
    scans: list[RecordedScan] = []
    jt: dict[str, list[float]] = {j: [] for j in JOINTS}
    ja: dict[str, list[float]] = {j: [] for j in JOINTS}
    n_ls = 0
    try:
        for topic, t_ns, msg in iter_messages(p):
            if topic == DESIGN_TOPIC:
                header = json.loads(msg.data)
            elif topic == RAW_TOPIC:
                raw = bytes(np.asarray(msg.data, dtype=np.uint8))
                fr = scip.decode_scan(raw)
                if dmin_mm is None:
                    dmin_mm = _dmin_from_header(header)
                scans.append(RecordedScan(len(scans), fr.request, fr.steps,
                                          scip.ranges_mm_to_m(fr.ranges_mm, dmin_mm), fr.ranges_mm,
                                          fr.timestamp_ms, t_ns * 1e-9, raw))
            elif topic == SCAN_TOPIC:
                n_ls += 1
            elif topic == JOINT_TOPIC:
                st = msg.header.stamp
                for name, pos in zip(msg.name, msg.position):
                    if name in jt:
                        jt[name].append(st.sec + st.nanosec * 1e-9)
                        ja[name].append(float(pos))
    except (ReaderError, FileNotFoundError) as exc:
        raise DesignFileError(f"{p}: cannot read bag ({exc})") from None
    if header is None:
        raise DesignFileError(f"{p}: no {DESIGN_TOPIC} message; not a nodlidar recording")
    joints = {j: (np.array(jt[j]), np.array(ja[j])) for j in JOINTS if jt[j]}
    return BagContents(header, scans, joints, n_ls, recovered)


def _dmin_from_header(header: dict | None) -> int:
    if header is None:
        raise DesignFileError("raw scan before the design message; not a nodlidar recording")
    return int(header.get("dmin_mm", 20))


def design_from_header(header: dict):
    """The solved Design (and the calibration's perturbations and id) a recording used."""
    import tomllib

    from ..solver import solve
    from ..spec import design_from_dict

    design = solve(design_from_dict(tomllib.loads(header["design_toml"]), source="<bag>"))
    perts, cal_id = None, "none"
    if header.get("calibration_toml"):
        import tempfile

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


def replay_bag(path: str | Path, **assemble_kw):
    """Read a recording and assemble it like the live session did.

    Returns ``(BagContents, PointCloud)``; ``assemble_kw`` go to
    :func:`~nodlidar.runtime.assembly.assemble` (frame, robot2sensor, world2robot...).
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
