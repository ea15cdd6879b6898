"""``nodlidar track [RECORDING | live | --sim]``: detect and track moving objects, scan by scan.

Three sources of scans, all through the same segmentation and tracker:

* ``RECORDING``: a recording made by ``nodlidar record`` (its own design and calibration),
  through the runtime assembly (:func:`nodlidar.tracking.recording.scans_from_recording`);
* ``live``: the device (``--port``/``--servo-port``) or, without ports, the simulated sensor
  over its emulated serial links (scene ``paper-tracking`` unless ``--scene``), through a
  runtime session: the head nods, every scan is assembled once the servo samples cover it
  (one scan of latency) and tracked as it arrives, for ``--scans`` scans;
* ``--sim`` (the default when nothing is given): the simulator's direct API, no emulators,
  its scans assembled by the runtime's assembly like the other two.

``--calibration`` is the runtime's calibration in every source (a recording's own is
replaced by it); ``--perturb`` builds the simulated sensor with as-built mirror errors
(``--sim`` and simulated ``live``; a recording is what it is, so it is refused there).

Each scan is segmented online (voxel inconsistency with the evidence so far), clustered,
associated to tracks; every track update is printed (``--json``: one JSON object per line
and update). Recordings and live scans are in the sensor base frame raised by
``--sensor-height`` (the floor at z = 0 for the ground removal).
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from ._runtime_args import add_device_args, session_from_args


def register(sub: argparse._SubParsersAction) -> None:
    from .._light import DEFAULT_SENSOR_HEIGHT_M  # (--help imports no numpy)

    p = sub.add_parser("track", help="detect and track moving objects (recording, live or simulator)",
                       description=__doc__)
    p.add_argument("recording", nargs="?",
                   help="recording made by nodlidar record (a bag folder), or 'live'")
    p.add_argument("--sim", action="store_true", help="use the simulator's direct API")
    p.add_argument("--scans", type=int, default=60, help="scans to simulate / track live (default 60)")
    p.add_argument("--lifted", action="store_true", help="mirrors lifted (--sim and live)")
    p.add_argument("--entropy", choices=("renyi", "voxel"), default="renyi")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="one JSON line per track update")
    p.add_argument("--sensor-height", type=float, default=DEFAULT_SENSOR_HEIGHT_M, metavar="M",
                   help="recording/live: sensor base height above the floor [m] "
                        f"(default {DEFAULT_SENSOR_HEIGHT_M}, the paper's Pioneer mount)")
    # the runtime commands' device options; --scene and the --sim options also drive --sim
    add_device_args(p.add_argument_group("sensor (live, and --sim)"), scene="paper-tracking")
    p.set_defaults(func=run)


class _Printer:
    def __init__(self, as_json: bool) -> None:
        self.as_json = as_json

    def __call__(self, states) -> None:
        for st in states:
            if self.as_json:
                print(json.dumps(st.to_dict()), flush=True)
            elif st.confirmed or not st.alive:
                v = "   -  " if math.isnan(st.v_m_s) else f"{st.v_m_s:6.3f}"
                h = "   -   " if math.isnan(st.heading_rad) else f"{math.degrees(st.heading_rad):7.2f}"
                sd = math.sqrt(max(st.cov[2, 2], 0.0))
                print(f"scan {st.scan:4d} track {st.track_id:3d} "
                      f"{'alive' if st.alive else 'ended'}  x {st.x_m:6.3f} y {st.y_m:6.3f} m  "
                      f"v {v} m/s (sd {sd:.3f})  heading {h} deg  "
                      f"[{st.n_scans} scans, {st.n_points} pts]", flush=True)


def _live(args, step) -> None:
    """Track from a runtime session (device or simulated sensor) as scans arrive."""
    from ..tracking.recording import LiveScans

    with session_from_args(args, seed=args.seed) as s:
        model = s.model
        assert model is not None  # set by Session.open (the with statement)
        live = LiveScans(model, (s.lift_left, s.lift_right),
                         sensor_height_m=args.sensor_height)

        def on_scan(scan, samplers) -> None:
            for sp in live.on_scan(scan, samplers):
                step(sp)
            for smp in samplers.values():  # keep only what the scans still pending need
                smp.prune(live.need_since_s())

        # keep=False: the capture holds no scans and the samplers every sample until
        # pruned above - a long live run loses no nod angle and its memory stays flat
        cap = s.capture(lambda scans, _nod: len(scans) >= args.scans, lift=args.lifted,
                        on_scan=on_scan, keep=False)
        for sp in live.finish(cap):
            step(sp)
    print(f"live: tracked {live.n_done} of {live.n_in} scans (calibration "
          f"{model.calibration_id})", file=sys.stderr)


MAX_SIM_SCANS = 20_000     # simulated up front: ~35 min of sensor time
MAX_LIVE_SCANS = 100_000   # 2.8 h at 10 Hz


def run(args: argparse.Namespace) -> int:
    from ..errors import require
    from ..solver import solve
    from ..spec import load_design
    from ..tracking.segment import OnlineSegmenter
    from ..tracking.tracker import Tracker, TrackerConfig

    # the simulator makes every scan up front (memory grows with --scans); live and recorded
    # scans stream, but a run still ends (2.8 h at 10 Hz)
    hi = MAX_SIM_SCANS if args.sim else MAX_LIVE_SCANS
    require(1 <= args.scans <= hi, "--scans", args.scans, f"1 .. {hi}")
    require(math.isfinite(args.sensor_height), "--sensor-height", args.sensor_height,
            "a finite height [m]")
    if args.port is not None or args.servo_port is not None:
        require(args.recording == "live", "recording", args.recording,
                "'live' with --port/--servo-port")
    show = _Printer(args.json)

    if args.recording and not args.sim and args.recording != "live":
        from ..tracking.recording import scans_from_recording

        require(args.perturb == "none", "--perturb", args.perturb,
                "none with a recording (it applies to the simulated sensor: --sim or live)")
        design, scans = scans_from_recording(args.recording, sensor_height_m=args.sensor_height,
                                             calibration=args.calibration)
        print(f"recording {args.recording}: {len(scans)} scans (calibration "
              f"{scans[0].calibration_id})", file=sys.stderr)
    else:
        design = solve(load_design(args.design))
        scans = None
    seg = OnlineSegmenter(range_sigma=design.lidar.range_sigma_m)
    # the lidar's range noise, as the evaluation (run_online) gives it: the margins of the
    # seen-through test and the round model's residuals are in units of it
    trk = Tracker(TrackerConfig(entropy=args.entropy), range_sigma=design.lidar.range_sigma_m)

    def step(scan_points) -> None:
        show(trk.update(seg.update(scan_points)))

    if args.recording == "live" and not args.sim:
        from ..tracking.segment import warm_up

        warm_up()  # compiled now, not inside the capture's first callback
        _live(args, step)
        return 0
    if scans is None:
        from ..runtime.assembly import AssemblyModel
        from ..tracking.simdata import simulate_scans
        from ._runtime_args import sim_perturbations

        perts, cal_id = None, "none"
        if args.calibration is not None:
            from ..calibration.calfile import load_calibration

            cal = load_calibration(args.calibration, design)
            perts, cal_id = cal.perturbations, cal.id
        # the runtime's model, as a live session builds it: the design, calibrated by the
        # file if one is given (not by the simulator's truth)
        model = AssemblyModel.from_design(design, perts, cal_id)
        scans = simulate_scans(design, args.scans, mirrors_deployed=not args.lifted,
                               scene=args.scene, noise=not args.no_noise, seed=args.seed,
                               perturbations=sim_perturbations(args.perturb), model=model)
        print(f"sim: {len(scans)} scans (sensor as built: {args.perturb}; calibration "
              f"{model.calibration_id})", file=sys.stderr)
    for scan in scans:
        step(scan)
    sys.stdout.flush()
    return 0
