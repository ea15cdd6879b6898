"""Evaluation of the live tracker on any scene: per-mover truth, online convergence,
multi-object metrics, mirrors vs lifted.

Truth comes from the scene itself (:func:`mover_truth`: every mover's trajectory gives its
ground-plane position and velocity at any time). :func:`run_online` feeds simulated scans,
one at a time, to a :class:`~nodlidar.tracking.tracker.Tracker` (segmenting online: evidence
so far only) and keeps what the tracker said after every scan. The metrics only use what the
live tracker reported at the time (causal):

* **following**: in each scan, a track follows the mover that holds more than half of the
  points it took in that scan (simulator truth per beam), and a mover is followed by the
  track, of those following it, that took most of its points. Each track follows at most
  one mover per scan, as CLEAR MOT matches each hypothesis to one object: a track that took
  a few stray points of a neighbour (a person's edge beside another's cluster), or two
  people in one cluster, follows its majority only, and the other mover is not followed in
  that scan (a miss, not a change of identity);
* **online convergence** of a mover: its estimates are those of the track following it, in
  the scans where one does (1-based count of those scans, as the paper counts scans with the
  object; tracks never confirmed - one sighting, no velocity, never reported - are left
  out, as for identity switches and purity); the first count after which every estimate
  stays within ``V_TOL_M_S`` (0.01 m/s) of the true speed and ``HEADING_TOL_DEG`` (2 deg)
  of the true heading at the estimate's time; None when the last estimate is not.
  ``conv_scan`` is the same moment as the run's scan number (1-based): time since the
  start. The two differ when a configuration sees the object in more of the scans
  (mirrors: more windows cross it per nod cycle), so a count of 15 with mirrors can come
  sooner than a count of 10 lifted;
* **first scan** of a mover (``first_scan``): the run's scan number (1-based) in which a
  track first followed it, i.e. when the configuration first saw it as a mover. With the
  mirrors deployed the view is the middle of the fan (the sides go to the mirrors), so a
  mover that starts beside the sensor is first seen later than lifted, and its
  ``conv_scan`` can only be later by as much;
* **reported scan** of a mover (``reported_scan``): the run's scan number (1-based) of
  the first scan in which a confirmed track followed it, i.e. when the tracker's output
  first held it (None: never). ``first_scan`` is when any track, tentative or not, did;
* **in view** of a mover (``view_scan``): the run's scan number (1-based) in which the
  configuration's beams first returned ``VIEW_POINTS`` points or more from it (simulator
  truth, whatever the tracker made of them): the earliest it could be seen at all. Where
  the mirrors' ``view_scan`` is after the scan at which lifted converged, no tracker
  converges as early with the mirrors: the view, not the estimate, sets the delay.
  ``conv_after_view`` is ``conv_scan - view_scan``: how long the configuration took to
  converge once its beams met the mover;
* **identity switches**: how often the track following a mover changes, counted over the
  tracks the tracker confirmed (its output): a tentative track never confirmed (seen in
  fewer than ``confirm_scans`` scans, then lost) was never reported as an object, so it is
  no identity, as CLEAR MOT counts switches between the tracker's hypotheses. Such tracks
  are listed per mover as ``tentative_tracks`` (and in ``tracks``): a sliver of a person
  seen once before they walk behind another, then a track from when they come out, is one
  identity, not two;
* **purity** of a mover: of the points of the (confirmed) track that followed it longest,
  the fraction that are the mover's;
* **GOSPA** (Stone Soup's :class:`~stonesoup.metricgenerator.ospametric.GOSPAMetric`,
  p = 1, c = ``gospa_c_m``, alpha = 2): per scan, the confirmed tracks' positions against
  the movers' true positions, averaged over the scans;
* **false tracks**: confirmed tracks most of whose points are the static world (simulator
  truth 0: walls, furniture), i.e. something static taken for a mover.

A mover whose trajectory is ``fixed`` (a person standing still) has no heading: its
estimates are judged on speed alone, and ``scans_followed`` says how often a track took it
for a mover at all (the right answer is never).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import require
from .segment import SegmentConfig
from .tracker import Tracker, TrackerConfig

if TYPE_CHECKING:
    from pathlib import Path

    from ..design import Design
    from ..geometry import Perturbation
    from ..sim.raycast import SceneSimulator
    from ..sim.scene import Scene

__all__ = ["V_TOL_M_S", "HEADING_TOL_DEG", "VIEW_POINTS", "mover_truth", "OnlineResult",
           "run_online", "evaluate", "online_convergence", "false_tracks", "compare_mirrors",
           "comparison_markdown", "summary_rows", "grid_scene"]

V_TOL_M_S = 0.01
HEADING_TOL_DEG = 2.0
#: points of a mover one scan must return for ``view_scan``: the segmentation's least
#: cluster (``SegmentConfig.min_cluster_points``)
VIEW_POINTS = 5


def grid_scene(speed_m_s: float, heading_deg: float, length_m: float = 3.0) -> Scene:
    """The issue's speed x heading grid: the paper's cylinder (r 0.18 m, 1 m tall) back
    and forth on a leg of ``length_m`` [m] through (2.5, 0) at ``speed_m_s`` [m/s],
    heading ``heading_deg`` [deg], in an 8 x 6 m room without a ceiling."""
    from ..sim.scene import scene_from_dict

    u = np.array([np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))])
    s = np.array([2.5, 0.0]) - length_m / 2 * u
    return scene_from_dict({"name": f"grid {speed_m_s:g} x {heading_deg:g}",
                            "room": {"size_m": [8.0, 6.0, 2.5], "center_m": [2.5, 0.0],
                                     "ceiling": False},
                            "mover": [{"radius_m": 0.18, "height_m": 1.0,
                                       "trajectory": "back_and_forth",
                                       "start_m": [float(s[0]), float(s[1]), 0.0],
                                       "heading_deg": heading_deg, "length_m": length_m,
                                       "speed_m_s": speed_m_s}]})


def mover_truth(scene: Scene, t_s: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Ground-plane positions and velocities of every mover of ``scene`` at times ``t_s``.

    Returns
    -------
    (n_movers, n, 2) positions [m] and (n_movers, n, 2) velocities [m/s]. Velocity by the
    trajectory's own law (fixed: 0; constant velocity: its vector; back and forth and
    waypoints: the current leg's, 0 while it waits), not by differencing positions.
    """
    from ..sim.scene import BackAndForth, ConstantVelocity, Fixed, Waypoints

    t = np.atleast_1d(np.asarray(t_s, float))
    pos, vel = [], []
    for m in scene.movers:
        tr = m.trajectory
        pos.append(np.asarray(tr.position(t))[:, :2])
        if isinstance(tr, BackAndForth | Waypoints):
            vel.append(np.asarray(tr.velocity(t))[:, :2])
        elif isinstance(tr, ConstantVelocity):
            vel.append(np.broadcast_to(np.asarray(tr.velocity_m_s)[:2], (len(t), 2)).copy())
        else:
            require(isinstance(tr, Fixed), "trajectory", type(tr).__name__,
                    "Fixed, ConstantVelocity, BackAndForth or Waypoints")
            vel.append(np.zeros((len(t), 2)))
    shape = (len(scene.movers), len(t), 2)
    return np.asarray(pos).reshape(shape), np.asarray(vel).reshape(shape)


