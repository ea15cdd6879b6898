"""The mirror vs no-mirror study (paper Section VI) in simulation.

The same run twice - the paper's scenario (:func:`nodlidar.sim.scene.paper_tracking_scene`:
a cylinder of radius 0.18 m, 2 m ahead, moving at 0.13 m/s, heading 89.4 deg, back and forth;
the sensor on a robot with known pose) - with the mirrors deployed and with them lifted; same
scans, nod ramp and noise seed. Per configuration:

* **traces**: a trace is a maximal run of consecutive steps of one mirror window (or of the
  direct beams) in one scan whose beams all hit the object (simulator ground truth), one beam
  at least. The paper's "contiguous measurements" (Fig. 10 caption).
* **point density**: object points per scan that sees it, and in total.
* **segmentation**: precision / recall of the dynamic points against ground truth (over all
  returned beams, ground included).
* **convergence**: after each scan ``k`` (1-based count of the scans in which the tracked
  object was detected) the estimate from all its scans so far. The *convergence scan* of
  ``v`` is the first ``k`` from which every later estimate is within ``V_TOL_M_S`` = 0.01 m/s
  of the truth; of the heading, within ``HEADING_TOL_DEG`` = 2 deg; ``"both"`` the later of
  the two. ``None``: not converged by the end. Measured against the truth (the paper's
  VICON), the same definition for both configurations and both entropies.

Findings (seed sweeps with :func:`seed_sweep`; notebook 03 has the table): Rényi's quadratic
entropy converges in every run, with the mirrors earlier in 7 of 8 seeds (median scan 6.5
vs 12); the paper's voxel entropy (eq. 12) converges late (scan 15-27 of 27) and without
the mirrors not at all in 2 of 6 seeds (final heading 2.1-2.4 deg off), its final speed
always within 0.01 m/s. The paper's 7 vs 9 is not reproduced by either.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..paper import TRACKING_HEADING_DEG, TRACKING_SPEED_M_S
from .motion import coarse_motion, compensate, refine_motion
from .scans import ScanPoints
from .segment import SegmentConfig, segment_batch
from .simdata import simulate_scans
from .tracker import Tracker, TrackerConfig

if TYPE_CHECKING:
    from pathlib import Path

    from matplotlib.figure import Figure  # noqa: TID251 (types only, never imported at run time)

    from ..design import Design
    from ..sim.scene import Scene
    from .segment import Segmented

__all__ = ["table_markdown", "table_csv", "V_TOL_M_S", "HEADING_TOL_DEG", "count_traces",
           "convergence_index", "ConfigResult", "StudyResult", "seed_sweep", "plot_segmentation",
           "run_config", "run_study", "study_table", "plot_clouds", "plot_convergence"]

V_TOL_M_S = 0.01
HEADING_TOL_DEG = 2.0


def count_traces(scan: ScanPoints, on_object: np.ndarray) -> int:
    """Number of traces (module docstring) in one scan: maximal runs of consecutive steps of
    the same mirror id with ``on_object`` true."""
    o = np.asarray(on_object, bool)
    if not o.any():
        return 0
    order = np.argsort(scan.steps, kind="stable")
    st, mi, oo = scan.steps[order], scan.mirror[order], o[order]
    n = 0
    for m in np.unique(mi[oo]):
        s = st[(mi == m) & oo]
        n += 1 + int(np.sum(np.diff(s) > 1))
    return n


def convergence_index(values: np.ndarray, truth: float, tol: float) -> int | None:
    """First 1-based index from which every value is within ``tol`` of ``truth`` (None if the
    last one is not)."""
    ok = np.abs(np.asarray(values, float) - truth) <= tol
    if not len(ok) or not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 2) if len(bad) else 1


def _angdiff_deg(a_rad: np.ndarray, b_deg: float) -> np.ndarray:
    return (np.degrees(np.asarray(a_rad)) - b_deg + 180.0) % 360.0 - 180.0


@dataclass
class ConfigResult:
    """One configuration's numbers (see the module docstring)."""

    mirrors_deployed: bool
    n_scans: int
    scans_seen: int
    scans_detected: int
    traces_per_scan: list[int]
    points_per_scan: list[int]
    precision: float
    recall: float
    estimates: dict[str, dict[str, list[float]]]  # entropy -> {"scan","v","heading_deg"}
    convergence: dict[str, dict[str, int | None]]
    final_error: dict[str, dict[str, float]]
    cloud: dict[str, np.ndarray] = field(default_factory=dict)
    segments: list[Any] = field(default_factory=list)  # every scan's Segmented (Figs 11b/12b)

    @property
    def traces_total(self) -> int:
        return int(sum(self.traces_per_scan))

    @property
    def points_total(self) -> int:
        return int(sum(self.points_per_scan))

    @property
    def label(self) -> str:
        return "mirrors" if self.mirrors_deployed else "no mirrors"


