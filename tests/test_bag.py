"""ROS 2 bag recording (MCAP and sqlite3): round trip through the rosbags reader, kill
safety and recovery (read-only: into a temporary copy), undecodable frames skipped and
counted, malformed bags as one-line errors, write errors (disk full) as one line."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from nodlidar import scip
from nodlidar.cli import main
from nodlidar.errors import DesignFileError, NodlidarError
from nodlidar.lidar import lidar_model
from nodlidar.paper import PAPER_DESIGN
from nodlidar.runtime.bag import (
    RAW_TOPIC,
    BagRecorder,
    BagWriteError,
    iter_messages,
    read_bag,
    read_recording,
    recover_bag,
    replay_bag,
)

ROOT = Path(__file__).resolve().parents[1]
DESIGN_TOML = Path(PAPER_DESIGN).read_text()
URG = lidar_model("URG-04LX")
STORAGES = ["mcap", "sqlite3"]
# 2000-01-01T00:00:00Z: stamps must be in this century (not 1970 or session seconds)
Y2000_NS = 946_684_800 * 10**9


def fake_scan(k: int, rng) -> SimpleNamespace:
    """A scan as the driver delivers it, with its raw SCIP frame."""
    mm = rng.integers(20, 5600, URG.n_steps).astype(np.int32)
    mm[rng.random(URG.n_steps) < 0.05] = 0  # error code
    req = scip.DistanceRequest("MD", URG.step_min, URG.step_max, 1, 0, 0, "n1")
    raw = scip.encode_scan_reply(req.echo(0), "99", (1000 + 100 * k) % (1 << 24), mm, 3)
    fr = scip.decode_scan(raw)
    return SimpleNamespace(request=fr.request, steps=fr.steps, ranges_mm=fr.ranges_mm,
                           ranges_m=scip.ranges_mm_to_m(fr.ranges_mm, 20), raw=raw,
                           stamp_s=12.0 + 0.1 * k, timestamp_ms=fr.timestamp_ms)


def recorder(path, storage="mcap", **kw) -> BagRecorder:
    # the session clock reads 11.9 s when the recording opens (just before the scans)
    return BagRecorder(path, DESIGN_TOML, extra={"dmin_mm": 20}, storage=storage,
                       clock=lambda: 11.9, **kw)


def write_bag(path, n_scans: int = 5, storage: str = "mcap", corrupt: tuple[int, ...] = ()):
    """A closed bag of ``n_scans`` fake scans with nod and left-mirror samples covering
    them; the raw frames of the scans in ``corrupt`` get one byte flipped."""
    rng = np.random.default_rng(0)
    scans = [fake_scan(k, rng) for k in range(n_scans)]
    t = 12.0 + np.arange(0, 0.1 * n_scans + 0.1, 0.004)
    with recorder(path, storage) as rec:
        for k, s in enumerate(scans):
            if k in corrupt:
                raw = bytearray(s.raw)
                raw[len(raw) // 2] ^= 0x01  # a data byte: the line's checksum fails
                s = SimpleNamespace(**{**vars(s), "raw": bytes(raw)})
            rec.write_scan(s, URG)
            rec.commit()
        rec.write_samples("nod", t, 0.1 * np.sin(t))
        rec.write_samples("mirror_left", t[::10], np.zeros(len(t[::10])))
    return scans, t


def snapshot(d: Path) -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in sorted(d.iterdir())}


@pytest.mark.parametrize("storage", STORAGES)
def test_round_trip_with_rosbags_reader(tmp_path, storage):
    scans, t = write_bag(tmp_path / "b", storage=storage)
    assert len(list((tmp_path / "b").glob("*.mcap" if storage == "mcap" else "*.db3"))) == 1
    topics: dict[str, list] = {}
    stamps: dict[str, list[int]] = {}
    for topic, t_ns, msg in iter_messages(tmp_path / "b"):  # the rosbags reader
        topics.setdefault(topic, []).append(msg)
        stamps.setdefault(topic, []).append(t_ns)
    n_joint = len(t) + len(t[::10])
    assert {k: len(v) for k, v in topics.items()} == {
        "/nodlidar/design": 1, "/robot_description": 1, "/tf_static": 1, "/scan/raw": 5,
        "/scan": 5, "/nodlidar/points": 5, "/joint_states": n_joint, "/tf": n_joint}
    for topic, ns in stamps.items():
        assert ns[0] > Y2000_NS and ns == sorted(ns), topic
    header = json.loads(topics["/nodlidar/design"][0].data)
    off = header["epoch_offset_ns"]
    assert header["format"] == 2 and header["storage"] == storage
    ls = topics["/scan"][2]
    # LaserScan: float32 metres (exact mm -> float32: relative 6e-8), NaN for error codes
    assert_allclose(ls.ranges, scans[2].ranges_m, rtol=1e-7, equal_nan=True)
    assert_allclose(ls.angle_min, URG.bearing_from_step(URG.step_min), rtol=1e-6)
    assert_allclose(ls.angle_increment, 2 * np.pi / 1024, rtol=1e-6)
    # header.stamp = the first ray: step-0 time + step_min step periods (integer ns)
    first = int(round(URG.beam_time_s(12.2, URG.step_min) * 1e9)) + off
    assert ls.header.stamp.sec * 10**9 + ls.header.stamp.nanosec == first
    assert topics["/nodlidar/points"][2].header.stamp == ls.header.stamp

    back = read_bag(tmp_path / "b")
    assert not back.recovered and len(back.scans) == 5 and back.laser_scans == 5
    assert back.clouds == 5 and back.skipped == {} and back.storage == storage
    for a, b in zip(scans, back.scans):
        assert_array_equal(b.ranges_mm, a.ranges_mm)  # the raw frames decode exactly
        assert b.raw == a.raw
        # epoch ns minus the integer offset: the session clock back to the ns rounding
        assert abs(b.stamp_s - a.stamp_s) <= 0.5e-9 + 1e-15 * a.stamp_s
    assert_allclose(back.joints["nod"][0], t, atol=1e-9, rtol=0)
    assert_array_equal(back.joints["nod"][1], 0.1 * np.sin(t))  # float64 positions exact
    assert set(back.joints) == {"nod", "mirror_left"}
    # the storage file given instead of the folder reads the same bag
    f = next((tmp_path / "b").glob("*.mcap" if storage == "mcap" else "*.db3"))
    assert [s.raw for s in read_bag(f).scans] == [s.raw for s in back.scans]


def test_existing_directory_refused(tmp_path):
    (tmp_path / "b").mkdir()
    with pytest.raises(NodlidarError, match="exists"):
        BagRecorder(tmp_path / "b", DESIGN_TOML).open()
    with pytest.raises(NodlidarError, match="storage"):
        BagRecorder(tmp_path / "c", DESIGN_TOML, storage="rosbag1")


@pytest.mark.parametrize("storage", STORAGES)
def test_unclosed_bag_read_without_writing_into_it(tmp_path, storage):
    """A recorder that was never closed (as after SIGKILL): no metadata.yaml. read_bag
    reads every committed scan (not the uncommitted one) through a repaired temporary
    copy and leaves the bag byte for byte as it was (read-only media); recover_bag
    repairs in place on request."""
    rng = np.random.default_rng(1)
    rec = recorder(tmp_path / "b", storage).open()
    t = 12.0 + np.arange(0, 0.6, 0.004)
    for k in range(4):
        rec.write_scan(fake_scan(k, rng), URG)
        rec.write_samples("nod", t[(t >= 12 + 0.1 * k) & (t < 12.1 + 0.1 * k)], np.zeros(25))
        rec.commit()
    rec.write_scan(fake_scan(4, rng), URG)  # in flight: not committed
    assert not (tmp_path / "b" / "metadata.yaml").exists()
    # the process "dies" here: nothing is committed, flushed or closed any more
    shutil.copytree(tmp_path / "b", tmp_path / "copy")  # the files as a kill leaves them
    before = snapshot(tmp_path / "copy")
    os.chmod(tmp_path / "copy", 0o555)
    try:
        back = read_bag(tmp_path / "copy")
    finally:
        os.chmod(tmp_path / "copy", 0o755)
    assert back.recovered and len(back.scans) == 4
    assert snapshot(tmp_path / "copy") == before  # nothing written into the bag
    assert recover_bag(tmp_path / "copy") is True
    assert recover_bag(tmp_path / "copy") is False  # idempotent
    assert (tmp_path / "copy" / "metadata.yaml").exists()
    again = read_bag(tmp_path / "copy")
    assert not again.recovered and len(again.scans) == 4
    rec.abort()


def test_mcap_cut_short_is_repaired_for_every_reader(tmp_path):
    """Why the repair: an MCAP file cut short (no footer, as a kill leaves it) is refused
    by rosbags ("File end magic is invalid"); after recover_bag both rosbags and the
    independent mcap reader read every message before the cut, whatever byte it is at
    (a cut in the summary at the end loses no message)."""
    from mcap.exceptions import EndOfFile, McapError
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2 import Reader

    _, _ = write_bag(tmp_path / "b", n_scans=6)
    full = next((tmp_path / "b").glob("*.mcap")).read_bytes()
    with Reader(tmp_path / "b") as r:
        total = r.message_count
    for cut in (len(full) // 3, len(full) // 2, len(full) - 200):
        d = tmp_path / f"cut{cut}"
        d.mkdir()
        (d / "cut.mcap").write_bytes(full[:cut])
        with pytest.raises(Exception, match="magic|empty"):
            with Reader(d / "cut.mcap") as r:
                list(r.messages())
        if cut < len(full) // 2 + 1:
            # the mcap library: its seeking reader fails too (it reads the last bytes as
            # a footer); its stream reader yields the complete records and then stops at
            # the cut (EndOfFile) - what the repair builds on
            with (d / "cut.mcap").open("rb") as fh, pytest.raises(McapError):
                list(make_reader(fh).iter_messages())
            n_rec = 0
            with (d / "cut.mcap").open("rb") as fh, pytest.raises(EndOfFile):
                for _ in StreamReader(fh).records:
                    n_rec += 1
            assert n_rec > 10
        assert recover_bag(d) is True
        with Reader(d) as r:
            n_rosbags = sum(1 for _ in r.messages())
        with (d / "cut.mcap").open("rb") as fh:
            n_mcap = sum(1 for _ in make_reader(fh).iter_messages())
        assert 0 < n_rosbags == n_mcap
        assert (n_rosbags == total) if cut == len(full) - 200 else (n_rosbags < total)


def test_recover_bad_paths(tmp_path):
    with pytest.raises(DesignFileError, match="not found"):
        recover_bag(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DesignFileError, match="cannot recover"):
        recover_bag(tmp_path / "empty")
    with recorder(tmp_path / "nodesign", clouds=False) as rec:
        pass
    with pytest.raises(DesignFileError, match="no scans"):
        replay_bag(tmp_path / "nodesign")
    assert rec.scans == 0
    rng = np.random.default_rng(2)
    with recorder(tmp_path / "nonod") as rec:
        rec.write_scan(fake_scan(0, rng), URG)
        rec.write_samples("mirror_left", np.array([12.0]), np.array([0.0]))
    with pytest.raises(DesignFileError, match="no nod servo samples"):
        read_recording(tmp_path / "nonod")
    with pytest.raises(DesignFileError, match="not found"):
        read_recording(tmp_path / "nope")
    write_bag(tmp_path / "good")
    good = read_recording(tmp_path / "good")
    assert len(good.scans) == 5 and "nod" in good.joints


@pytest.mark.parametrize("storage", STORAGES)
def test_bad_frame_is_skipped_and_counted(tmp_path, storage, capsys):
    """One corrupted raw frame no longer makes the bag unreadable: the other scans are
    read, the bad one counted; replay warns (exit 0), --strict refuses (exit 2)."""
    scans, _ = write_bag(tmp_path / "b", n_scans=6, storage=storage, corrupt=(2,))
    back = read_bag(tmp_path / "b")
    assert back.skipped == {RAW_TOPIC: 1}
    assert [s.raw for s in back.scans] == [s.raw for k, s in enumerate(scans) if k != 2]
    assert main(["replay", str(tmp_path / "b")]) == 0
    err = capsys.readouterr().err
    assert "warning: skipped 1 undecodable messages (/scan/raw: 1)" in err
    assert main(["replay", str(tmp_path / "b"), "--strict"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot be decoded" in err[0]
    assert main(["replay", str(tmp_path / "b"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["skipped"] == {RAW_TOPIC: 1} and out["scans"] == 5 and out["storage"] == storage


def _raw_bag(path: Path, design_payload: str, storage: str = "mcap") -> Path:
    """A bag whose design message carries ``design_payload`` verbatim (rosbags writer)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c = w.add_connection("/nodlidar/design", "std_msgs/msg/String", typestore=ts)
        w.write(c, Y2000_NS + 1, ts.serialize_cdr(ts.types["std_msgs/msg/String"](
            data=design_payload), "std_msgs/msg/String"))
    return path


