"""A recording as ROS 2 tools see it, checked with readers nodlidar does not use to write:
the ``mcap`` reader with the ``mcap_ros2`` decoder, and rosbags' reader.

- PointCloud2 points equal ``replay``'s cloud (1 mm) with every per-point field;
- the TF tree resolves from every frame to ``nodlidar_base``, and the direct beams of each
  LaserScan, taken through /tf_static + /tf (nod interpolated at each ray's time from the
  stamp and time_increment), land on the PointCloud2's points;
- stamps monotonic and in this century; latched topics offered transient-local;
- the URDF has the frames of the TF tree, the nod and mirror joints about the right axes
  and the glass boxes of the solved design;
- an old (format 1, sqlite3, session-clock stamps, no PointCloud2) bag still replays.
"""

from __future__ import annotations

import contextlib
import io
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from nodlidar.cli import main
from nodlidar.hinge import side_lift_axes
from nodlidar.lidar import lidar_model
from nodlidar.paper import PAPER_DESIGN
from nodlidar.runtime import ros
from nodlidar.runtime.bag import read_bag, replay_bag

URG = lidar_model("URG-04LX")
Y2000_NS = 946_684_800 * 10**9
Y2100_NS = 4_102_444_800 * 10**9
LATCHED = ("/nodlidar/design", "/robot_description", "/tf_static")


def _run(*argv) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = main(list(argv))
    return code, out.getvalue()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """25 scans of the simulated sensor (as built with Table I) recorded to MCAP."""
    d = tmp_path_factory.mktemp("rec")
    code, out = _run("record", "--out", str(d / "bag"), "--scans", "25", "--sim-rate", "5",
                     "--perturb", "table1", "--json")
    assert code == 0
    summary = json.loads(out)
    contents, cloud = replay_bag(d / "bag")
    return d / "bag", summary, contents, cloud


