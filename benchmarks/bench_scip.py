"""Full-frame GD decode rate: nodlidar.scip vs two baselines: a per-character pure-Python
decoder written here, and the decoder of the PyPI ``hokuyolx`` client (an independent SCIP
implementation; issue 16 asks for >= 50x it).

Both decoders take one complete ``GD0044072501`` reply (2134 bytes, 682 values: the real
URG-04LX capture in tests/data, else an equivalent synthetic frame), verify every checksum
and return the ranges. Prints frames/s of each and their ratios; under
``benchmarks/run.py`` the figures are ``scip.ratio_vs_hokuyolx``, ``scip.ratio_vs_python``
and ``scip.frames_per_s``, ``scip.reply_ratio_vs_hokuyolx`` for the driver's path
(``decode_scan`` of an already framed :class:`~nodlidar.scip.ScipReply`), and
``scip.frame_us`` / ``scip.hokuyolx_frame_us`` (CPU time per frame), ``scip.floor_us`` and
``scip.floor_ratio_vs_hokuyolx``: the bare array calls any numpy decoder of the frame makes
(``np.frombuffer``, one ``reduceat`` for the line sums, one gather, one matrix product, one
cast - no checks, no Python), i.e. what is left to gain.

Rates are in CPU time of this thread (``time.thread_time``; every decoder is single
threaded pure Python or numpy), measured in alternating slices of ~0.1 s so that all
decoders see the same machine: on a shared machine wall time mostly measures the other
processes (as ``bench_sim``). Ratios are taken per round of slices (adjacent in time) and
the median over the rounds reported.
Run: ``.venv/bin/python benchmarks/bench_scip.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nodlidar import scip

CAPTURE = (Path(__file__).resolve().parents[1] / "tests" / "data" / "urg04lx-captures"
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


def make_floor_decode(message: bytes):
    """The array calls of nodlidar's decode of ``message`` alone, with the layout found
    beforehand: a view of the block, the line sums, one gather, one product, one cast."""
    i = message.index(b"\n")
    start, n = i + 5, len(message) - 1
    lay = scip._scan_layout(n - start, 3)
    w = scip._LF_WEIGHTS[3]

    def floor_decode(msg: bytes) -> np.ndarray:
        a = np.frombuffer(msg, np.uint8, n - start, start)
        np.add.reduceat(a, lay.bounds, dtype=np.uint8)
        return a.take(lay.data).dot(w).astype(np.int32)

    return floor_decode


def rates(fns: dict, message, slices: int = 9, slice_s: float = 0.1) -> dict[str, list[float]]:
    """Calls/s of each ``fn(message)`` in thread CPU time, per slice: ``slices`` rounds of
    one slice of about ``slice_s`` per function, in turn."""
    per: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(slices):
        for k, fn in fns.items():
            n, t0 = 0, time.thread_time()
            while True:
                for _ in range(20):
                    fn(message)
                n += 20
                dt = time.thread_time() - t0
                if dt >= slice_s:
                    per[k].append(n / dt)
                    break
    return per


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
    reply = scip.parse_reply(message)
    floor = make_floor_decode(message)
    assert list(floor(message)) == va
    per = rates({"base": baseline_decode, "lx": hokuyolx_decode, "vec": vectorised_decode,
                 "reply": lambda _m: scip.decode_scan(reply), "floor": floor}, message)
    r = {k: float(np.median(v)) for k, v in per.items()}
    lx = np.array(per["lx"])

    def ratio(k: str) -> float:  # median over rounds of the ratio within each round
        return float(np.median(np.array(per[k]) / lx))

    r_base, r_lx, r_vec, r_reply = r["base"], r["lx"], r["vec"], r["reply"]
    us = {k: 1e6 / np.array(v) for k, v in per.items()}
    print(f"GD0044072501 full frame ({len(message)} bytes, {len(va)} values; {source})")
    print(f"  pure-Python per-character : {r_base:10.0f} frames/s")
    print(f"  hokuyolx (PyPI client)    : {r_lx:10.0f} frames/s"
          f"  ({np.min(us['lx']):.0f} / {np.median(us['lx']):.0f} us min / median)")
    print(f"  nodlidar.scip (numpy)     : {r_vec:10.0f} frames/s"
          f"  ({np.min(us['vec']):.1f} / {np.median(us['vec']):.1f} us)")
    print(f"  nodlidar.scip, framed     : {r_reply:10.0f} frames/s  (decode_scan(ScipReply))")
    print(f"  array calls alone (floor) : {r['floor']:10.0f} frames/s"
          f"  ({np.min(us['floor']):.1f} / {np.median(us['floor']):.1f} us)")
    print(f"  ratio vs per-character    : {ratio('vec') / ratio('base'):10.1f}x")
    print(f"  ratio vs hokuyolx         : {ratio('vec'):10.1f}x  (goal >= 50x; per round "
          f"{np.min(np.array(per['vec']) / lx):.1f}-{np.max(np.array(per['vec']) / lx):.1f})")
    print(f"  floor vs hokuyolx         : {ratio('floor'):10.1f}x")
    return {"ratio_vs_hokuyolx": ratio("vec"), "ratio_vs_python": ratio("vec") / ratio("base"),
            "frames_per_s": r_vec, "hokuyolx_frames_per_s": r_lx,
            "reply_ratio_vs_hokuyolx": ratio("reply"),
            "frame_us": float(np.median(us["vec"])),
            "hokuyolx_frame_us": float(np.median(us["lx"])),
            "floor_us": float(np.median(us["floor"])),
            "floor_ratio_vs_hokuyolx": ratio("floor")}


if __name__ == "__main__":
    main()