@dataclass
class StudyResult:
    configs: list[ConfigResult]
    truth_v_m_s: float
    truth_heading_deg: float
    n_scans: int
    robot_velocity_m_s: tuple[float, ...] = (0.0, 0.0, 0.0)


def _driving(scene: Scene | str | Path, robot_velocity_m_s: Sequence[float] | None) -> Scene:
    """``scene`` with its sensor (the robot) driving at a constant world velocity [m/s]."""
    import dataclasses

    from ..sim.scene import load_scene

    sc = load_scene(scene)
    if robot_velocity_m_s is None or not any(robot_velocity_m_s):
        return sc
    v = tuple(float(x) for x in robot_velocity_m_s) + (0.0,) * (3 - len(robot_velocity_m_s))
    return dataclasses.replace(sc, sensor=dataclasses.replace(sc.sensor,
                                                              velocity_m_s=(v[0], v[1], v[2])))


def run_config(design: Design, *, mirrors_deployed: bool, n_scans: int = 38, seed: int = 0,
               noise: bool = True, entropies: Sequence[str] = ("renyi", "voxel"),
               segment: SegmentConfig | None = None, tracker: TrackerConfig | None = None,
               scene: Scene | str | Path = "paper-tracking",
               robot_velocity_m_s: Sequence[float] | None = None) -> ConfigResult:
    """Simulate, segment, track and evaluate one configuration.

    ``robot_velocity_m_s`` : (vx, vy[, vz]) [m/s], optional
        The robot carrying the sensor drives at this world velocity; its pose is known
        (the paper's "reliable localisation"), so every scan is placed in the world by it.
    """
    segment = segment or SegmentConfig()
    # the study re-estimates from all the track's points after each scan count
    tracker = dataclasses.replace(tracker or TrackerConfig(), keep_points=True)
    scans = simulate_scans(design, n_scans, mirrors_deployed=mirrors_deployed, seed=seed,
                           noise=noise, scene=_driving(scene, robot_velocity_m_s))
    segs = segment_batch(scans, segment, design.lidar.range_sigma_m)
    tp = fp = fn = 0
    traces, npts = [], []
    for s in segs:
        assert s.scan.truth_id is not None  # simulated scans carry the ground truth
        truth = s.scan.truth_id >= 1
        tp += int(np.sum(s.dynamic & truth))
        fp += int(np.sum(s.dynamic & ~truth))
        fn += int(np.sum(~s.dynamic & truth))
        if truth.any():
            traces.append(count_traces(s.scan, truth))
            npts.append(int(truth.sum()))
    trk = Tracker(tracker, range_sigma=design.lidar.range_sigma_m)  # as run_online
    for s in segs:
        trk.update(s)
    tracks = trk.all_tracks()
    v_true, h_true = TRACKING_SPEED_M_S, TRACKING_HEADING_DEG
    # "scan" holds ints (scan counts) among the floats
    estimates: dict[str, dict[str, list[float]]] = {}
    conv: dict[str, dict[str, int | None]] = {}
    final: dict[str, dict[str, float]] = {}
    cloud: dict[str, np.ndarray] = {}
    best = max(tracks, key=lambda tr: len(tr.scans)) if tracks else None
    k_det = len(best.scans) if best else 0
    for ent in entropies:
        ks: list[float] = []
        vs: list[float] = []
        hs: list[float] = []
        for k in range(2, k_det + 1):
            assert best is not None  # k_det > 0
            C = np.array(best.centroids[:k])
            T = np.array(best.t_centroids[:k])
            P = np.concatenate(best.points[:k])
            Tp = np.concatenate(best.times[:k])
            m = refine_motion(P, Tp, coarse_motion(C, T), entropy=ent, sigma_m=tracker.sigma_m,
                              voxel_m=tracker.voxel_m, n_scans=k)
            ks.append(k)
            vs.append(m.v_m_s)
            hs.append(float(np.degrees(m.heading_rad)))
        estimates[ent] = {"scan": ks, "v": vs, "heading_deg": hs}
        herr = _angdiff_deg(np.radians(hs), h_true) if hs else np.zeros(0)
        # index 1 (one scan) has no estimate: pad so indices are scan counts
        cv = convergence_index(np.r_[np.inf, vs], v_true, V_TOL_M_S)
        ch = convergence_index(np.r_[np.inf, herr + h_true], h_true, HEADING_TOL_DEG)
        conv[ent] = {"v": cv, "heading": ch,
                     "both": None if cv is None or ch is None else max(cv, ch)}
        final[ent] = {"v_m_s": float(vs[-1] - v_true) if vs else float("nan"),
                      "heading_deg": float(herr[-1]) if hs else float("nan")}
    if best is not None and estimates.get(entropies[0], {}).get("v"):
        e = estimates[entropies[0]]
        vel = np.array([e["v"][-1] * np.cos(np.radians(e["heading_deg"][-1])),
                        e["v"][-1] * np.sin(np.radians(e["heading_deg"][-1]))])
        P = np.concatenate(best.points)
        Tp = np.concatenate(best.times)
        mir = np.concatenate(best.mirrors)
        cloud = {"points": compensate(P, Tp, vel, float(Tp.max())), "raw": P, "t": Tp, "mirror": mir}
    return ConfigResult(mirrors_deployed, n_scans, len(traces), k_det, traces, npts,
                        tp / max(tp + fp, 1), tp / max(tp + fn, 1), estimates, conv, final, cloud,
                        list(segs))