def _good_header() -> dict:
    return {"format": 2, "design_toml": DESIGN_TOML, "calibration_toml": None,
            "lift_left": {"deployed_rad": 0.0, "lifted_rad": 1.5, "rate_rad_s": 1.0},
            "lift_right": {"deployed_rad": 0.0, "lifted_rad": 1.5, "rate_rad_s": 1.0},
            "dmin_mm": 20, "epoch_offset_ns": 0}


def _edit_header(**kw) -> str:
    h = _good_header()
    h.update(kw)
    return json.dumps(h)


MALFORMED = {
    "metadata not yaml": lambda d: (d / "metadata.yaml").write_text("{: [\n"),
    "metadata no version": lambda d: (d / "metadata.yaml").write_text(
        (d / "metadata.yaml").read_text().replace("version: 9", "versio: 9")),
    "metadata version 99": lambda d: (d / "metadata.yaml").write_text(
        (d / "metadata.yaml").read_text().replace("version: 9", "version: 99")),
    "metadata storage": lambda d: (d / "metadata.yaml").write_text(
        (d / "metadata.yaml").read_text().replace("storage_identifier: mcap",
                                                  "storage_identifier: rosbag1")),
    "metadata empty": lambda d: (d / "metadata.yaml").write_text(""),
    "storage file missing": lambda d: next(d.glob("*.mcap")).unlink(),
    "storage file garbage": lambda d: next(d.glob("*.mcap")).write_bytes(b"\x00" * 100),
    "storage file truncated": lambda d: next(d.glob("*.mcap")).write_bytes(
        next(d.glob("*.mcap")).read_bytes()[:-40]),
}
MALFORMED_HEADERS = {
    "not json": "{design",
    "json list": "[1, 2]",
    "no design": json.dumps({k: v for k, v in _good_header().items() if k != "design_toml"}),
    "format 99": _edit_header(format=99),
    "lift not numbers": _edit_header(lift_left={"deployed_rad": "0", "lifted_rad": 1.5,
                                                "rate_rad_s": 1.0}),
    "lift equal": _edit_header(lift_right={"deployed_rad": 0.0, "lifted_rad": 0.0,
                                           "rate_rad_s": 1.0}),
    "dmin text": _edit_header(dmin_mm="20"),
    "offset negative": _edit_header(epoch_offset_ns=-1),
    "calibration number": _edit_header(calibration_toml=3),
    "design not toml": _edit_header(design_toml="[layout\nx = "),
}


