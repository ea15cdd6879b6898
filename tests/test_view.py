"""nodlidar view: a Foxglove WebSocket client (the `websockets` package, the Foxglove
WebSocket protocol's subprotocol) connects to the printed URL, subscribes to the advertised channels
and decodes the messages with the schemas the server advertises (protobuf
FileDescriptorSets, read here by a small wire-format decoder - neither nodlidar's nor the
SDK's code). The MCAP file of the same run is read with the `mcap` package."""

import asyncio
import base64
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

ROOT = Path(__file__).resolve().parents[1]
# foxglove-sdk >= 0.2x negotiates only "foxglove.sdk.v1" (the same ws-protocol messages as
# "foxglove.websocket.v1", which older clients offer and this server answers with HTTP 400)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


# --- a minimal protobuf decoder driven by a FileDescriptorSet --------------------------------
def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = result = 0
    while True:
        b = buf[i]
        i += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, i
        shift += 7


def _fields(buf: bytes):
    """(field number, wire type, value) of every field; value: int or bytes."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wt = key >> 3, key & 7
        if wt == 0:
            v, i = _varint(buf, i)
        elif wt == 1:
            v, i = buf[i:i + 8], i + 8
        elif wt == 5:
            v, i = buf[i:i + 4], i + 4
        elif wt == 2:
            n, i = _varint(buf, i)
            v, i = buf[i:i + n], i + n
        else:
            raise ValueError(f"wire type {wt}")
        yield num, wt, v


class Schemas:
    """Message types of FileDescriptorSets: full name -> {number: (name, type, type_name,
    repeated)} (descriptor.proto field numbers)."""

    def __init__(self) -> None:
        self.types: dict[str, dict[int, tuple]] = {}

    def add_set(self, fds: bytes) -> None:
        for num, _, f in _fields(fds):
            if num == 1:   # FileDescriptorSet.file
                pkg = next((v.decode() for n, _, v in _fields(f) if n == 2), "")
                for n, _, m in _fields(f):
                    if n == 4:   # FileDescriptorProto.message_type
                        self._message(m, f".{pkg}" if pkg else "")

    def _message(self, m: bytes, scope: str) -> None:
        name = next(v.decode() for n, _, v in _fields(m) if n == 1)
        full = f"{scope}.{name}"
        table = self.types.setdefault(full, {})
        for n, _, v in _fields(m):
            if n == 2:   # DescriptorProto.field
                fd = {k: val for k, _, val in _fields(v)}
                table[fd[3]] = (fd[1].decode(), fd[5], fd.get(6, b"").decode(), fd.get(4) == 3)
            elif n == 3:   # nested_type
                self._message(v, full)

    def decode(self, type_name: str, buf: bytes) -> dict:
        table = self.types[type_name if type_name.startswith(".") else "." + type_name]
        out: dict = {}
        for num, wt, v in _fields(buf):
            if num not in table:
                continue
            name, tp, tname, rep = table[num]
            if rep and wt == 2 and tp not in (9, 11, 12):   # packed repeated scalars
                vals, j = [], 0
                while j < len(v):
                    if tp in (1, 6, 16):
                        vals.append(self._scalar(tp, v[j:j + 8]))
                        j += 8
                    elif tp in (2, 7, 15):
                        vals.append(self._scalar(tp, v[j:j + 4]))
                        j += 4
                    else:
                        x, j = _varint(v, j)
                        vals.append(self._scalar(tp, x))
                out.setdefault(name, []).extend(vals)
                continue
            if tp == 11 and tname.lstrip(".") not in {k.lstrip(".") for k in self.types}:
                val = bytes(v)   # a type the set does not define: left undecoded
            else:
                val = self.decode(tname, v) if tp == 11 else self._scalar(tp, v)
            if rep:
                out.setdefault(name, []).append(val)
            else:
                out[name] = val
        return out

    @staticmethod
    def _scalar(tp: int, v):
        if tp == 1:
            return struct.unpack("<d", v)[0]
        if tp == 2:
            return struct.unpack("<f", v)[0]
        if tp in (6, 7, 15, 16):   # fixed64, fixed32, sfixed32, sfixed64
            return struct.unpack({6: "<Q", 7: "<I", 15: "<i", 16: "<q"}[tp], v)[0]
        if tp == 9:
            return v.decode()
        if tp == 12:
            return bytes(v)
        if tp == 8:
            return bool(v)
        if tp in (3, 5, 14):   # int64/int32/enum: two's complement in a 64-bit varint
            return v - (1 << 64) if v >= 1 << 63 else v
        return v


# --- the packed cloud --------------------------------------------------------------------
# foxglove PackedElementField.NumericType: UINT8 = 1, INT8, UINT16, INT16, UINT32, INT32, FLOAT32, FLOAT64
_NUMERIC = {1: "<u1", 2: "<i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<f4", 8: "<f8"}


def cloud_points(msg: dict) -> np.ndarray:
    """A decoded foxglove.PointCloud -> structured array, from its own field list."""
    stride = msg["point_stride"]
    dt = np.dtype({"names": [f["name"] for f in msg["fields"]],
                   "formats": [_NUMERIC[f["type"]] for f in msg["fields"]],
                   "offsets": [f.get("offset", 0) for f in msg["fields"]], "itemsize": stride})
    data = msg.get("data", b"")
    assert len(data) % stride == 0
    return np.frombuffer(data, dt)


# --- running the command -----------------------------------------------------------------
def _start_view(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "nodlidar.cli", "view", "--sim", "--ws-port", "0",
                             "--duration", "120", *extra], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line: list[str] = []
    got = threading.Event()

    def read() -> None:
        line.append(proc.stdout.readline())
        got.set()

    threading.Thread(target=read, daemon=True).start()
    if not got.wait(120):   # server start only: generous for a loaded machine
        proc.kill()
        pytest.fail("nodlidar view printed no URL within 120 s")
    url = line[0].strip()
    if not url.startswith("ws://"):
        proc.kill()
        pytest.fail(f"no URL: {url!r} {proc.stderr.read()[-2000:]}")
    return proc, url


async def _client(url: str, want_points: int, budget_s: float, startup_s: float = 120.0) -> dict:
    """Subscribe to everything; collect until a cloud of ``want_points`` arrived (at most
    ``budget_s`` after the first cloud - the stream's rate - and ``startup_s`` for the
    sensor to start, which on a loaded machine takes what it takes)."""
    import websockets

    schemas = Schemas()
    async with websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None,
                                  open_timeout=30) as ws:
        assert ws.subprotocol in SUBPROTOCOLS
        channels: dict[int, dict] = {}
        topics = {"/nodlidar/cloud", "/nodlidar/mirrors", "/tf"}
        while not topics <= {c["topic"] for c in channels.values()}:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 30))
            if msg["op"] == "advertise":
                for c in msg["channels"]:
                    channels[c["id"]] = c
        subs = {}
        for k, c in enumerate(channels.values(), start=1):
            assert c["encoding"] == "protobuf" and c["schemaEncoding"] == "protobuf"
            schemas.add_set(base64.b64decode(c["schema"]))
            subs[k] = c
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": k, "channelId": c["id"]} for k, c in subs.items()]}))
        t_sub = time.monotonic()
        got: dict = {"cloud": None, "cloud_log_time": None, "mirrors": {}, "tf": None,
                     "first_cloud_s": None, "big_after_first_s": None, "clouds": 0}

        def deadline() -> float:
            if got["first_cloud_s"] is None:
                return t_sub + startup_s
            return t_sub + got["first_cloud_s"] + budget_s

        while time.monotonic() < deadline():
            try:
                raw = await asyncio.wait_for(ws.recv(), max(0.05, deadline() - time.monotonic()))
            except TimeoutError:
                break
            now = time.monotonic() - t_sub
            if isinstance(raw, str) or raw[0] != 0x01:   # 0x01: message data
                continue
            sub_id, log_time = struct.unpack_from("<IQ", raw, 1)
            c = subs[sub_id]
            body = schemas.decode(c["schemaName"], raw[13:])
            if c["topic"] == "/nodlidar/cloud":
                got["clouds"] += 1
                if got["first_cloud_s"] is None:
                    got["first_cloud_s"] = now
                got["cloud"], got["cloud_log_time"], got["cloud_raw"] = body, log_time, raw[13:]
                if got["big_after_first_s"] is None and len(cloud_points(body)) >= want_points:
                    got["big_after_first_s"] = now - got["first_cloud_s"]
            elif c["topic"] == "/nodlidar/mirrors":
                for e in body.get("entities", []):
                    got["mirrors"][e["id"]] = e
            elif c["topic"] == "/tf":
                got["tf"] = body
            if got["big_after_first_s"] is not None and got["mirrors"] and got["tf"]:
                break
        return got


@pytest.mark.slow
def test_view_serves_cloud_and_mirrors(tmp_path):
    from mcap.reader import make_reader

    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    mcap_path = tmp_path / "view.mcap"
    proc, url = _start_view(tmp_path, "--sim-rate", "5", "--no-tracks", "--mcap", str(mcap_path))
    try:
        assert url.startswith("ws://127.0.0.1:")   # bound to this machine only by default
        got = asyncio.run(_client(url, 10_000, 5.0))
    finally:
        proc.send_signal(signal.SIGINT)   # how a user ends a view: a clean summary, exit 0
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-3000:]
    assert "points" in out and "wrote" in out

    # >= 10 000 points within 5 s of the stream starting (the first cloud)
    n_last = len(cloud_points(got["cloud"])) if got["cloud"] else 0
    assert got["big_after_first_s"] is not None, (got["clouds"], n_last)
    print(f"first cloud {got['first_cloud_s']:.2f} s after subscribing; >= 10 000 points "
          f"{got['big_after_first_s']:.2f} s later")
    pts = cloud_points(got["cloud"])
    assert len(pts) >= 10_000 and got["cloud"]["frame_id"] == "sensor"
    assert {"x", "y", "z"} <= set(pts.dtype.names) and pts.dtype["x"] == np.float32
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(float)
    assert np.isfinite(xyz).all()

    design = solve(load_design(PAPER_DESIGN))
    # direct beams are `range` from the lidar's centre, wherever the nod put it:
    # o = pivot - R_y(nod) pivot (conventions.md); float32 fields carry ~1e-6 relative
    # error over <= 5.6 m, so 50 um is tight and still above rounding
    direct = pts["mirror"] == -1
    assert 0.1 < direct.mean() < 0.9   # both direct and reflected beams are there
    piv = np.asarray(design.spec.nod.pivot_m)
    nod = pts["nod"][direct].astype(float)
    c, s = np.cos(nod), np.sin(nod)
    rp = np.stack([c * piv[0] + s * piv[2], np.full_like(nod, piv[1]), -s * piv[0] + c * piv[2]], 1)
    o = piv - rp
    assert_allclose(np.linalg.norm(xyz[direct] - o, axis=1), pts["range"][direct], atol=5e-5)
    assert set(np.unique(pts["mirror"])) == {-1, 0, 1, 2, 3}

    # the mirror patches: one entity per mirror in the head frame, corners = the design's
    ents = got["mirrors"]
    assert set(ents) == {f"mirror/{m.name}" for m in design.mirrors}
    for m in design.patches(None):
        e = ents[f"mirror/{m.name}"]
        assert e["frame_id"] == "head" and e.get("frame_locked") is True
        tri = e["triangles"][0]
        corners = np.array([[p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0)] for p in tri["points"]])
        assert_allclose(corners, m.corners(), atol=1e-12)   # doubles on the wire: exact
        assert tri["indices"] == [0, 1, 2, 0, 2, 3]
    # /tf: world -> sensor -> head
    chain = {(t["parent_frame_id"], t["child_frame_id"]) for t in got["tf"]["transforms"]}
    assert chain == {("world", "sensor"), ("sensor", "head")}

    # the MCAP file holds the same stream: the cloud the client got, byte for byte
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: summary.statistics.channel_message_counts[i]
                  for i, c in summary.channels.items()}
        assert topics["/nodlidar/cloud"] >= 1 and topics["/nodlidar/mirrors"] >= 1
        same = [m for _, ch, m in reader.iter_messages(topics=["/nodlidar/cloud"])
                if m.log_time == got["cloud_log_time"]]
    assert len(same) == 1 and same[0].data == got["cloud_raw"]


def test_view_refuses_an_existing_mcap_and_sim_with_ports(tmp_path, capsys):
    from nodlidar.cli import main

    existing = tmp_path / "x.mcap"
    existing.write_bytes(b"")
    assert main(["view", "--mcap", str(existing), "--ws-port", "0"]) == 2
    assert main(["view", "--sim", "--port", "socket://127.0.0.1:1", "--servo-port",
                 "socket://127.0.0.1:2"]) == 2
    with pytest.raises(SystemExit) as exc:   # argparse: usage error
        main(["view", "--ws-port", "70000"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--mcap" in err and "--force" in err and "--sim" in err and "--ws-port" in err
    assert existing.read_bytes() == b""


def test_encoded_messages_decode_with_the_advertised_schemas():
    """Round trip of every message kind through the SDK's encoder and this file's decoder:
    tracks (position, heading arrow, deletion of ended tracks), the nod transform (the
    quaternion rotates the pivot's offset like conventions.md's R_y(nod))."""
    import foxglove
    from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

    from nodlidar.live import encode

    ctx = foxglove.Context()
    sch = Schemas()
    for ch_cls in (SceneUpdateChannel, FrameTransformsChannel):
        ch = ch_cls("/t" + ch_cls.__name__, context=ctx)
        sch.add_set(ch.schema().data)

    class St:
        def __init__(self, i, alive=True):
            self.track_id, self.x_m, self.y_m, self.v_m_s = i, 1.5, -0.25, 0.13
            self.heading_rad, self.confirmed, self.alive = np.radians(89.4), True, alive

    up = sch.decode("foxglove.SceneUpdate", encode.track_update([St(3), St(4, alive=False)], 123).encode())
    (e,) = up["entities"]
    assert e["id"] == "track/3" and e["frame_id"] == "world"
    cube = e["cubes"][0]["pose"]["position"]
    assert (cube["x"], cube["y"]) == (1.5, -0.25)
    arrow = e["arrows"][0]
    assert_allclose(arrow["shaft_length"], 0.13)
    q = arrow["pose"]["orientation"]   # yaw = heading: q = (0, 0, sin h/2, cos h/2)
    assert_allclose(2 * np.arctan2(q["z"], q["w"]), np.radians(89.4), atol=1e-12)
    assert [d["id"] for d in up["deletions"]] == ["track/4"]

    nod, piv = 0.3, (0.02, 0.0, -0.05)
    tf = sch.decode("foxglove.FrameTransforms", encode.frame_transforms(nod, piv, 0.4, 5).encode())
    head = next(t for t in tf["transforms"] if t["child_frame_id"] == "head")
    q = head["rotation"]
    qv = np.array([q.get("x", 0.0), q.get("y", 0.0), q.get("z", 0.0)])
    w = q["w"]
    p = np.array([1.0, 0.0, 0.0])   # the head's +x, rotated by the quaternion
    rot = p + 2 * w * np.cross(qv, p) + 2 * np.cross(qv, np.cross(qv, p))
    assert_allclose(rot, [np.cos(nod), 0.0, -np.sin(nod)], atol=1e-12)   # +pitch tips x down
    tr = head["translation"]
    t = np.array([tr.get("x", 0.0), tr.get("y", 0.0), tr.get("z", 0.0)])
    # the pivot is a fixed point of p_sensor = R p_head + t
    pv = np.asarray(piv)
    rpv = pv + 2 * w * np.cross(qv, pv) + 2 * np.cross(qv, np.cross(qv, pv))
    assert_allclose(rpv + t, pv, atol=1e-12)


def test_static_cloud_plot():
    """plot_cloud_3d: one scatter per mirror holding exactly that mirror's (finite) points,
    subsampled deterministically to max_points; axes in metres at equal scale."""
    import matplotlib.pyplot as plt  # noqa: TID251 (a plot test)

    from nodlidar.analysis.plots import plot_cloud_3d

    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(1000, 3)) * [2.0, 1.0, 0.5]
    xyz[5] = np.nan   # skipped
    mirror = rng.integers(-1, 4, size=1000)
    fig = plot_cloud_3d(xyz, mirror=mirror)
    ax = fig.axes[0]
    finite = np.isfinite(xyz).all(axis=1)
    for col in ax.collections:
        label = col.get_label().split(" (")[0]
        m = -1 if label == "direct" else int(label.split()[-1])
        drawn = np.column_stack(col._offsets3d)
        assert_allclose(drawn, xyz[finite & (mirror == m)])
    assert sum(len(c.get_offsets()) for c in ax.collections) == finite.sum()
    box = ax.get_box_aspect()   # proportional to the data's extent on each axis
    ext = np.nanmax(xyz, axis=0) - np.nanmin(xyz, axis=0)
    assert_allclose(box / box[0], ext / ext[0], rtol=1e-6)
    plt.close(fig)
    fig = plot_cloud_3d(xyz, mirror=mirror, max_points=100)
    assert 50 <= sum(len(c.get_offsets()) for c in fig.axes[0].collections) <= 100
    plt.close(fig)


@pytest.mark.slow
def test_view_mirrors_calibrated_and_tracks_in_the_mcap(tmp_path):
    """With --calibration the mirror entities are the calibrated patches (not the design's);
    on the paper's tracking scene the tracker's tracks are published (frame world), one id
    per track the summary counts. Read back from the --mcap file with the mcap package."""
    from mcap.reader import make_reader

    from nodlidar.calibration.calfile import Calibration, write_calibration
    from nodlidar.calibration.fit import design_hash
    from nodlidar.paper import PAPER_DESIGN, TABLE_I_PERTURBATIONS
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    design = solve(load_design(PAPER_DESIGN))
    cal = Calibration(id="cal-view", design_name=design.spec.name, design_hash=design_hash(design.spec),
                      created="2026-12-01T00:00:00+00:00", model="exact",
                      perturbations=dict(TABLE_I_PERTURBATIONS))
    write_calibration(tmp_path / "cal.toml", cal)
    mcap_path = tmp_path / "v.mcap"
    r = subprocess.run([sys.executable, "-m", "nodlidar.cli", "-q", "view", "--ws-port", "0",
                        "--scene", "paper-tracking", "--perturb", "table1", "--calibration",
                        str(tmp_path / "cal.toml"), "--sim-rate", "5", "--duration", "12",
                        "--mcap", str(mcap_path), "--json"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    first, summary = (json.loads(line) for line in r.stdout.splitlines())
    assert first["url"].startswith("ws://127.0.0.1:") and summary["scans"] > 0

    schemas = Schemas()
    mirrors, track_ids, track_frames = {}, set(), set()
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, msg in reader.iter_messages(topics=["/nodlidar/mirrors", "/nodlidar/tracks"]):
            if schema.name not in {k.lstrip(".") for k in schemas.types}:
                schemas.add_set(schema.data)
            up = schemas.decode(schema.name, msg.data)
            for e in up.get("entities", []):
                if channel.topic == "/nodlidar/mirrors":
                    mirrors[e["id"]] = e
                else:
                    track_ids.add(e["id"])
                    track_frames.add(e["frame_id"])
                    assert e["cubes"], e
            track_ids.update(d["id"] for d in up.get("deletions", []))
    calibrated = design.patches(dict(TABLE_I_PERTURBATIONS))
    nominal = design.patches(None)
    for m, n in zip(calibrated, nominal, strict=True):
        tri = mirrors[f"mirror/{m.name}"]["triangles"][0]
        corners = np.array([[p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0)] for p in tri["points"]])
        assert_allclose(corners, m.corners(), atol=1e-12)
        assert np.abs(corners - n.corners()).max() > 1e-3   # Table I moves every mirror by mm
    if summary["tracking"] != "on":
        pytest.fail(f"the tracker could not be built: {summary['tracking']}")
    assert track_ids and track_frames == {"world"}
    assert len(track_ids) == summary["tracks"]


@pytest.mark.slow
def test_view_with_device_ports(capsys):
    """The device path: the emulators served over TCP (real time, as hardware), given to
    view with --port/--servo-port like every runtime command; points from the assembled
    scans, the summary's counts consistent with the URL line."""
    from nodlidar.cli import main
    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.sim.sensor import SimulatedSensor
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    design = solve(load_design(PAPER_DESIGN))
    with SimulatedSensor(design, "room", transport="tcp", rate=1.0) as sim:
        code = main(["-q", "view", "--port", sim.lidar_url, "--servo-port", sim.servo_url,
                     "--ws-port", "0", "--duration", "4", "--no-tracks", "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    first, summary = (json.loads(line) for line in out.out.splitlines())
    assert summary["url"] == first["url"] and summary["scans"] >= 10
    assert summary["points"] > 0 and summary["messages"]["cloud"] >= 1
    # one transform per scan (none for a scan that came before the first nod sample) + the
    # initial one
    assert summary["scans"] - 3 <= summary["messages"]["tf"] - 1 <= summary["scans"]