def run_study(design: Design, n_scans: int = 38, seed: int = 0, noise: bool = True,
              entropies: Sequence[str] = ("renyi", "voxel"), **kw: Any) -> StudyResult:
    """Both configurations, same run otherwise (``kw`` go to :func:`run_config`)."""
    res = [run_config(design, mirrors_deployed=dep, n_scans=n_scans, seed=seed, noise=noise,
                      entropies=entropies, **kw) for dep in (True, False)]
    rv = tuple(float(x) for x in (kw.get("robot_velocity_m_s") or (0.0, 0.0, 0.0)))
    return StudyResult(res, TRACKING_SPEED_M_S, TRACKING_HEADING_DEG, n_scans, rv)


def study_table(result: StudyResult) -> list[dict]:
    """One row per (configuration, entropy)."""
    rows = []
    for c in result.configs:
        for ent, cv in c.convergence.items():
            e = c.estimates[ent]
            rows.append({
                "config": c.label, "entropy": ent, "scans": c.n_scans,
                "scans_seeing_object": c.scans_seen, "scans_detected": c.scans_detected,
                "traces_total": c.traces_total,
                # the paper counts traces over the 13 scans that saw the object
                "traces_first_13_scans": int(sum(c.traces_per_scan[:13])),
                "traces_per_scan": round(c.traces_total / max(c.scans_seen, 1), 2),
                "points_per_scan": round(c.points_total / max(c.scans_seen, 1), 1),
                "points_total": c.points_total,
                "precision": round(c.precision, 4), "recall": round(c.recall, 4),
                "conv_v": cv["v"], "conv_heading": cv["heading"], "conv_both": cv["both"],
                "final_v_m_s": round(e["v"][-1], 4) if e["v"] else None,
                "final_heading_deg": round(e["heading_deg"][-1], 3) if e["v"] else None,
                "err_v_m_s": round(c.final_error[ent]["v_m_s"], 4),
                "err_heading_deg": round(c.final_error[ent]["heading_deg"], 3),
            })
    return rows


