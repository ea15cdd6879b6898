"""Full-frame GD decode rate: nodlidar.scip (numpy-vectorised) vs a per-character
pure-Python decoder written here as the baseline.

Both decoders take one complete ``GD0044072501`` reply (2134 bytes, 682 values: a real
URG-04LX capture if ../shared/data is present, else an equivalent synthetic frame), verify
every checksum and return the ranges. Prints frames/s of each and their ratio.
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


def main() -> None:
    if CAPTURE.exists():
        message, source = CAPTURE.read_bytes(), CAPTURE.name
    else:
        rng = np.random.default_rng(0)
        message = scip.encode_scan_reply("GD0044072501", "00", 123456,
                                         rng.integers(0, 5600, 682), 3)
        source = "synthetic frame"
    ts_a, va = baseline_decode(message)
    ts_b, vb = vectorised_decode(message)
    assert ts_a == ts_b and list(vb) == va, "decoders disagree"
    r_base = rate(baseline_decode, message)
    r_vec = rate(vectorised_decode, message)
    print(f"GD0044072501 full frame ({len(message)} bytes, {len(va)} values; {source})")
    print(f"  pure-Python per-character : {r_base:10.0f} frames/s")
    print(f"  nodlidar.scip (numpy)     : {r_vec:10.0f} frames/s")
    print(f"  ratio                     : {r_vec / r_base:10.1f}x")


if __name__ == "__main__":
    main()
