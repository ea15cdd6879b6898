"""Figures for the design analysis (compute first, plot second).

Every ``plot_*`` takes a result object from :mod:`nodlidar.analysis.drift` or
:mod:`nodlidar.analysis.tolerance` and an optional ``ax`` (one Axes, or a sequence with
one Axes per mirror for the per-mirror figures) and returns the Figure. matplotlib is
imported inside the functions, so importing this module is cheap.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes  # noqa: TID251 (types only, never imported at run time)
    from matplotlib.figure import Figure  # noqa: TID251
    from mpl_toolkits.mplot3d import Axes3D

    from .drift import DensityResult, DriftResult, InterleaveResult
    from .tolerance import SensitivityResult, ToleranceResult

__all__ = [
    "mirror_colour",
    "plot_bearing",
    "plot_separation",
    "plot_drift_vs_range",
    "plot_interleave",
    "plot_interleave_strip",
    "plot_density",
    "plot_tolerance_hist",
    "plot_tolerance_percentiles",
    "plot_sensitivities",
    "plot_cloud_3d",
]

DIRECT_COLOUR = "0.45"


def mirror_colour(index: int) -> Any:
    """Colour of mirror ``index`` (-1: direct beams), the same in every figure."""
    if index < 0:
        return DIRECT_COLOUR
    import matplotlib  # noqa: TID251 (lazy, inside a plot function)

    return matplotlib.colormaps["tab10"](index % 10)


def _grid(ax, n: int, *, sharex: bool = False):
    """``(fig, [axes])``: ``n`` panels, either given or in a new figure."""
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    if ax is None:
        cols = 2 if n > 1 else 1
        rows = int(np.ceil(n / cols))
        fig, grid = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.4 * rows), squeeze=False,
                                 sharex=sharex, layout="constrained")
        axs = list(grid.ravel())
        for extra in axs[n:]:
            extra.set_visible(False)
        return fig, axs[:n]
    axs = list(ax) if isinstance(ax, Sequence | np.ndarray) else [ax]
    if len(axs) != n:
        from ..errors import ParameterError

        raise ParameterError("ax", f"{len(axs)} axes", f"{n} axes (one per mirror)")
    return axs[0].figure, axs


def _one(ax, figsize=(6.4, 4.0)):
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    if ax is None:
        fig, ax = plt.subplots(figsize=figsize, layout="constrained")
        return fig, ax
    return ax.figure, ax


def _select(result: DriftResult, mirrors):
    return [m for m in result.mirrors if mirrors is None or m.name in mirrors]


def _null_formatter():
    from matplotlib.ticker import NullFormatter  # noqa: TID251 (lazy, inside a plot function)

    return NullFormatter()


def _range_colours(ranges):
    import matplotlib  # noqa: TID251 (lazy, inside a plot function)

    cmap = matplotlib.colormaps["viridis"]
    return [cmap(x) for x in np.linspace(0.0, 0.9, len(ranges))]


def plot_bearing(result: DriftResult, mirrors: Sequence[str] | None = None,
                 ax: Axes | Sequence[Axes] | None = None) -> Figure:
    """Actual bearing of each reflected beam on each arc, per mirror (paper Figs 6a/7a).

    x: the beam's step; y: bearing where it crosses the arc [deg]; one line per arc
    radius, dashed black the interleave target set for D.
    """
    ms = _select(result, mirrors)
    fig, axs = _grid(ax, len(ms))
    colours = _range_colours(result.ranges_m)
    for a, m in zip(axs, ms, strict=True):
        for j, r in enumerate(result.ranges_m):
            a.plot(m.steps, np.degrees(m.bearing_trace[j]), color=colours[j], lw=1.2,
                   label=f"{r:g} m")
        a.plot(m.steps, np.degrees(m.target_bearing), "k--", lw=1,
               label=f"target (D={result.design_distance_m:g} m)")
        a.set_title(f"{m.name}: actual bearing on arcs of radius R")
        a.set_xlabel("lidar step")
        a.set_ylabel("bearing [deg]")
        a.grid(alpha=0.3)
    axs[0].legend(fontsize=7, ncol=2, title="R", title_fontsize=7)
    return fig


def plot_separation(result: DriftResult, mirrors: Sequence[str] | None = None,
                    ax: Axes | Sequence[Axes] | None = None) -> Figure:
    """Angular separation of consecutive reflected beams, per mirror (paper Figs 6b/7b).

    y in native steps (1 = pi/512 on a URG-04LX); it tends to 1 as R grows.
    """
    ms = _select(result, mirrors)
    fig, axs = _grid(ax, len(ms))
    colours = _range_colours(result.ranges_m)
    res = result.resolution_rad
    for a, m in zip(axs, ms, strict=True):
        x = 0.5 * (m.steps[1:] + m.steps[:-1])
        for j, r in enumerate(result.ranges_m):
            a.plot(x, m.separation_trace[j] / res, color=colours[j], lw=1.2, label=f"{r:g} m")
        a.axhline(1.0, color="k", ls="--", lw=1, label="native step")
        a.set_title(f"{m.name}: separation of consecutive reflected beams")
        a.set_xlabel("lidar step")
        a.set_ylabel("separation [native steps]")
        a.grid(alpha=0.3)
    axs[0].legend(fontsize=7, ncol=2, title="R", title_fontsize=7)
    return fig


def plot_drift_vs_range(result: DriftResult, ax: Axes | None = None) -> Figure:
    """Bearing error against the interleave target vs arc radius, every mirror.

    Solid: largest |error| over the mirror's beams; dotted: RMS. Log-scaled range.
    """
    fig, a = _one(ax)
    r = result.ranges_m
    for i, m in enumerate(result.mirrors):
        e = np.degrees(np.abs(m.error_from_target))
        c = mirror_colour(i)
        a.plot(r, e.max(axis=1), "-o", color=c, ms=3, label=f"{m.name} max")
        a.plot(r, np.sqrt(np.mean(e**2, axis=1)), ":", color=c, label=f"{m.name} rms")
    a.axvline(result.design_distance_m, color="k", lw=0.8, ls="--")
    a.axhline(np.degrees(result.resolution_rad) / 3, color="0.5", lw=0.8, ls="-.",
              label="1/3 step (interleave pitch)")
    a.set_xscale("log")
    a.set_yscale("log")
    a.set_xlabel("arc radius R [m]")
    a.set_ylabel("|bearing - target| [deg]")
    a.set_title("Drift from the interleave target (set for D) vs range")
    a.grid(alpha=0.3, which="both")
    a.legend(fontsize=7, ncol=2)
    return fig


def plot_interleave(result: InterleaveResult, ax: Axes | None = None,
                    ray_every: int = 12) -> Figure:
    """Top view (paper Fig. 2b): where direct and reflected beams land on each arc.

    Every ``ray_every``-th beam of each group is drawn as its ray (origin -> mirror -> the
    largest arc); the landing points on every arc are dots. Direct beams grey, reflected
    beams coloured by mirror.
    """
    fig, a = _one(ax, figsize=(6.4, 5.6))
    idx = result.mirror_index
    rmax_i = int(np.argmax(result.ranges_m))
    for k in [-1, *range(len(result.mirror_names))]:
        sel = np.nonzero(idx == k)[0]
        label = "direct" if k < 0 else result.mirror_names[k]
        c = mirror_colour(k)
        for i in sel[::ray_every]:
            far = result.points[rmax_i, i]
            if result.hit is not None and k >= 0:
                h = result.hit[i]
                a.plot([0, h[0], far[0]], [0, h[1], far[1]], color=c, lw=0.4, alpha=0.6)
            else:
                a.plot([0, far[0]], [0, far[1]], color=c, lw=0.4, alpha=0.6)
        for j in range(len(result.ranges_m)):
            p = result.points[j, sel]
            a.scatter(p[:, 0], p[:, 1], s=2, color=c, label=label if j == 0 else None,
                      rasterized=True, zorder=3 if k >= 0 else 2)
    lo, hi = result.window_rad
    for r in result.ranges_m:
        t = np.linspace(lo, hi, 200)
        a.plot(r * np.cos(t), r * np.sin(t), color="0.85", lw=0.6, zorder=0)
    a.plot(0, 0, "k^", ms=6)
    a.set_aspect("equal")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.set_title(f"{result.design_name}: beams on arcs of "
                + ", ".join(f"{r:g}" for r in result.ranges_m) + " m")
    a.legend(fontsize=7, markerscale=4, loc="upper left")
    return fig


def plot_interleave_strip(result: InterleaveResult, centre_deg: float = 0.0,
                          width_deg: float = 4.0, ax: Axes | None = None) -> Figure:
    """Close-up of the interleave: bearing (x) against arc radius (y) near ``centre_deg``.

    On the arc of radius D every third beam is direct and the reflected ones sit at a
    third of a step; elsewhere the reflected beams slide relative to the direct ones.
    """
    fig, a = _one(ax)
    lo, hi = centre_deg - width_deg / 2, centre_deg + width_deg / 2
    b = np.degrees(result.bearing)
    for k in [-1, *range(len(result.mirror_names))]:
        sel = result.mirror_index == k
        first = True
        for j, r in enumerate(result.ranges_m):
            bb = b[j, sel]
            bb = bb[(bb >= lo) & (bb <= hi)]
            a.scatter(bb, np.full(len(bb), r), s=14 if k < 0 else 10,
                      marker="|" if k < 0 else "o", color=mirror_colour(k),
                      label=("direct" if k < 0 else result.mirror_names[k]) if first else None)
            first = False
    a.set_yscale("log")
    a.yaxis.set_minor_formatter(_null_formatter())
    a.set_yticks(result.ranges_m)
    a.set_yticklabels([f"{r:g}" for r in result.ranges_m])
    a.set_xlim(lo, hi)
    a.set_xlabel("bearing [deg]")
    a.set_ylabel("arc radius [m]")
    a.set_title("Interleave close-up (one native step = "
                f"{np.degrees(result.resolution_rad):.3f} deg)")
    a.grid(alpha=0.3, axis="x")
    a.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.18))
    return fig


def plot_density(result: DensityResult, ax: Axes | None = None) -> Figure:
    """Beams per degree across the front window on each arc, and with the mirrors lifted."""
    fig, a = _one(ax)
    c = np.degrees(result.bin_centres_rad)
    colours = _range_colours(result.ranges_m)
    for j, r in enumerate(result.ranges_m):
        a.step(c, np.radians(result.density_per_rad[j]), where="mid", color=colours[j],
               label=f"mirrors, R = {r:g} m")
    a.step(c, np.radians(result.density_no_mirrors_per_rad), where="mid", color="k", ls="--",
           label="no mirrors")
    a.set_ylim(bottom=0)
    a.set_xlabel("bearing [deg]")
    a.set_ylabel("beams per degree")
    a.set_title("Beam density across the front window")
    a.grid(alpha=0.3)
    a.legend(fontsize=7)
    return fig


def _range_index(result: ToleranceResult, range_m: float | None) -> int:
    r = result.ranges_m
    if range_m is None:
        return int(np.argmin(np.abs(r - np.median(r))))
    return int(np.argmin(np.abs(r - range_m)))


def plot_tolerance_hist(result: ToleranceResult, range_m: float | None = None,
                        ax: Axes | None = None,
                        metric: str = "bearing_error_max") -> Figure:
    """Histogram over sampled builds of a metric per mirror, at the range nearest ``range_m``.

    Metrics with a range axis: ``bearing_error_max`` (deg), ``bearing_error_mean`` (deg),
    ``range_error_max`` (mm), ``height_max`` (mm); ``elevation_max`` (deg) has none.
    """
    fig, a = _one(ax)
    data = np.asarray(getattr(result, metric), dtype=float)
    j = _range_index(result, range_m)
    if data.ndim == 3:
        data = data[:, :, j]
    deg = metric in ("bearing_error_max", "bearing_error_mean", "elevation_max")
    data = np.degrees(data) if deg else data * 1e3
    bins = np.histogram_bin_edges(data, bins=60)
    for i, name in enumerate(result.mirror_names):
        a.hist(data[:, i], bins=bins, histtype="step", color=mirror_colour(i), label=name, lw=1.3)
        p95 = np.percentile(data[:, i], 95)
        a.axvline(p95, color=mirror_colour(i), ls=":", lw=1)
    where = "" if np.asarray(getattr(result, metric)).ndim == 2 else f" at R = {result.ranges_m[j]:g} m"
    a.set_xlabel(metric.replace("_", " ") + (" [deg]" if deg else " [mm]"))
    a.set_ylabel("builds")
    a.set_title(f"{result.n_samples} sampled builds{where} (dotted: 95th percentile)")
    a.legend(fontsize=7)
    return fig


def plot_tolerance_percentiles(result: ToleranceResult, metric: str = "bearing_error_max",
                               ax: Axes | None = None) -> Figure:
    """Percentiles over builds of a per-range metric vs range, per mirror."""
    fig, a = _one(ax)
    q = result.tolerance.percentiles
    p = result.percentiles(metric)  # (q, m, r)
    deg = metric.startswith("bearing")
    p = np.degrees(p) if deg else p * 1e3
    styles = ["-", "--", ":", "-."]
    for i, name in enumerate(result.mirror_names):
        for k, qq in enumerate(q):
            a.plot(result.ranges_m, p[k, i], styles[k % len(styles)], color=mirror_colour(i),
                   marker="o", ms=3, label=f"{name} p{qq:g}")
    a.set_xscale("log")
    a.set_xlabel("arc radius R [m]")
    a.set_ylabel(metric.replace("_", " ") + (" [deg]" if deg else " [mm]"))
    a.set_title(f"Percentiles over {result.n_samples} builds")
    a.grid(alpha=0.3, which="both")
    a.legend(fontsize=6, ncol=len(result.mirror_names))
    return fig


def plot_sensitivities(result: SensitivityResult, ax: Axes | None = None) -> Figure:
    """Mean sensitivity of each mirror's bearing at D to each parameter (bar chart)."""
    from .tolerance import PARAMETERS

    fig, a = _one(ax, figsize=(7.0, 3.8))
    params = list(PARAMETERS)
    width = 0.8 / len(result.mirror_names)
    x = np.arange(len(params))
    for i, name in enumerate(result.mirror_names):
        vals = []
        for p in params:
            v = np.mean(result.finite_difference[name][p])
            vals.append(np.degrees(v) * 1e-3 if PARAMETERS[p] == "m" else v)
        a.bar(x + (i - (len(result.mirror_names) - 1) / 2) * width, vals, width,
              color=mirror_colour(i), label=name)
    a.set_xticks(x)
    a.set_xticklabels([f"{p}\n[{'deg/deg' if PARAMETERS[p] == 'rad' else 'deg/mm'}]"
                       for p in params], fontsize=7)
    a.axhline(0, color="k", lw=0.6)
    a.set_title(f"d(bearing at D = {result.design_distance_m:g} m) / d(parameter), mean over beams")
    a.legend(fontsize=7)
    return fig


