"""Run a runtime session and publish what it sees over the Foxglove WebSocket protocol.

:class:`FoxgloveSink` owns the foxglove context, its channels, the WebSocket server and the
optional MCAP writer (both get every message). :func:`run_view` nods the head, assembles
the scans as they arrive (:class:`~nodlidar.runtime.session.LiveAssembler`, the same
points ``nodlidar scan``/``replay`` give) and publishes:

- ``/nodlidar/cloud`` (foxglove.PointCloud, frame ``sensor``): the growing cloud - every
  point so far, the newest ``max_points`` once there are more;
- ``/nodlidar/mirrors`` (foxglove.SceneUpdate, frame ``head``): the mirror patches of the
  solved design, with the session's calibration applied;
- ``/tf`` (foxglove.FrameTransforms): world -> sensor -> head (the nod, every scan);
- ``/nodlidar/tracks`` (foxglove.SceneUpdate, frame ``world``): the tracker's tracks, when
  the tracker can be built (a worker thread, so a slow update never stalls the stream).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import DeviceError, require
from . import encode

if TYPE_CHECKING:
    from ..design import Design
    from ..runtime.assembly import AssemblyModel, PointCloud
    from ..runtime.servo_angles import MirrorLiftProfile
    from ..runtime.session import Session
    from ..tracking.recording import LiveScans
    from ..tracking.segment import OnlineSegmenter
    from ..tracking.tracker import Tracker

__all__ = ["TOPICS", "FoxgloveSink", "CloudWindow", "ViewStats", "run_view", "build_tracking"]

_log = logging.getLogger(__name__)   # debug detail (nodlidar -v)

#: Scans the tracker thread may lag behind before scans are skipped for tracking.
TRACK_BACKLOG = 50

TOPICS = {"cloud": "/nodlidar/cloud", "mirrors": "/nodlidar/mirrors", "tracks": "/nodlidar/tracks",
          "tf": "/tf"}


class CloudWindow:
    """The newest ``max_points`` points of a growing cloud, kept packed (bytes-ready)."""

    def __init__(self, max_points: int) -> None:
        require(max_points >= 1, "max_points", max_points, ">= 1")
        self.max_points = int(max_points)
        self._chunks: list[np.ndarray] = []
        self.n = 0          # points held
        self.total = 0      # points ever added

    def add(self, cloud: PointCloud) -> None:
        """Append a :class:`~nodlidar.runtime.assembly.PointCloud` chunk."""
        n = len(cloud)
        if n == 0:
            return
        nod = cloud.nod_rad if cloud.nod_rad is not None else np.full(n, np.nan)
        packed = np.frombuffer(encode.pack_points(cloud.xyz, cloud.range_m, nod, cloud.mirror,
                                                  cloud.scan), encode.CLOUD_DTYPE)
        self._chunks.append(packed)
        self.n += n
        self.total += n
        while self.n - len(self._chunks[0]) >= self.max_points:   # drop whole old chunks
            self.n -= len(self._chunks.pop(0))

    def data(self) -> bytes:
        """The newest ``max_points`` points, packed."""
        if not self._chunks:
            return b""
        allp = np.concatenate(self._chunks) if len(self._chunks) > 1 else self._chunks[0]
        return allp[-self.max_points:].tobytes()


class FoxgloveSink:
    """The foxglove channels, WebSocket server and MCAP writer of one view.

    Nothing is opened in the constructor: :meth:`start` binds the server (``port`` 0: any
    free port) and creates the MCAP file; :meth:`close` stops both.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8765, mcap: str | Path | None = None,
                 overwrite: bool = False, name: str = "nodlidar") -> None:
        require(0 <= int(port) <= 65535, "--ws-port", port, "0 (any free port) .. 65535")
        self.host, self.port, self.name = host, int(port), name
        self.mcap_path = Path(mcap) if mcap is not None else None
        self.overwrite = overwrite
        self.server: Any = None    # foxglove.WebSocketServer once started
        self.writer: Any = None    # foxglove.mcap.MCAPWriter with --mcap
        self.context: Any = None
        self.channels: dict[str, Any] = {}
        self.messages: dict[str, int] = dict.fromkeys(TOPICS, 0)
        self._lock = threading.Lock()   # the tracker thread publishes too

    def start(self) -> str:
        """Open the channels, the server and the MCAP file; returns the ``ws://`` URL."""
        import foxglove
        from foxglove.channels import FrameTransformsChannel, PointCloudChannel, SceneUpdateChannel

        # the context must outlive the channels (a dropped context closes them)
        self.context = ctx = foxglove.Context()
        self.channels = {"cloud": PointCloudChannel(TOPICS["cloud"], context=ctx),
                         "mirrors": SceneUpdateChannel(TOPICS["mirrors"], context=ctx),
                         "tracks": SceneUpdateChannel(TOPICS["tracks"], context=ctx),
                         "tf": FrameTransformsChannel(TOPICS["tf"], context=ctx)}
        if self.mcap_path is not None:
            self.writer = foxglove.open_mcap(self.mcap_path, allow_overwrite=self.overwrite,
                                             context=ctx)
        try:
            self.server = foxglove.start_server(name=self.name, host=self.host, port=self.port,
                                                context=ctx)
        except BaseException:
            if self.writer is not None:
                self.writer.close()
            raise
        return self.url

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.server.port}"

    def publish(self, kind: str, msg: Any, t_ns: int) -> None:
        with self._lock:
            self.channels[kind].log(msg, log_time=t_ns)
            self.messages[kind] += 1

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self.writer is not None:
            self.writer.close()
            self.writer = None