@pytest.mark.parametrize("kind", sorted(MALFORMED))
def test_malformed_bag_is_one_line(tmp_path, capsys, kind):
    write_bag(tmp_path / "b", n_scans=2)
    MALFORMED[kind](tmp_path / "b")
    with pytest.raises(DesignFileError):
        read_bag(tmp_path / "b")
    assert main(["replay", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


@pytest.mark.parametrize("kind", sorted(MALFORMED_HEADERS))
def test_malformed_design_message_is_one_line(tmp_path, capsys, kind):
    _raw_bag(tmp_path / "b", MALFORMED_HEADERS[kind])
    assert main(["replay", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    # the same bag with a good header gets past the header (and has no scans)
    _raw_bag(tmp_path / "ok", json.dumps(_good_header()))
    with pytest.raises(DesignFileError, match="no scans"):
        replay_bag(tmp_path / "ok")


def test_write_error_keeps_committed_scans(tmp_path):
    """Any storage error while writing (here: the MCAP file handle fails as on a full
    disk) is a BagWriteError naming the committed scans; those stay readable."""
    rng = np.random.default_rng(3)
    rec = recorder(tmp_path / "b", "mcap").open()
    t = 12.0 + np.arange(0, 0.5, 0.004)
    for k in range(3):
        rec.write_scan(fake_scan(k, rng), URG)
        rec.write_samples("nod", t[(t >= 12 + 0.1 * k) & (t < 12.1 + 0.1 * k)], np.zeros(25))
        rec.commit()

    def full(*_a):
        raise OSError(28, "No space left on device")

    rec._w.storage.bio.write = full
    with pytest.raises(BagWriteError, match="after 3 committed scans.*No space left"):
        rec.write_scan(fake_scan(3, rng), URG)
        rec.commit()
    back = read_bag(tmp_path / "b")
    assert back.recovered and len(back.scans) == 3


def _wait_for(cond, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.05)
    return False


def _pump(proc, lines: list[str]) -> threading.Thread:
    def pump():
        for line in proc.stderr:
            lines.append(line)

    th = threading.Thread(target=pump, daemon=True)
    th.start()
    return th


@pytest.mark.slow
@pytest.mark.parametrize("storage", STORAGES)
def test_sigkill_keeps_every_scan_before_the_last(tmp_path, storage):
    """`nodlidar record` as a subprocess against the simulated sensor, SIGKILLed after it
    reported N scans: the bag reads (through a repaired copy) with >= N scans, every one
    decoding to a full scan, and replays."""
    kill_after = 20
    out = tmp_path / "bag"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "nodlidar.cli", "record", "--out", str(out), "--scans", "100000",
         "--sim-rate", "5", "--sim-transport", "tcp", "--storage", storage],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    lines: list[str] = []
    try:
        _pump(proc, lines)
        ok = _wait_for(lambda: any(f"recorded {kill_after} scans" in ln for ln in lines), 120)
        assert ok, "".join(lines)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "metadata.yaml").exists()  # it never closed
    back = read_bag(out)
    assert back.recovered and not (out / "metadata.yaml").exists()
    # 'recorded N scans' is printed after scan N was committed, so all N are there (the
    # issue asks for >= N - 1: every scan before the one in flight)
    assert len(back.scans) >= kill_after
    for s in back.scans:
        assert len(s.ranges_mm) == URG.n_steps
    _, cloud = replay_bag(out)
    assert len(cloud) > 0


@pytest.mark.slow
@pytest.mark.parametrize("storage", STORAGES)
def test_disk_full_while_recording_is_one_line(tmp_path, storage):
    """`nodlidar record` with a 1.5 MB file-size limit (the kernel refuses writes past it,
    EFBIG, as a full disk refuses them): one line on stderr, exit 1, no traceback; the
    scans committed before are kept and replay reads them."""
    out = tmp_path / "bag"
    limit = 1_500_000

    def cap_size():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails, no signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.run(
        [sys.executable, "-m", "nodlidar.cli", "record", "--out", str(out), "--scans", "100000",
         "--sim-rate", "5", "--sim-transport", "tcp", "--storage", storage],
        capture_output=True, text=True, cwd=ROOT, preexec_fn=cap_size, timeout=300)
    err = [ln for ln in proc.stderr.splitlines() if ln.startswith("nodlidar record:")]
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and len(err) == 1, proc.stderr
    assert "committed scans" in err[0]
    n = int(err[0].split("failed after ")[1].split()[0])
    back = read_bag(out)
    assert n > 0 and len(back.scans) >= n
    _, cloud = replay_bag(out)
    assert len(cloud) > 0


@pytest.mark.slow
def test_record_force_and_json(tmp_path, capsys):
    """One overwrite policy: an existing --out is refused unless --force, and --force
    replaces only a bag folder; --json summarises what was written."""
    out = tmp_path / "bag"
    args = ["record", "--out", str(out), "--scans", "3", "--sim-rate", "5"]
    assert main(args + ["--storage", "sqlite3"]) == 0
    capsys.readouterr()
    assert main(args) == 2
    assert "--force" in capsys.readouterr().err
    assert main(args + ["--force", "--json"]) == 0
    j = json.loads(capsys.readouterr().out)
    assert j["storage"] == "mcap" and j["scans"] == 3 and j["point_clouds"] == 3
    assert j["bag_points"] > 1000 and j["epoch_offset_ns"] > Y2000_NS
    assert sorted(f.suffix for f in out.iterdir()) == [".mcap", ".yaml"]  # sqlite3 bag replaced
    other = tmp_path / "photos"
    other.mkdir()
    (other / "a.jpg").write_bytes(b"x")
    assert main(["record", "--out", str(other), "--scans", "3", "--force"]) == 2
    assert "bag folder" in capsys.readouterr().err and (other / "a.jpg").exists()
    with pytest.raises(SystemExit) as e:  # argparse: a usage error, before any work
        main(["record", "--out", str(tmp_path / "x"), "--seconds", "inf"])
    assert e.value.code == 2 and "--seconds" in capsys.readouterr().err
    (tmp_path / "c.ply").write_bytes(b"")
    assert main(["replay", str(out), "--out", str(tmp_path / "c.ply")]) == 2
    assert main(["replay", str(out), "--out", str(tmp_path / "c.ply"), "--force"]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("storage", STORAGES)
def test_mutated_bags_never_raise_anything_but_a_nodlidar_error(tmp_path, storage):
    """Random damage (byte flips in the storage file, cuts and garbage in
    metadata.yaml): read_bag either reads the bag (counting what it skipped) or raises a
    one-line DesignFileError - never another exception."""
    write_bag(tmp_path / "b", n_scans=4, storage=storage)
    src = tmp_path / "b"
    store = next(src.glob("*.mcap" if storage == "mcap" else "*.db3"))
    data, meta = store.read_bytes(), (src / "metadata.yaml").read_bytes()
    rng = np.random.default_rng(11)
    outcomes = {"read": 0, "error": 0}
    for i in range(24):
        d = tmp_path / f"m{i}"
        d.mkdir()
        body, m = bytearray(data), bytearray(meta)
        if i % 3 == 2:  # metadata.yaml cut or with a garbage byte
            j = int(rng.integers(0, len(m)))
            m = m[:j] if i % 2 else m[:j] + bytes([int(rng.integers(0, 256))]) + m[j + 1:]
        else:  # a few bytes of the storage file flipped
            for j in rng.integers(0, len(body), 1 + i % 4):
                body[int(j)] ^= int(rng.integers(1, 256))
        (d / store.name).write_bytes(bytes(body))
        (d / "metadata.yaml").write_bytes(bytes(m))
        try:
            back = read_bag(d)
        except DesignFileError as exc:
            assert "\n" not in str(exc)
            outcomes["error"] += 1
        else:
            assert len(back.scans) + back.skipped.get(RAW_TOPIC, 0) <= 4
            outcomes["read"] += 1
    assert sum(outcomes.values()) == 24
    assert outcomes["read"] >= 8  # (seeded) damaged bags are read, not just refused


@pytest.mark.parametrize("storage", STORAGES)
def test_interrupted_recording_is_closed(tmp_path, storage):
    """Ctrl-C (KeyboardInterrupt) inside the recorder still finishes the bag: it opens
    without repair, with every scan written and its PointCloud2."""
    rng = np.random.default_rng(4)
    t = 12.0 + np.arange(0, 0.5, 0.004)
    with pytest.raises(KeyboardInterrupt):
        with recorder(tmp_path / "b", storage) as rec:
            for k in range(3):
                rec.write_scan(fake_scan(k, rng), URG)
                rec.write_samples("nod", t[(t >= 12 + 0.1 * k) & (t < 12.1 + 0.1 * k)],
                                  np.zeros(25))
                rec.commit()
            raise KeyboardInterrupt
    assert (tmp_path / "b" / "metadata.yaml").exists()
    back = read_bag(tmp_path / "b")
    assert not back.recovered and len(back.scans) == 3 and back.clouds == 3


# -- lift profiles in the header (issue 18: the lift angle from the design) --------------


def test_header_lift_profiles_come_from_the_design(tmp_path):
    """No profiles given: the header holds the recorded design's (lift_angle_rad = 1.2,
    each side's sign), and reading gives them back; a profile given is kept as is."""
    from nodlidar.runtime.servo_angles import MirrorLiftProfile, lift_profiles
    from nodlidar.solver import solve
    from nodlidar.spec import design_from_dict

    old = "lift_angle_rad = 1.5707963267948966"
    assert DESIGN_TOML.count(old) == 1
    toml = DESIGN_TOML.replace(old, "lift_angle_rad = 1.2")
    want = lift_profiles(solve(design_from_dict(tomllib.loads(toml))))
    assert_allclose([want[0].lifted_rad, want[1].lifted_rad], [-1.2, 1.2], rtol=0, atol=1e-15)
    rng = np.random.default_rng(1)
    right = MirrorLiftProfile(0.1, 1.3, 2.0)
    for name, kw, expect in (("design", {}, want), ("given", {"lift_right": right},
                                                    (want[0], right))):
        with BagRecorder(tmp_path / name, toml, extra={"dmin_mm": 20}, clock=lambda: 11.9,
                         clouds=False, **kw) as rec:
            rec.write_scan(fake_scan(0, rng), URG)
        back = read_bag(tmp_path / name)
        assert back.lift_profiles() == expect
        assert back.header["lift_left"] == {"deployed_rad": 0.0,
                                            "lifted_rad": expect[0].lifted_rad,
                                            "rate_rad_s": 1.0}


def test_recording_with_the_old_default_profiles_still_replays(tmp_path):
    """Every recording before the lift angle came from the design has the profile
    ``(0, pi/2)`` on both sides in its header; it loads, and replay classifies the mirror
    samples with the recorded profiles, not the design's: left samples at +pi/2 are
    lifted (the design's left lifted angle is -pi/2), right samples at 0 deployed."""
    from nodlidar.runtime.servo_angles import MirrorLiftProfile, lift_profiles
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    design = solve(load_design(PAPER_DESIGN))
    assert lift_profiles(design)[0].lifted_rad == pytest.approx(-np.pi / 2)
    old = MirrorLiftProfile(0.0, np.pi / 2)
    rng = np.random.default_rng(2)
    scans = [fake_scan(k, rng) for k in range(3)]
    t = 12.0 + np.arange(0, 0.4, 0.004)
    with BagRecorder(tmp_path / "old", DESIGN_TOML, extra={"dmin_mm": 20}, clock=lambda: 11.9,
                     lift_left=old, lift_right=old) as rec:
        for s in scans:
            rec.write_scan(s, URG)
        rec.write_samples("nod", t, np.zeros_like(t))
        rec.write_samples("mirror_left", t[::10], np.full(len(t[::10]), np.pi / 2))
        rec.write_samples("mirror_right", t[::10], np.zeros(len(t[::10])))
    header = read_bag(tmp_path / "old").header
    assert header["lift_left"] == header["lift_right"] == {
        "deployed_rad": 0.0, "lifted_rad": np.pi / 2, "rate_rad_s": 1.0}
    contents, cloud = replay_bag(tmp_path / "old")
    assert contents.lift_profiles() == (old, old)
    assert cloud.meta["mirror_moving"] == 0
    # independently: the left windows' steps (the design's map) are exactly the lifted ones
    left = [i for i, m in enumerate(design.mirrors) if m.side == "L"]
    on_left = np.isin(design.mirror_of_step[cloud.step - URG.step_min], left)
    assert on_left.sum() > 100
    assert_array_equal(cloud.lifted, on_left)