def _decoded(bag: Path):
    """(topic -> [(log_time, ros message)], channel metadata) with mcap + mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    msgs: dict[str, list] = {}
    with next(bag.glob("*.mcap")).open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        meta = {c.topic: dict(c.metadata) for c in reader.get_summary().channels.values()}
        for _schema, channel, message, decoded in reader.iter_decoded_messages():
            msgs.setdefault(channel.topic, []).append((message.log_time, decoded))
    return msgs, meta


def _ns(stamp) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def _by_scan_step(scan, step) -> np.ndarray:
    return np.lexsort((np.asarray(step), np.asarray(scan)))


@pytest.mark.slow
def test_pointcloud2_equals_replay(recording):
    bag, summary, contents, cloud = recording
    msgs, _ = _decoded(bag)
    pcs = [m for _, m in msgs["/nodlidar/points"]]
    assert len(pcs) == summary["scans"] == summary["point_clouds"] == 25
    assert all(m.header.frame_id == ros.BASE_FRAME and m.height == 1 for m in pcs)
    a = np.concatenate([ros.pointcloud2_array(m) for m in pcs])
    assert summary["bag_points"] == len(a) == len(cloud) > 10_000
    ia, ib = _by_scan_step(a["scan"], a["step"]), _by_scan_step(cloud.scan, cloud.step)
    a = a[ia]
    xyz = np.stack([a["x"], a["y"], a["z"]], -1).astype(float)
    # the bar is 1 mm; float32 x y z alone is within 1 um at these ranges
    assert_allclose(xyz, cloud.xyz[ib], atol=1e-3, rtol=0)
    for f, attr in (("step", "step"), ("mirror", "mirror"), ("scan", "scan"),
                    ("range", "range_m")):
        assert_array_equal(a[f], getattr(cloud, attr)[ib])
    assert_array_equal(a["lifted"].astype(bool), cloud.lifted[ib])
    assert_allclose(a["nod"], cloud.nod_rad[ib], atol=1e-6, rtol=0)  # float32 field
    # t: epoch seconds = session clock + the recording's offset (float64: 0.3 us at 1.8e9 s)
    assert_allclose(a["t"] - contents.epoch_offset_ns * 1e-9, cloud.t[ib], atol=1e-6, rtol=0)
    assert (cloud.mirror >= 0).sum() > 1000  # reflected beams are in the comparison


@pytest.mark.slow
def test_stamps_monotonic_in_this_century_and_latched_topics(recording):
    bag, *_ = recording
    msgs, meta = _decoded(bag)
    for topic, items in msgs.items():
        log = [t for t, _ in items]
        assert log == sorted(log) and Y2000_NS < log[0] and log[-1] < Y2100_NS, topic
        if topic == "/tf":
            stamps = [_ns(m.transforms[0].header.stamp) for _, m in items]
        elif hasattr(items[0][1], "header"):
            stamps = [_ns(m.header.stamp) for _, m in items]
        else:
            continue
        # per joint for /joint_states and /tf (each servo's samples are in order)
        if topic in ("/tf", "/joint_states"):
            key = [(m.transforms[0].child_frame_id if topic == "/tf" else m.name[0])
                   for _, m in items]
            for k in set(key):
                s = [t for t, kk in zip(stamps, key) if kk == k]
                assert s == sorted(s), (topic, k)
        else:
            assert stamps == sorted(stamps), topic
    # LaserScan and PointCloud2 of a scan share the first ray's stamp (urg_node)
    ls = [_ns(m.header.stamp) for _, m in msgs["/scan"]]
    pc = [_ns(m.header.stamp) for _, m in msgs["/nodlidar/points"]]
    assert ls == pc
    for topic in LATCHED:
        assert "durability: transient_local" in meta[topic]["offered_qos_profiles"], topic
        assert len(msgs[topic]) == 1
    assert "transient_local" not in meta["/scan"]["offered_qos_profiles"]


def _tf_tree(msgs):
    static = {t.child_frame_id: (t.header.frame_id, t.transform)
              for _, m in msgs["/tf_static"] for t in m.transforms}
    dynamic: dict[str, list] = {}
    for _, m in msgs["/tf"]:
        for t in m.transforms:
            dynamic.setdefault(t.child_frame_id, []).append(
                (_ns(t.header.stamp), t.header.frame_id, t.transform))
    return static, dynamic


def _matrix(q) -> np.ndarray:
    """Rotation matrix of a geometry_msgs Quaternion (written out, no library)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@pytest.mark.slow
def test_tf_chain_puts_direct_laserscan_beams_on_the_cloud(recording):
    bag, _summary, _contents, cloud = recording
    msgs, _ = _decoded(bag)
    static, dynamic = _tf_tree(msgs)
    parent = {c: p for c, (p, _) in static.items()}
    parent.update({c: v[0][1] for c, v in dynamic.items()})
    frames = set(parent) | set(parent.values())
    for f in frames:  # every frame resolves to the base, without cycles
        seen = [f]
        while seen[-1] != ros.BASE_FRAME:
            seen.append(parent[seen[-1]])
            assert len(seen) < 10, seen
    assert {ros.LASER_FRAME, ros.HEAD_FRAME} <= frames
    assert {f"mirror_{n}" for n in cloud.mirror_names} <= frames
    assert parent[ros.LASER_FRAME] == ros.HEAD_FRAME
    assert parent[ros.HEAD_FRAME] == ros.BASE_FRAME

    # laser -> head (static), head -> base at each nod sample (dynamic)
    _, st = static[ros.LASER_FRAME]
    R_s, t_s = _matrix(st.rotation), np.array([st.translation.x, st.translation.y,
                                               st.translation.z])
    nod = dynamic[ros.HEAD_FRAME]
    t_nod = np.array([s for s, _, _ in nod]) * 1e-9
    Rn = np.array([_matrix(tr.rotation) for _, _, tr in nod])
    # the nod is a pitch: recover the angle from the matrix, interpolate at ray times
    ang = np.arctan2(Rn[:, 0, 2], Rn[:, 0, 0])
    assert_allclose(Rn[:, 1], np.tile([0, 1, 0], (len(Rn), 1)), atol=1e-12)
    tn = np.array([[tr.translation.x, tr.translation.y, tr.translation.z] for _, _, tr in nod])

    pts = np.concatenate([ros.pointcloud2_array(m) for _, m in msgs["/nodlidar/points"]])
    checked = 0
    for k, (_, ls) in enumerate(msgs["/scan"]):
        r = np.asarray(ls.ranges, float)
        i = np.arange(len(r))
        theta = ls.angle_min + i * ls.angle_increment
        t_ray = _ns(ls.header.stamp) * 1e-9 + i * ls.time_increment
        p_laser = np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros_like(r)], -1)
        a = np.interp(t_ray, t_nod, ang)
        c, s = np.cos(a), np.sin(a)
        p_head = p_laser @ R_s.T + t_s
        p_base = np.stack([c * p_head[:, 0] + s * p_head[:, 2], p_head[:, 1],
                           -s * p_head[:, 0] + c * p_head[:, 2]], -1) + tn[0]
        mine = pts[(pts["scan"] == k) & (pts["mirror"] == -1)]
        idx = mine["step"] - URG.step_min  # cluster 1: LaserScan index = step - first step
        got = np.stack([mine["x"], mine["y"], mine["z"]], -1)
        # 1 mm: float32 ranges (< 1 um) and the 1 ns stamp rounding
        assert_allclose(got, p_base[idx], atol=1e-3, rtol=0)
        checked += len(mine)
    assert checked > 5000
    # reflected beams are NOT where the LaserScan would draw them (why the PointCloud2)
    refl = pts[pts["mirror"] >= 0]
    assert len(refl) > 500


