"""Soak: a long ``nodlidar record --cloud`` on the simulated sensor, then the same bag
replayed, and the live cloud compared with the replay point for point.

Runs ``nodlidar record`` as a child process, samples its resident memory (VmRSS) every
few seconds and fits a line to the second half (after start-up), then replays the bag in
chunks (the whole of an 8 h recording does not fit in memory at once): each chunk of
scans is assembled with every bag sample within ``MARGIN_S`` of it - linear
interpolation only needs the two samples around a beam, so this equals assembling the
whole bag at once - and compared with the live file's rows of the same scans.

Run (8 h of simulated time at 40x, about 12 min of wall time when the machine keeps up)::

    .venv/bin/python benchmarks/soak_record.py --seconds 28800 --sim-rate 40 --dir /tmp/soak

Prints one JSON object: scans, live and replay points, the largest coordinate
difference, the RSS samples' slope [MB/h of simulated time and MB/h of wall time].
Not part of ``make bench`` (it takes long and writes several GB).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

MARGIN_S = 5.0  # samples are at most ~0.1 s apart; 5 s covers any stall of the sampler


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def record(args, bag: Path, cloud: Path) -> dict:
    exe = Path(sys.executable).with_name("nodlidar")
    cmd = [str(exe), "record", "--out", str(bag), "--seconds", str(args.seconds),
           "--sim-rate", str(args.sim_rate), "--cloud", str(cloud)]
    if args.storage:
        cmd += ["--storage", args.storage]
    t0 = time.monotonic()
    log = (bag.parent / "record.log").open("w")
    p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    wall, mem = [], []
    while p.poll() is None:
        m = rss_mb(p.pid)
        if m is not None:
            wall.append(time.monotonic() - t0)
            mem.append(m)
        time.sleep(args.rss_period)
    log.close()
    if p.returncode != 0:
        raise SystemExit(f"record failed ({p.returncode}): {(bag.parent / 'record.log').read_text()[-2000:]}")
    w, m = np.array(wall), np.array(mem)
    np.savetxt(bag.parent.parent / f"{bag.parent.name}-rss.txt", np.c_[w, m], fmt="%.2f",
               header="wall_s rss_mb")  # kept beside the work directory
    half = w >= w[-1] / 2 if len(w) else w.astype(bool)
    slope_wall = float(np.polyfit(w[half], m[half], 1)[0]) * 3600 if half.sum() >= 3 else float("nan")
    wall_s = time.monotonic() - t0
    # simulated seconds per wall second actually achieved: the clock runs at sim_rate
    return {"wall_s": round(wall_s, 1), "rss_first_mb": round(float(m[0]), 1) if len(m) else None,
            "rss_half_mb": round(float(m[half][0]), 1) if half.any() else None,
            "rss_last_mb": round(float(m[-1]), 1) if len(m) else None,
            "rss_max_mb": round(float(m.max()), 1) if len(m) else None,
            "rss_slope_mb_per_wall_h": round(slope_wall, 2),
            "rss_slope_mb_per_sim_h": round(slope_wall / args.sim_rate, 3),
            "rss_samples": len(m),
            "record_stdout_tail": (bag.parent / "record.log").read_text().splitlines()[-2:]}


def replay_compare(bag: Path, cloud: Path, chunk: int) -> dict:
    from nodlidar import scip
    from nodlidar.runtime.assembly import AssemblyModel, ScanBatch, assemble
    from nodlidar.runtime.bag import (
        DESIGN_TOPIC,
        JOINT_TOPIC,
        JOINTS,
        RAW_TOPIC,
        BagContents,
        RecordedScan,
        design_from_header,
        iter_messages,
    )

    # pass 1: header and every servo sample (small: ~20 samples per simulated second)
    header = None
    jt: dict[str, list[float]] = {j: [] for j in JOINTS}
    ja: dict[str, list[float]] = {j: [] for j in JOINTS}
    for topic, _t, msg in iter_messages(bag):
        if topic == DESIGN_TOPIC:
            header = json.loads(msg.data)
        elif topic == JOINT_TOPIC:
            st = msg.header.stamp
            for name, pos in zip(msg.name, msg.position):
                if name in jt:
                    jt[name].append(st.sec + st.nanosec * 1e-9)
                    ja[name].append(float(pos))
    joints = {j: (np.array(jt[j]), np.array(ja[j])) for j in JOINTS if jt[j]}
    design, perts, cal_id = design_from_header(header)
    model = AssemblyModel.from_design(design, perts, cal_id)
    left, right = BagContents(header, [], joints, 0, False).lift_profiles()
    dmin = int(header.get("dmin_mm", 20))

    # the live file does not fit in memory either: map its rows (dtype from the header)
    live_head = read_cloud_header(cloud)
    rows = np.memmap(cloud, dtype=live_head["dtype"], mode="r", offset=live_head["offset"],
                     shape=(live_head["n"],))

    lidar = model.lidar
    out = {"scans": 0, "replay_points": 0, "live_points": int(live_head["n"]),
           "max_abs_dxyz_m": 0.0, "mismatched_chunks": 0, "stats": {}}
    pos = 0  # next live row

    def flush(batch: list) -> None:
        nonlocal pos
        t_lo = lidar.beam_time_s(batch[0].stamp_s, 0) - MARGIN_S
        t_hi = lidar.beam_time_s(batch[-1].stamp_s, lidar.step_max) + MARGIN_S

        def window(j):
            if j is None:
                return None
            t, a = j
            k0, k1 = np.searchsorted(t, [t_lo, t_hi])
            return t[k0:k1], a[k0:k1]

        c = assemble(model, ScanBatch.from_scans(batch), window(joints["nod"]),
                     mirror_left=window(joints.get("mirror_left")),
                     mirror_right=window(joints.get("mirror_right")),
                     lift_left=left, lift_right=right)
        for k, v in c.meta.items():
            out["stats"][k] = out["stats"].get(k, 0) + int(v)
        live = rows[pos:pos + len(c)]
        scan_ok = len(live) == len(c) and np.array_equal(live["scan"] - batch[0].seq, c.scan)
        if not scan_ok:
            out["mismatched_chunks"] += 1
        else:
            xyz = np.stack([live["x"], live["y"], live["z"]], -1).astype(float)
            ref = c.xyz.astype(live["x"].dtype).astype(float)  # the file's precision
            out["max_abs_dxyz_m"] = max(out["max_abs_dxyz_m"], float(np.abs(xyz - ref).max(initial=0)))
        pos += len(c)
        out["replay_points"] += len(c)

    batch: list = []
    for topic, t_ns, msg in iter_messages(bag):
        if topic != RAW_TOPIC:
            continue
        raw = bytes(np.asarray(msg.data, dtype=np.uint8))
        fr = scip.decode_scan(raw)
        batch.append(RecordedScan(out["scans"], fr.request, fr.steps,
                                  scip.ranges_mm_to_m(fr.ranges_mm, dmin), fr.ranges_mm,
                                  fr.timestamp_ms, t_ns * 1e-9, b""))
        out["scans"] += 1
        if len(batch) >= chunk:
            flush(batch)
            batch = []
    if batch:
        flush(batch)
    out["live_rows_left_over"] = int(live_head["n"] - pos)
    return out


def read_cloud_header(path: Path) -> dict:
    """Point count, row dtype and data offset of a binary PLY written by nodlidar."""
    from nodlidar.runtime.cloud import _PLY_DTYPE

    fields, n = [], 0
    with path.open("rb") as fh:
        while True:
            line = fh.readline().decode("ascii").strip()
            w = line.split()
            if w[:2] == ["element", "vertex"]:
                n = int(w[2])
            elif w and w[0] == "property":
                fields.append((w[2], _PLY_DTYPE[w[1]]))
            elif line == "end_header":
                return {"n": n, "dtype": np.dtype(fields), "offset": fh.tell()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=28800.0, help="simulated seconds")
    ap.add_argument("--sim-rate", type=float, default=40.0)
    ap.add_argument("--dir", required=True, help="work directory (bag + cloud; removed first)")
    ap.add_argument("--rss-period", type=float, default=5.0, help="wall seconds between RSS reads")
    ap.add_argument("--chunk", type=int, default=2000, help="scans per replay chunk")
    ap.add_argument("--keep", action="store_true", help="keep the bag and cloud")
    ap.add_argument("--storage", default=None, help="record --storage (mcap, sqlite3)")
    args = ap.parse_args()
    d = Path(args.dir)
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    bag, cloud = d / "bag", d / "live.ply"
    res = {"seconds": args.seconds, "sim_rate": args.sim_rate}
    res["record"] = record(args, bag, cloud)
    print(json.dumps(res), flush=True)
    t0 = time.monotonic()
    res["replay"] = replay_compare(bag, cloud, args.chunk)
    res["replay"]["wall_s"] = round(time.monotonic() - t0, 1)
    res["equal"] = (res["replay"]["replay_points"] == res["replay"]["live_points"]
                    and res["replay"]["mismatched_chunks"] == 0
                    and res["replay"]["live_rows_left_over"] == 0)
    print(json.dumps(res), flush=True)
    if not args.keep:
        shutil.rmtree(d, ignore_errors=True)


if __name__ == "__main__":
    main()