@dataclass
class ViewStats:
    """What a view published."""

    scans: int = 0
    points: int = 0
    cloud_points: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    tracks: int = 0
    tracks_skipped: int = 0
    tracking: str = "off"
    stats: dict[str, int] = field(default_factory=dict)


def _opened(session: Session) -> tuple[Design, AssemblyModel, MirrorLiftProfile, MirrorLiftProfile]:
    """The design, assembly model and lift profiles of an open session."""
    s = session
    if s.design is None or s.model is None or s.lift_left is None or s.lift_right is None:
        raise DeviceError("the session is not open (use it inside 'with Session(...)')")
    return s.design, s.model, s.lift_left, s.lift_right


def build_tracking(session: Session, sensor_height_m: float) -> tuple[
        tuple[LiveScans, OnlineSegmenter, Tracker] | None, str | None]:
    """``(live_scans, segmenter, tracker)`` for the session, or ``(None, reason)`` when the
    tracker cannot be built (kept loose: tracking is optional in a view)."""
    try:
        from ..tracking.recording import LiveScans
        from ..tracking.segment import OnlineSegmenter, warm_up
        from ..tracking.tracker import Tracker, TrackerConfig

        design, model, lift_left, lift_right = _opened(session)
        warm_up()  # the tracking's compiled loops, before the first scan reaches them
        live = LiveScans(model, (lift_left, lift_right), sensor_height_m=sensor_height_m)
        return (live, OnlineSegmenter(range_sigma=design.lidar.range_sigma_m),
                Tracker(TrackerConfig(), range_sigma=design.lidar.range_sigma_m)), None
    except Exception as exc:   # noqa: BLE001 - any API drift in the tracker: view without tracks
        return None, f"{type(exc).__name__}: {exc}"


class _TrackWorker(threading.Thread):
    """Segment + track ScanPoints off the stream thread; publish the tracks."""

    def __init__(self, seg, trk, sink: FoxgloveSink, log: Callable[[str], None]) -> None:
        super().__init__(name="nodlidar-view-tracks", daemon=True)
        self.seg, self.trk, self.sink, self.log = seg, trk, sink, log
        self.q: queue.Queue = queue.Queue()
        self.ids: set[int] = set()
        self.error: str | None = None
        self.stopping = threading.Event()

    def run(self) -> None:
        while (sp := self.q.get()) is not None:
            if self.error is not None or self.stopping.is_set():
                continue   # drain: after the view stopped, a backlog is not worth tracking
            try:
                states = self.trk.update(self.seg.update(sp))
                self.ids.update(int(s.track_id) for s in states)
                self.sink.publish("tracks", encode.track_update(states, time.time_ns()), time.time_ns())
            except Exception as exc:   # noqa: BLE001 - the view goes on without tracks
                self.error = f"{type(exc).__name__}: {exc}"
                self.log(f"tracking stopped: {self.error}")


