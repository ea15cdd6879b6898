"""``nodlidar view``: live 3D view of the sensor in Foxglove.

Nods the head and serves, over the Foxglove WebSocket protocol, the growing 3D cloud
(foxglove.PointCloud on /nodlidar/cloud, frame sensor), the mirror patches of the solved
design with the calibration applied (foxglove.SceneUpdate on /nodlidar/mirrors, frame
head, nodding with /tf) and the tracks (/nodlidar/tracks, frame world, when the tracker
can be built). Prints the ws:// URL to open in Foxglove (Open connection -> Foxglove
WebSocket); --mcap FILE writes the same stream to an MCAP file. Runs until Ctrl-C or
--duration.

Without --port/--servo-port (or with --sim) it uses the built-in simulated sensor; the
server binds to 127.0.0.1 unless --host says otherwise.
"""

from __future__ import annotations

import argparse
import json
import signal
import threading

from ._args import add_force_arg, bounded_float, bounded_int, check_output_path
from ._output import status
from ._runtime_args import add_device_args, check_sim_options, session_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="live 3D view in Foxglove (cloud, mirrors, tracks)",
                       description=__doc__)
    add_device_args(p)
    p.add_argument("--sim", action="store_true",
                   help="the built-in simulated sensor (the default without --port)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address the WebSocket server binds to (default 127.0.0.1: this machine "
                        "only; 0.0.0.0 for every interface)")
    p.add_argument("--ws-port", type=bounded_int(0, 65535), default=8765, metavar="N",
                   help="WebSocket server port (default 8765; 0: any free port)")
    p.add_argument("--mcap", metavar="FILE", default=None,
                   help="also write the stream to this MCAP file")
    add_force_arg(p)
    p.add_argument("--duration", type=bounded_float(0, None, lo_open=True, unit="s"), default=None,
                   metavar="S", help="stop after S wall seconds (default: run until Ctrl-C)")
    p.add_argument("--max-points", type=bounded_int(1, 50_000_000), default=200_000, metavar="N",
                   help="points in the published cloud: the newest N (default 200000)")
    p.add_argument("--cloud-period", type=bounded_float(0.05, 3600, unit="s"), default=0.5,
                   metavar="S", help="publish the cloud at most every S wall seconds (default 0.5; "
                                     "each message holds the whole window)")
    p.add_argument("--no-tracks", action="store_true", help="do not run the tracker")
    p.add_argument("--sensor-height", type=bounded_float(0, 100, unit="m"), default=0.4,
                   metavar="M", help="sensor base above the floor [m] (tracks' frame; default 0.4)")
    p.add_argument("--lift", action="store_true", help="lift the mirrors (direct beams only)")
    p.add_argument("--json", action="store_true",
                   help="stdout as JSON lines: {\"url\": ...} first, the summary at the end")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import ParameterError
    from ..live.view import FoxgloveSink, run_view

    if args.sim and (args.port is not None or args.servo_port is not None):
        raise ParameterError("--sim", "with --port/--servo-port",
                             "either --sim (the simulated sensor) or the device ports")
    if args.mcap is not None:
        check_output_path(args.mcap, force=args.force, option="--mcap")
    check_sim_options(args)  # before the URL line: a refused option is then the only line
    sink = FoxgloveSink(host=args.host, port=args.ws_port, mcap=args.mcap, overwrite=args.force)
    stop = threading.Event()
    url = sink.start()
    restore = _stop_on_signals(stop)
    try:
        if args.json:
            print(json.dumps({"url": url, "mcap": args.mcap}), flush=True)
        else:
            print(url, flush=True)   # the one line to open in Foxglove
        status(f"open {url} in Foxglove (Open connection -> Foxglove WebSocket); Ctrl-C stops")
        with session_from_args(args) as s:
            st = run_view(s, sink, duration_s=args.duration, max_points=args.max_points,
                          cloud_period_s=args.cloud_period,
                          track=not args.no_tracks, sensor_height_m=args.sensor_height,
                          lift=args.lift, log=status, stop=stop)
    finally:
        restore()
        sink.close()
    summary = {"url": url, "scans": st.scans, "points": st.points, "cloud_points": st.cloud_points,
               "messages": st.messages, "tracks": st.tracks, "tracking": st.tracking,
               "tracking_skipped_scans": st.tracks_skipped,
               "mcap": args.mcap, "dropped": {k: v for k, v in st.stats.items()
                           if v and k in ("error_codes", "no_nod", "mirror_moving", "blocked")}}
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        print(f"{st.scans} scans, {st.points} points ({st.cloud_points} in the last cloud), "
              f"{st.tracks} tracks (tracking {st.tracking}); messages: "
              + ", ".join(f"{k} {v}" for k, v in st.messages.items())
              + (f"; wrote {args.mcap}" if args.mcap else ""))
    return 0


def _stop_on_signals(stop: threading.Event):
    """Ctrl-C / SIGTERM end the view cleanly at the next scan (the MCAP file is closed, the
    summary printed); a second Ctrl-C interrupts at once. Installed whatever the inherited
    disposition (a background job starts with SIGINT ignored). Returns the restorer."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum, _frame) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        status("stopping at the next scan (Ctrl-C again to interrupt now)")
        stop.set()

    for sig in old:
        signal.signal(sig, handler)

    def restore() -> None:
        for sig, h in old.items():
            signal.signal(sig, h)

    return restore