def plot_cloud_3d(cloud: Any, *, mirror: np.ndarray | None = None, ax: Axes3D | None = None,
                  max_points: int = 30_000, elev_deg: float = 25.0, azim_deg: float = -120.0,
                  point_size: float = 1.0, title: str | None = None) -> Figure:
    """Static 3D scatter of a point cloud, coloured by mirror (direct beams grey).

    For notebooks and users without Foxglove (``nodlidar view`` is the live view).

    Parameters
    ----------
    cloud : PointCloud or (n, 3) array
        A :class:`~nodlidar.runtime.assembly.PointCloud` (its ``xyz`` [m] and ``mirror``
        ids are used) or bare points [m]; rows with a non-finite coordinate are skipped.
    mirror : (n,) int, optional
        Mirror index per point (-1 direct); taken from ``cloud.mirror`` when not given.
    ax : a 3D Axes (``projection="3d"``), optional
    max_points : int
        At most this many points are drawn (every k-th, deterministic), so a sweep of
        100 000 points stays interactive.
    elev_deg, azim_deg : float
        View angles [deg].

    Returns the Figure. The axes have equal scale in x, y and z (metres).
    """
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    from ..errors import ParameterError

    xyz = np.asarray(getattr(cloud, "xyz", cloud), dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ParameterError("cloud", f"shape {xyz.shape}", "a PointCloud or an (n, 3) array")
    if mirror is None:
        mirror = getattr(cloud, "mirror", None)
    ids = np.full(len(xyz), -1, dtype=int) if mirror is None else np.asarray(mirror, dtype=int)
    if ids.shape != (len(xyz),):
        raise ParameterError("mirror", f"shape {ids.shape}", f"({len(xyz)},)")
    if max_points < 1:
        raise ParameterError("max_points", max_points, "an integer >= 1")
    keep = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))
    keep = keep[:: max(1, int(np.ceil(len(keep) / max_points)))]
    xyz, ids = xyz[keep], ids[keep]
    names = list(getattr(cloud, "mirror_names", ()) or ())
    if ax is None:
        ax = cast("Axes3D", plt.figure(figsize=(7.0, 5.6), layout="constrained")
                  .add_subplot(projection="3d"))
    fig = cast("Figure", ax.figure)
    for m in np.unique(ids):   # one scatter per mirror: a legend entry each
        sel = ids == m
        label = "direct" if m < 0 else (names[m] if m < len(names) else f"mirror {m}")
        ax.scatter(xyz[sel, 0], xyz[sel, 1], xyz[sel, 2], s=point_size, color=mirror_colour(int(m)),
                   label=f"{label} ({int(sel.sum())})", depthshade=False)
    if len(xyz):
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
        ax.set_box_aspect(np.maximum(hi - lo, 1e-3))   # metres look like metres on every axis
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.view_init(elev=elev_deg, azim=azim_deg)
    ax.set_title(title or f"{len(xyz)} points")
    if len(xyz):
        ax.legend(loc="upper left", fontsize="small", markerscale=4)
    return fig
