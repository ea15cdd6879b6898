"""``nodlidar emulate``: fixed TCP ports on loopback, the URLs as JSON, SCIP 1.1 boot mode,
bounded options refused in one line (issue 15)."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys

import pytest

from nodlidar.runtime.actuators import DynamixelBus

pytestmark = pytest.mark.timeout(120)


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def _emulate(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "nodlidar.cli", "emulate", "--scene", "wall",
                             "--no-noise", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _ask(sock: socket.socket, line: bytes) -> bytes:
    """Send one SCIP command; return its reply up to the blank line."""
    sock.sendall(line)
    buf = b""
    while not buf.endswith(b"\n\n"):
        chunk = sock.recv(4096)
        assert chunk, "connection closed"
        buf += chunk
    return buf


@pytest.mark.slow
def test_emulate_fixed_ports_json_and_scip1_boot():
    lidar_port, servo_port = _free_ports(2)
    p = _emulate("--tcp", "--port", str(lidar_port), "--servo-port", str(servo_port),
                 "--json", "--scip1", "--rate", "5")
    try:
        info = json.loads(p.stdout.readline())  # one JSON object, printed once serving
        assert info["lidar_url"] == f"socket://127.0.0.1:{lidar_port}"
        assert info["servo_url"] == f"socket://127.0.0.1:{servo_port}"
        assert info["scip"] == "1.1" and info["rate"] == 5 and info["transport"] == "tcp"
        # the servo bus answers on its fixed port
        with DynamixelBus(info["servo_url"], timeout_s=2.0) as bus:
            assert [s.id for s in bus.discover()] == [1, 2, 3]
        # the lidar boots in SCIP 1.1: a 2.0 command is refused until SCIP2.0 switches it
        with socket.create_connection(("127.0.0.1", lidar_port), timeout=10) as s:
            assert _ask(s, b"VV\n").split(b"\n")[1] != b"00P"
            assert _ask(s, b"SCIP2.0\n").split(b"\n")[:2] == [b"SCIP2.0", b"0"]
            vv = _ask(s, b"VV\n").split(b"\n")
            assert vv[:2] == [b"VV", b"00P"] and any(x.startswith(b"PROT:") for x in vv)
    finally:
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    assert out == ""  # --json: nothing but the one object


@pytest.mark.parametrize("args, words", [
    (["--rate", "inf"], "--rate"),
    (["--rate", "0"], "--rate"),
    (["--rate", "1e6"], "--rate"),
    (["--port", "7000"], "--port"),  # without --tcp: does not apply
    (["--tcp", "--port", "70000"], "--port"),
    (["--tcp", "--port", "7001", "--servo-port", "7001"], "--servo-port"),
    (["--seed", "-1"], "--seed"),
])
def test_emulate_refuses_bad_options_in_one_line(args, words):
    p = _emulate(*args)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 2, (out, err)
    lines = err.strip().splitlines()
    assert "Traceback" not in err and words in lines[-1], err


def test_emulate_port_in_use_is_one_line():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        p = _emulate("--tcp", "--servo-port", str(port))
        out, err = p.communicate(timeout=60)
    assert p.returncode == 1, (out, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