def run_view(session: Session, sink: FoxgloveSink, *, duration_s: float | None = None,
             max_points: int = 200_000, batch_scans: int = 3, cloud_period_s: float = 0.5,
             track: bool = True,
             sensor_height_m: float = 0.4, lift: bool = False,
             log: Callable[[str], None] | None = None,
             stop: threading.Event | None = None) -> ViewStats:
    """Stream an open ``session`` to a started ``sink`` until ``duration_s`` (wall seconds;
    None: until ``stop`` is set or KeyboardInterrupt).

    Scans are assembled in batches of ``batch_scans``; the cloud (the newest
    ``max_points``) is published at most every ``cloud_period_s`` wall seconds and once at
    the end, the mirrors with every cloud (so a client that connects late still gets
    them), the nod transform every scan.
    """
    from ..runtime.session import LiveAssembler

    log = log or (lambda _m: None)
    require(max_points >= 1, "--max-points", max_points, ">= 1")
    require(duration_s is None or (math.isfinite(duration_s) and duration_s > 0), "--duration",
            duration_s, "> 0 seconds")
    design, model, lift_left, lift_right = _opened(session)
    pivot = design.spec.nod.pivot_m
    perts = session.calibration.perturbations if session.calibration is not None else None
    patches = design.patches(perts)
    window = CloudWindow(max_points)
    stats = ViewStats()

    last_cloud = [-math.inf]

    def publish_cloud(final: bool = False) -> None:
        # the whole window each time: rate-limited, a 200 000-point cloud is 5.6 MB
        if window.n == 0 or (not final and time.monotonic() - last_cloud[0] < cloud_period_s):
            return
        last_cloud[0] = time.monotonic()
        t = time.time_ns()
        sink.publish("cloud", encode.point_cloud(window.data(), t), t)
        sink.publish("mirrors", encode.mirror_update(patches, t), t)
        _log.debug("cloud %d published: %d points (%d so far), %d scans", sink.messages["cloud"],
                   min(window.n, max_points), window.total, stats.scans)

    def on_cloud(chunk) -> None:
        window.add(chunk)
        publish_cloud()

    assembler = LiveAssembler(model, lift_left, lift_right, on_cloud,
                              batch_scans=batch_scans)
    tracking, why = build_tracking(session, sensor_height_m) if track else (None, "not asked")
    worker = None
    if tracking is not None:
        live_scans, seg, trk = tracking
        worker = _TrackWorker(seg, trk, sink, log)
        worker.start()
        stats.tracking = "on"
    else:
        stats.tracking = f"off ({why})"
        if track:
            log(f"tracks not shown: the tracker could not be built ({why})")
    t0 = time.time_ns()
    sink.publish("mirrors", encode.mirror_update(patches, t0), t0)
    sink.publish("tf", encode.frame_transforms(0.0, pivot, sensor_height_m, t0), t0)
    wall0 = time.monotonic()

    def on_scan(scan, samplers) -> None:
        stats.scans += 1
        assembler.add(scan, samplers)
        nod = samplers["nod"].samples()
        if len(nod.angle_rad):
            t = time.time_ns()
            sink.publish("tf", encode.frame_transforms(float(nod.angle_rad[-1]), pivot,
                                                       sensor_height_m, t), t)
        need = assembler.need_since_s()
        if worker is not None and worker.error is None:
            for sp in live_scans.on_scan(scan, samplers):
                if worker.q.qsize() < TRACK_BACKLOG:
                    worker.q.put(sp)
                else:   # the tracker is slower than the sensor: memory stays bounded
                    if not stats.tracks_skipped:
                        log(f"tracker behind by {TRACK_BACKLOG} scans: skipping scans")
                    stats.tracks_skipped += 1
            need = min(need, live_scans.need_since_s())
        for smp in samplers.values():   # memory stays flat however long the view runs
            smp.prune(need)

    def done(_scans, _nod) -> bool:
        return ((duration_s is not None and time.monotonic() - wall0 >= duration_s)
                or (stop is not None and stop.is_set()))

    try:
        cap = session.capture(done, lift=lift, on_scan=on_scan, keep=False)
        assembler.finish(cap.joints)
        publish_cloud(final=True)
    except KeyboardInterrupt:   # Ctrl-C is how a view ends: a clean summary, not an error
        pass
    finally:
        if worker is not None:
            # finish the update in progress, skip the backlog, and wait: a thread still in
            # native code when the interpreter exits aborts the process
            worker.stopping.set()
            worker.q.put(None)
            worker.join()
            stats.tracks = len(worker.ids)
            if worker.error is not None:
                stats.tracking = f"stopped ({worker.error})"
    stats.points = window.total
    stats.cloud_points = min(window.n, max_points)
    stats.messages = dict(sink.messages)
    stats.stats = dict(assembler.stats)
    return stats
