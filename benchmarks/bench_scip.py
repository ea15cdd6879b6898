"""Full-frame GD decode rate: nodlidar.scip (numpy-vectorised) vs two baselines: a
per-character pure-Python decoder written here, and the decoder of the PyPI ``hokuyolx``
client (an independent SCIP implementation; issue 16 asks for >= 50x it).

Both decoders take one complete ``GD0044072501`` reply (2134 bytes, 682 values: a real
URG-04LX capture if ../shared/data is present, else an equivalent synthetic frame), verify
every checksum and return the ranges. Prints frames/s of each and their ratios; under
``benchmarks/run.py`` the figures are ``scip.ratio_vs_hokuyolx``, ``scip.ratio_vs_python``
and ``scip.frames_per_s``.
Run: ``.venv/bin/python benchmarks/bench_scip.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nodlidar import scip

CAPTURE = (Path(__file__).resolve().parents[2] / "shared" / "data" / "urg04lx-captures"
           / "capture-a-gd0044072501.bin")


def baseline_decode(message: bytes) -> tuple[int, list[int]]:
    """Straightforward decoder: one Python operation per character."""
    lines = message.split(b"\n")
    status = lines[1]
    s = 0
    for c in status[:-1]:
        s += c
    if (s & 0x3F) + 0x30 != status[-1]:
        raise ValueError("status checksum")
    data = []
    for line in lines[2:]:
        if not line:
            break
        s = 0
        for c in line[:-1]:
            s += c
        if (s & 0x3F) + 0x30 != line[-1]:
            raise ValueError("checksum")
        data.append(line[:-1])
    ts_chars, body = data[0], b"".join(data[1:])
    ts = 0
    for c in ts_chars:
        ts = (ts << 6) | (c - 0x30)
    values = []
    for i in range(0, len(body), 3):
        v = 0
        for c in body[i:i + 3]:
            v = (v << 6) | (c - 0x30)
        values.append(v)
    return ts, values


def hokuyolx_decode(message: bytes) -> tuple[int, np.ndarray]:
    """The ``hokuyolx`` client's own path from a received GD reply to (timestamp, ranges):
    ``_recv`` (ASCII decode, split), ``_send_req`` (echo, status checksum),
    ``_single_measurment`` (timestamp checksum and decode, ``_process_scan_data``: every
    block's checksum, 3-character values). No socket: the object is made without
    ``__init__`` (which would connect), with the timestamp left raw as nodlidar's."""
    lx = _LX
    split = message[:-2].decode("ascii").split("\n")
    split.pop(0)  # the echo, checked against the request by _recv
    status = lx._check_sum(split.pop(0))
    if status != "00":  # as _single_measurment
        raise ValueError(status)
    ts = lx._convert2ts(split.pop(0), convert=False)
    return ts, lx._process_scan_data(split, False)


def _make_lx():
    from hokuyolx import HokuyoLX

    lx = HokuyoLX.__new__(HokuyoLX)  # no connection: only its decoding methods are used
    lx.convert_time = False
    return lx


_LX = None


def vectorised_decode(message: bytes) -> tuple[int, np.ndarray]:
    f = scip.decode_scan(message)
    return f.timestamp_ms, f.ranges_mm


def rate(fn, message: bytes, min_time: float = 0.5) -> float:
    n, t0 = 0, time.perf_counter()
    while True:
        for _ in range(50):
            fn(message)
        n += 50
        dt = time.perf_counter() - t0
        if dt >= min_time:
            return n / dt


def main() -> dict[str, float]:
    if CAPTURE.exists():
        message, source = CAPTURE.read_bytes(), CAPTURE.name
    else:
        rng = np.random.default_rng(0)
        message = scip.encode_scan_reply("GD0044072501", "00", 123456,
                                         rng.integers(0, 5600, 682), 3)
        source = "synthetic frame"
    global _LX
    _LX = _make_lx()
    ts_a, va = baseline_decode(message)
    ts_b, vb = vectorised_decode(message)
    ts_c, vc = hokuyolx_decode(message)
    assert ts_a == ts_b == ts_c and list(vb) == va == list(vc), "decoders disagree"
    r_base = rate(baseline_decode, message)
    r_lx = rate(hokuyolx_decode, message)
    r_vec = rate(vectorised_decode, message)
    print(f"GD0044072501 full frame ({len(message)} bytes, {len(va)} values; {source})")
    print(f"  pure-Python per-character : {r_base:10.0f} frames/s")
    print(f"  hokuyolx (PyPI client)    : {r_lx:10.0f} frames/s")
    print(f"  nodlidar.scip (numpy)     : {r_vec:10.0f} frames/s")
    print(f"  ratio vs per-character    : {r_vec / r_base:10.1f}x")
    print(f"  ratio vs hokuyolx         : {r_vec / r_lx:10.1f}x  (goal >= 50x)")
    return {"ratio_vs_hokuyolx": r_vec / r_lx, "ratio_vs_python": r_vec / r_base,
            "frames_per_s": r_vec, "hokuyolx_frames_per_s": r_lx}


if __name__ == "__main__":
    main()