def table_markdown(rows: list[dict]) -> str:
    keys = list(rows[0])
    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join("-" if r[k] is None else str(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(out)


def table_csv(rows: list[dict]) -> str:
    keys = list(rows[0])
    return "\n".join([",".join(keys)] + [",".join("" if r[k] is None else str(r[k]) for k in keys)
                                         for r in rows]) + "\n"


def seed_sweep(design: Design, seeds: Iterable[int], n_scans: int = 38,
               entropies: Sequence[str] = ("renyi",), **kw: Any) -> list[dict]:
    """Convergence scan ("both") and final errors per noise seed, both configurations: how
    robust the single-run comparison is. One row per (seed, entropy); ``kw`` go to
    :func:`run_config`."""
    rows = []
    for seed in seeds:
        res = run_study(design, n_scans=n_scans, seed=seed, entropies=entropies, **kw)
        m, n = res.configs
        for ent in entropies:
            rows.append({"seed": seed, "entropy": ent,
                         "conv_mirrors": m.convergence[ent]["both"],
                         "conv_no_mirrors": n.convergence[ent]["both"],
                         "err_v_mirrors": round(m.final_error[ent]["v_m_s"], 4),
                         "err_v_no_mirrors": round(n.final_error[ent]["v_m_s"], 4),
                         "err_heading_mirrors": round(m.final_error[ent]["heading_deg"], 3),
                         "err_heading_no_mirrors": round(n.final_error[ent]["heading_deg"], 3)})
    return rows


def plot_clouds(result: StudyResult) -> Figure:
    """Figs 10-12 analogue: motion-compensated accumulated object cloud, side (y-z) and top
    (x-y) views, per configuration; magenta direct, cyan mirror-reflected (as the paper's
    Fig. 12). Returns the figure."""
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    fig, axes = plt.subplots(len(result.configs), 2, figsize=(10, 3.2 * len(result.configs)),
                             squeeze=False)
    for row, c in zip(axes, result.configs):
        if not c.cloud:
            continue
        q = c.cloud["points"]
        refl = c.cloud["mirror"] >= 0
        for sel, col, lab in ((~refl, "magenta", "direct"), (refl, "c", "mirror-reflected")):
            if sel.any():
                row[0].scatter(q[sel, 1], q[sel, 2], s=2, color=col, label=lab)
                row[1].scatter(q[sel, 0], q[sel, 1], s=2, color=col, label=lab)
        row[0].set(xlabel="y [m]", ylabel="z [m]", title=f"{c.label}: side view ({len(q)} points)")
        row[1].set(xlabel="x [m]", ylabel="y [m]", title=f"{c.label}: top view", aspect="equal")
        row[1].legend(fontsize=7, markerscale=4)
    fig.tight_layout()
    return fig


def plot_segmentation(seg: Segmented | list[Segmented] | tuple[Segmented, ...],
                      title: str | None = None) -> Figure:
    """Top view of segmented scans (one ``Segmented`` or a list, accumulated; the paper's
    Figs 11b/12b): static returns grey, dynamic (segmented) red, the ground-truth object
    outlined where known, the ground left out. Returns the figure."""
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    segs = seg if isinstance(seg, (list, tuple)) else [seg]
    pts = np.concatenate([g.scan.points for g in segs])
    stat = np.concatenate([g.scan.valid & ~g.ground & ~g.dynamic for g in segs])
    dyn = np.concatenate([g.dynamic for g in segs])
    known = all(g.scan.truth_id is not None for g in segs)
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.scatter(pts[stat, 0], pts[stat, 1], s=1, color="0.6", label="static")
    if known:
        t = np.concatenate([np.asarray(g.scan.truth_id) >= 1 for g in segs])  # known: no None
        ax.scatter(pts[t, 0], pts[t, 1], s=30, facecolors="none", edgecolors="k", lw=0.5,
                   label="object (truth)")
    ax.scatter(pts[dyn, 0], pts[dyn, 1], s=6, color="r", label="dynamic (segmented)")
    scans = [g.scan.scan for g in segs]
    what = f"scan {scans[0]}" if len(scans) == 1 else f"scans {min(scans)}-{max(scans)}"
    ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal",
           title=title or f"{what}: top view (world frame)")
    ax.legend(fontsize=7)
    return fig


def plot_convergence(result: StudyResult) -> Figure:
    """Fig. 13 analogue: v and heading estimates vs scan, both configurations and entropies."""
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    fig, (av, ah) = plt.subplots(1, 2, figsize=(11, 3.8))
    styles = {"renyi": "-", "voxel": "--"}
    for c in result.configs:
        col = "tab:cyan" if c.mirrors_deployed else "tab:purple"
        for ent, e in c.estimates.items():
            lab = f"{c.label}, {ent}"
            av.plot(e["scan"], e["v"], styles.get(ent, ":"), color=col, marker=".", label=lab)
            ah.plot(e["scan"], e["heading_deg"], styles.get(ent, ":"), color=col, marker=".", label=lab)
    for ax, tv, tol, yl in ((av, result.truth_v_m_s, V_TOL_M_S, "v [m/s]"),
                            (ah, result.truth_heading_deg, HEADING_TOL_DEG, "heading [deg]")):
        ax.axhline(tv, color="k", lw=1)
        ax.axhspan(tv - tol, tv + tol, color="0.85", zorder=0)
        ax.set(xlabel="scans with the object", ylabel=yl)
        lo, hi = tv - 8 * tol, tv + 8 * tol
        ax.set_ylim(lo, hi)
    av.legend(fontsize=7)
    fig.tight_layout()
    return fig