@dataclass
class OnlineResult:
    """What the live tracker reported, scan by scan.

    ``records``: one dict per track update (scan, track, t_s, x_m, y_m, v_m_s, heading_rad,
    confirmed, counts: {truth id: points}). ``confirmed``: per scan, the confirmed live
    tracks' (t_s, x, y). ``update_s``: wall time of each ``Tracker.update`` [s].
    ``returns``: per scan, {"scan": its number, truth id: points} over every return of the
    scan (what the beams saw, tracked or not).
    """

    scene: Scene
    mirrors_deployed: bool
    entropy: str
    seed: int
    n_scans: int
    records: list[dict] = field(default_factory=list)
    confirmed: list[list[tuple[float, float, float]]] = field(default_factory=list)
    scan_t_s: list[float] = field(default_factory=list)
    update_s: list[float] = field(default_factory=list)
    returns: list[dict] = field(default_factory=list)


def run_online(design: Design, scene: Scene | str | Path, n_scans: int, *,
               mirrors_deployed: bool = True, seed: int = 0,
               entropy: str = "renyi", noise: bool = True, tracker: TrackerConfig | None = None,
               segment: SegmentConfig | None = None, simulator: SceneSimulator | None = None,
               perturbations: Mapping[str, Perturbation] | None = None) -> OnlineResult:
    """Simulate ``scene`` and run the tracker online on it (module docstring)."""
    import dataclasses
    import time

    from ..sim.scene import load_scene
    from .simdata import simulate_scans

    sc = load_scene(scene)
    cfg = dataclasses.replace(tracker or TrackerConfig(), entropy=entropy)
    scans = simulate_scans(design, n_scans, mirrors_deployed=mirrors_deployed, scene=sc,
                           perturbations=perturbations, noise=noise, seed=seed,
                           simulator=simulator)
    trk = Tracker(cfg, segment, design.lidar.range_sigma_m)
    res = OnlineResult(sc, mirrors_deployed, entropy, seed, n_scans)
    for s in scans:
        t0 = time.perf_counter()
        changed = trk.update(s)
        res.update_s.append(time.perf_counter() - t0)
        res.scan_t_s.append(s.t_mid_s)
        ids, cnt = (np.unique(s.truth_id, return_counts=True) if s.truth_id is not None
                    else (np.zeros(0, int), np.zeros(0, int)))
        res.returns.append({"scan": s.scan, **dict(zip(ids.tolist(), cnt.tolist()))})
        ended = {st.track_id for st in changed if not st.alive}
        for st in changed:
            if not st.alive or st.track_id in ended:
                continue
            tr = trk.tracks[st.track_id]
            ids, cnt = (np.unique(tr.truth[-1], return_counts=True) if tr.truth[-1] is not None
                        else (np.zeros(0, int), np.zeros(0, int)))
            res.records.append({"scan": s.scan, "track": st.track_id, "t_s": st.t_s,
                                "x_m": st.x_m, "y_m": st.y_m, "v_m_s": st.v_m_s,
                                "heading_rad": st.heading_rad, "confirmed": st.confirmed,
                                "counts": dict(zip(ids.tolist(), cnt.tolist()))})
        res.confirmed.append([(st.t_s, st.x_m, st.y_m) for st in trk.states() if st.confirmed])
    return res