def _rpy_matrix(rpy: str) -> np.ndarray:
    """URDF rpy: roll about X, then pitch about Y, then yaw about Z (fixed axes)."""
    r, p, y = (float(v) for v in rpy.split())
    return _rz(y) @ _ry(p) @ _rx(r)


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> np.ndarray:  # written out here: the test reads URDF on its own
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@pytest.mark.slow
def test_urdf_matches_tf_and_design(recording):
    from nodlidar.runtime.bag import design_from_header

    bag, _summary, contents, _cloud = recording
    msgs, _ = _decoded(bag)
    root = ET.fromstring(msgs["/robot_description"][0][1].data)
    links = {e.get("name") for e in root.findall("link")}
    joints = {e.get("name"): e for e in root.findall("joint")}
    static, dynamic = _tf_tree(msgs)
    tf_frames = set(static) | set(dynamic) | {ros.BASE_FRAME}
    assert links == tf_frames  # the URDF draws exactly the frames TF carries
    for j in joints.values():  # URDF parent/child = TF parent/child
        child, par = j.find("child").get("link"), j.find("parent").get("link")
        tf_parent = static[child][0] if child in static else dynamic[child][0][1]
        assert tf_parent == par
    nod = joints["nod"]
    assert nod.get("type") == "revolute" and nod.find("axis").get("xyz") == "0 1 0"
    design, perts, _ = design_from_header(contents.header)
    thick = design.spec.mirror.glass_thickness_m
    axes = side_lift_axes(design)
    for m in design.patches(perts):
        j = joints[f"mirror_{m.name}"]
        assert j.get("type") == "revolute" and j.find("axis").get("xyz") == "1 0 0"
        ax = axes[design.mirror(m.name).side]
        lim = j.find("limit")
        assert_allclose([float(lim.get("lower")), float(lim.get("upper"))],
                        [0.0, design.spec.mirror.lift_angle_rad], atol=1e-11)
        o = j.find("origin")
        R = _rpy_matrix(o.get("rpy"))
        t = np.array([float(v) for v in o.get("xyz").split()])
        # joint x = the side's lift axis, turned so that the lift is positive; z = +z;
        # origin on the axis (the one hinge model, nodlidar.hinge)
        assert_allclose(R[:, 0], np.sign(ax.lift_rad) * ax.direction_, atol=1e-9)
        assert_allclose(R[:, 2], [0.0, 0.0, 1.0], atol=1e-9)
        off = t - ax.point_
        assert_allclose(off - (off @ ax.direction_) * ax.direction_, 0, atol=1e-9)
        vis = root.find(f"link[@name='mirror_{m.name}']/visual")
        box = vis.find("geometry/box").get("size")
        size = [float(v) for v in box.split()]
        assert_allclose(size, [m.s_max - m.s_min, thick, m.z_max - m.z_min], rtol=1e-8)
        # the box drawn in the joint frame is the (as built) glass: its front face's
        # corners are the patch's corners (1e-8 m: the URDF prints 9-12 digits)
        Rv = _rpy_matrix(vis.find("origin").get("rpy"))
        tv = np.array([float(v) for v in vis.find("origin").get("xyz").split()])
        front = np.array([[sx * size[0] / 2, -size[1] / 2, sz * size[2] / 2]
                          for sx, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        assert_allclose((front @ Rv.T + tv) @ R.T + t, m.corners(), atol=1e-8)
        # at the deployed angle (all sampled angles are deployed here) /tf has this pose
        _, par, tr = dynamic[f"mirror_{m.name}"][0]
        assert par == ros.LASER_FRAME
        assert_allclose(_matrix(tr.rotation), R, atol=1e-9)
        assert_allclose([tr.translation.x, tr.translation.y, tr.translation.z], t, atol=1e-9)


@pytest.mark.slow
def test_rosbags_reader_agrees(recording):
    """rosbags' own reader sees the same topics and the same PointCloud2 bytes."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    bag, *_ = recording
    msgs, _ = _decoded(bag)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(bag) as r:
        counts = {c.topic: c.msgcount for c in r.connections}
        pcs = [ts.deserialize_cdr(d, c.msgtype) for c, _, d in r.messages()
               if c.topic == "/nodlidar/points"]
    assert counts == {k: len(v) for k, v in msgs.items()}
    for a, (_, b) in zip(pcs, msgs["/nodlidar/points"]):
        assert bytes(a.data) == bytes(b.data) and a.point_step == b.point_step


def test_format1_sqlite3_bag_still_replays(tmp_path):
    """A bag as nodlidar wrote it before (sqlite3, stamps = session seconds, no epoch
    offset, no PointCloud2/TF) replays: the scans and samples come back on the session
    clock."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from nodlidar import scip

    def fake_scan(k, rng):
        mm = rng.integers(20, 5600, URG.n_steps).astype(np.int32)
        req = scip.DistanceRequest("MD", URG.step_min, URG.step_max, 1, 0, 0, "n1")
        raw = scip.encode_scan_reply(req.echo(0), "99", 1000 + 100 * k, mm, 3)
        return type("S", (), {"raw": raw, "stamp_s": 12.0 + 0.1 * k})

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(5)
    header = {"format": 1, "design_toml": Path(PAPER_DESIGN).read_text(),
              "calibration_toml": None, "dmin_mm": 20,
              "lift_left": {"deployed_rad": 0.0, "lifted_rad": 1.5707963267948966,
                            "rate_rad_s": 1.0},
              "lift_right": {"deployed_rad": 0.0, "lifted_rad": 1.5707963267948966,
                             "rate_rad_s": 1.0}}
    t = 12.0 + np.arange(0, 0.5, 0.004)
    with Writer(tmp_path / "old", version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        cd = w.add_connection("/nodlidar/design", "std_msgs/msg/String", typestore=ts)
        cr = w.add_connection("/scan/raw", "std_msgs/msg/UInt8MultiArray", typestore=ts)
        cj = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        w.write(cd, 0, ts.serialize_cdr(T["std_msgs/msg/String"](data=json.dumps(header)),
                                        "std_msgs/msg/String"))
        for k in range(4):
            s = fake_scan(k, rng)
            m = T["std_msgs/msg/UInt8MultiArray"](
                layout=T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                data=np.frombuffer(s.raw, dtype=np.uint8))
            w.write(cr, int(round(s.stamp_s * 1e9)),
                    ts.serialize_cdr(m, "std_msgs/msg/UInt8MultiArray"))
        for ti in t:
            ns = int(round(ti * 1e9))
            m = T["sensor_msgs/msg/JointState"](
                header=T["std_msgs/msg/Header"](
                    stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                    frame_id=""), name=["nod"], position=np.array([0.1]),
                velocity=np.zeros(0), effort=np.zeros(0))
            w.write(cj, ns, ts.serialize_cdr(m, "sensor_msgs/msg/JointState"))
    back = read_bag(tmp_path / "old")
    assert back.storage == "sqlite3" and back.clouds == 0 and back.epoch_offset_ns == 0
    assert_allclose([s.stamp_s for s in back.scans], 12.0 + 0.1 * np.arange(4), atol=1e-9)
    assert_allclose(back.joints["nod"][0], t, atol=1e-9)
    code, out = _run("replay", str(tmp_path / "old"), "--json")
    assert code == 0
    j = json.loads(out)
    assert j["format"] == 1 and j["scans"] == 4 and j["points"] > 1000


def test_mirror_joint_tf_is_the_lift_rotation_about_the_side_axis():
    """/tf of a mirror at a lift-servo angle = the rest pose turned about the joint's x
    axis; the glass it carries is where nodlidar.hinge.lifted_patch puts it (deployed,
    half way, lifted) and, lifted, where the CAD's carrier puts it
    (cad.mounts.mirror_face_poses, mm) - one hinge for every layer."""
    from nodlidar.cad.mounts import mirror_face_poses
    from nodlidar.hinge import lifted_patch
    from nodlidar.runtime.actuators import MirrorLiftProfile
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    design = solve(load_design(PAPER_DESIGN))
    axes = side_lift_axes(design)
    cad = mirror_face_poses(design)
    prof = MirrorLiftProfile(deployed_rad=0.2, lifted_rad=1.7)
    hz, lift = design.spec.mirror.hinge_z_m, design.spec.mirror.lift_angle_rad
    patches = design.patches()
    for (name, R0, t0), m in zip(ros.mirror_joint_frames(patches, design), patches,
                                 strict=True):
        ax = axes[design.mirror(name).side]
        corners_joint = (m.corners() - t0) @ R0   # rest pose: head -> joint frame
        for servo, frac in ((0.2, 0.0), (0.95, 0.5), (1.7, 1.0)):
            a = float(ros.mirror_joint_angle(servo, prof, hz, lift))
            assert_allclose(a, lift * frac, atol=1e-12)
            q = ros.quat_mul(ros.quaternion(R0), ros.quat_axis(0, a))
            x, y, z, w = q
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
            p_tf = corners_joint @ R.T + t0
            assert_allclose(p_tf, lifted_patch(m, ax, frac).corners(), atol=1e-12,
                            err_msg=name)
            if frac == 1.0:
                # 1e-9 mm: the same rotation by two routes (matrix vs quaternion)
                assert_allclose(p_tf * 1000, cad[name]["lifted"]["corners_mm"], atol=1e-9,
                                err_msg=name)


def test_cdr_template_bytes_equal_the_typestore():
    """The batched JointState/TF serialisation is byte for byte the typestore's."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def js(v):
        return T["sensor_msgs/msg/JointState"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                sec=v["sec"], nanosec=v["nsec"]), frame_id=""), name=["nod"],
            position=np.array([v["pos"]]), velocity=np.zeros(0), effort=np.zeros(0))

    tmpl = ros.CdrTemplate(ts, "sensor_msgs/msg/JointState", js,
                           {"sec": "<i4", "nsec": "<u4", "pos": "<f8"})
    rng = np.random.default_rng(7)
    sec = rng.integers(1_700_000_000, 1_900_000_000, 20)
    nsec = rng.integers(0, 10**9, 20)
    pos = rng.normal(0, 1, 20)
    rows = tmpl.batch(sec=sec, nsec=nsec, pos=pos)
    for i in range(20):
        ref = ts.serialize_cdr(js({"sec": int(sec[i]), "nsec": int(nsec[i]), "pos": pos[i]}),
                               "sensor_msgs/msg/JointState")
        assert rows[i].tobytes() == bytes(ref)