def online_convergence(v: np.ndarray, h_err_deg: np.ndarray) -> int | None:
    """First 1-based index after which every ``|v| <= V_TOL_M_S`` and ``|h_err| <=
    HEADING_TOL_DEG`` (``v``: speed errors [m/s]; NaN = no estimate, not within)."""
    ok = (np.abs(np.asarray(v, float)) <= V_TOL_M_S) & \
        (np.abs(np.asarray(h_err_deg, float)) <= HEADING_TOL_DEG)
    if not len(ok) or not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 2) if len(bad) else 1


def _gospa(res: OnlineResult, c_m: float) -> float:
    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.types.state import State

    from .tracker import stone_soup_time

    metric = GOSPAMetric(p=1, c=c_m, measure=Euclidean(mapping=(0, 1)))
    out = []
    for t, conf in zip(res.scan_t_s, res.confirmed):
        pos, _ = mover_truth(res.scene, [t])
        stamp = stone_soup_time(t)
        truth = [State(p[0].reshape(2, 1), timestamp=stamp) for p in pos]
        est = [State(np.array([[x], [y]]), timestamp=stamp) for _, x, y in conf]
        if not truth and not est:
            continue
        out.append(metric.compute_gospa_metric(est, truth)[0].value["distance"])
    return float(np.mean(out)) if out else float("nan")


def false_tracks(res: OnlineResult) -> int:
    """Confirmed tracks most of whose points (over all their updates) are the static world
    (truth id 0)."""
    static: dict[int, int] = {}
    total: dict[int, int] = {}
    confirmed = set()
    for r in res.records:
        tid = r["track"]
        static[tid] = static.get(tid, 0) + r["counts"].get(0, 0)
        total[tid] = total.get(tid, 0) + sum(r["counts"].values())
        if r["confirmed"]:
            confirmed.add(tid)
    return int(sum(1 for t in confirmed if 2 * static[t] > total[t]))


def evaluate(res: OnlineResult, gospa_c_m: float = 1.0) -> dict:
    """Metrics of one online run (module docstring): per mover, and GOSPA."""
    movers = []
    confirmed = {r["track"] for r in res.records if r["confirmed"]}
    for k in range(len(res.scene.movers)):
        oid = 1 + k
        # per scan, of the tracks this mover is the majority of, the one that took most of
        # its points (module docstring, "following")
        best: dict[int, dict] = {}
        for r in res.records:
            n = r["counts"].get(oid, 0)
            if not n or 2 * n <= sum(r["counts"].values()):
                continue
            if r["scan"] not in best or n > best[r["scan"]]["counts"].get(oid, 0):
                best[r["scan"]] = r
        seq = [best[s] for s in sorted(best)]
        tracks = [r["track"] for r in seq]
        # identities: the confirmed tracks, in the order they followed the mover
        ids = [t for t in tracks if t in confirmed]
        switches = int(sum(a != b for a, b in zip(ids, ids[1:])))
        row: dict = {"mover": res.scene.movers[k].name, "scans_followed": len(seq),
                     "tracks": sorted(set(tracks)), "id_switches": switches,
                     "purity": None, "conv": None, "conv_scan": None, "conv_after_view": None,
                     "final_err_v_m_s": None,
                     "final_err_heading_deg": None,
                     "tentative_tracks": sorted(set(tracks) - confirmed),
                     "first_scan": int(seq[0]["scan"]) + 1 if seq else None,
                     "reported_scan": next((int(r["scan"]) + 1 for r in seq
                                            if r["confirmed"]), None),
                     "view_scan": next((int(c["scan"]) + 1 for c in res.returns
                                        if c.get(oid, 0) >= VIEW_POINTS), None)}
        # the estimates the tracker reported: a track never confirmed (one sighting, no
        # velocity yet) was not one, so its record is neither a wrong estimate nor the end
        # of the mover's sequence
        seq = [r for r in seq if r["track"] in confirmed]
        if seq:
            main = max(set(ids), key=ids.count)
            tot = own = 0
            for r in res.records:
                if r["track"] == main:
                    tot += sum(r["counts"].values())
                    own += r["counts"].get(oid, 0)
            row["purity"] = round(own / max(tot, 1), 4)
            t = np.array([r["t_s"] for r in seq])
            _, vel = mover_truth(res.scene, t)
            vt = vel[k]
            v = np.array([r["v_m_s"] for r in seq])
            h = np.array([r["heading_rad"] for r in seq])
            speed = np.hypot(vt[:, 0], vt[:, 1])
            ev = v - speed
            eh = (np.degrees(h - np.arctan2(vt[:, 1], vt[:, 0])) + 180.0) % 360.0 - 180.0
            # a mover standing still has no heading: judged on speed alone
            eh = np.where(speed > 0, eh, np.where(np.isfinite(v), 0.0, np.nan))
            row["conv"] = online_convergence(ev, eh)
            if row["conv"] is not None:
                # the same moment as a scan number of the run (1-based): time, not count
                row["conv_scan"] = int(seq[row["conv"] - 1]["scan"]) + 1
                if row["view_scan"] is not None:
                    row["conv_after_view"] = row["conv_scan"] - row["view_scan"]
            if np.isfinite(ev[-1]):
                row["final_err_v_m_s"] = round(float(ev[-1]), 4)
                row["final_err_heading_deg"] = round(float(eh[-1]), 3)
        movers.append(row)
    upd = np.asarray(res.update_s) * 1e3
    return {"config": "mirrors" if res.mirrors_deployed else "lifted", "entropy": res.entropy,
            "seed": res.seed, "scans": res.n_scans, "movers": movers,
            "gospa_m": round(_gospa(res, gospa_c_m), 4),
            "false_tracks": false_tracks(res),
            "update_ms_median": round(float(np.median(upd)), 2) if len(upd) else None,
            "update_ms_max": round(float(np.max(upd)), 2) if len(upd) else None}


def compare_mirrors(design: Design, scene: Scene | str | Path, seeds: Iterable[int], n_scans: int,
                    entropies: Sequence[str] = ("renyi",), **kw: Any) -> list[dict]:
    """Mirrors deployed vs lifted on ``scene`` over ``seeds``: one :func:`evaluate` dict per
    (seed, entropy, configuration) (``kw`` go to :func:`run_online`)."""
    from ..sim.raycast import SceneSimulator
    from ..sim.scene import load_scene

    sc = load_scene(scene)
    sim = SceneSimulator(design, sc, kw.pop("perturbations", None))
    out = []
    for seed in seeds:
        for ent in entropies:
            for dep in (True, False):
                out.append(evaluate(run_online(design, sc, n_scans, mirrors_deployed=dep,
                                               seed=seed, entropy=ent, simulator=sim, **kw)))
    return out


def _median(xs):
    """Median of convergence scans, None (not converged) counted as later than any."""
    if not xs:
        return None
    v = sorted(np.inf if x is None else x for x in xs)
    m = float(np.median(v))
    return None if not np.isfinite(m) else m


def summary_rows(results: list[dict]) -> list[dict]:
    """One row per (entropy, mover): median online convergence over seeds, mirrors vs
    lifted, median first scan seen (by a track, and by the beams) and reported (by a
    confirmed track; never: later than any), converged counts, worst
    purity, switches, final errors and GOSPA."""
    keys = sorted({(r["entropy"], i, m["mover"]) for r in results
                   for i, m in enumerate(r["movers"])})
    rows = []
    for ent, i, name in keys:
        row: dict = {"entropy": ent, "mover": name}
        for cfg in ("mirrors", "lifted"):
            rs = [r for r in results if r["entropy"] == ent and r["config"] == cfg]
            ms = [r["movers"][i] for r in rs]
            conv = [m["conv"] for m in ms]
            row[f"conv_{cfg}"] = _median(conv)
            row[f"conv_scan_{cfg}"] = _median([m.get("conv_scan") for m in ms])
            row[f"first_scan_{cfg}"] = _median([m.get("first_scan") for m in ms])
            row[f"view_scan_{cfg}"] = _median([m.get("view_scan") for m in ms])
            row[f"reported_scan_{cfg}"] = _median([m.get("reported_scan") for m in ms])
            row[f"conv_after_view_{cfg}"] = _median(
                [m["conv_scan"] - m["view_scan"]
                 if m.get("conv_scan") is not None and m.get("view_scan") is not None else None
                 for m in ms])
            row[f"converged_{cfg}"] = f"{sum(c is not None for c in conv)}/{len(conv)}"
            pur = [m["purity"] for m in ms if m["purity"] is not None]
            row[f"purity_min_{cfg}"] = min(pur) if pur else None
            row[f"switches_{cfg}"] = int(sum(m["id_switches"] for m in ms))
            ev = [abs(m["final_err_v_m_s"]) for m in ms if m["final_err_v_m_s"] is not None]
            eh = [abs(m["final_err_heading_deg"]) for m in ms
                  if m["final_err_heading_deg"] is not None]
            row[f"max_err_v_{cfg}"] = max(ev) if ev else None
            row[f"max_err_heading_{cfg}"] = max(eh) if eh else None
            g = [r["gospa_m"] for r in rs]
            row[f"gospa_{cfg}"] = round(float(np.mean(g)), 3) if g else None
            ft = [r.get("false_tracks", 0) for r in rs]
            row[f"false_tracks_{cfg}"] = int(sum(ft))
        rows.append(row)
    return rows


def comparison_markdown(rows: list[dict]) -> str:
    keys = list(rows[0])
    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join("-" if r[k] is None else str(r[k]) for k in keys) + " |"
            for r in rows]
    return "\n".join(out)
