"""Calibration figures: the paper's Figure 9 and residual histograms.

Compute first (:func:`~nodlidar.calibration.fit.calibrate`), plot second: each function
takes a :class:`~nodlidar.calibration.fit.CalibrationResult` and returns the Figure.
matplotlib is imported inside the functions (``import nodlidar`` stays light).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure  # noqa: TID251 (types only, never imported at run time)

    from .fit import CalibrationResult

__all__ = ["plot_walls", "plot_residual_histograms", "plot_formats", "MIRROR_COLOURS"]

#: Colours of the paper's Fig. 9: direct blue, R1 violet, R2 black, L1 red, L2 green.
MIRROR_COLOURS = {"direct": "tab:blue", "R1": "darkviolet", "R2": "black", "L1": "red",
                  "L2": "green"}
_MAX_POINTS = 4000  # per series and panel: enough to see the band, fast to draw


def _colour(name: str, i: int) -> str | tuple[float, float, float, float]:
    """The mirror's colour: a Matplotlib name, else an RGBA of the tab10 cycle."""
    import matplotlib  # noqa: TID251 (lazy, inside a plot function)

    return MIRROR_COLOURS.get(name) or matplotlib.colormaps["tab10"](i % 10)


def plot_formats() -> list[str]:
    """File extensions (without the dot) the figures can be saved as."""
    from matplotlib.figure import Figure  # noqa: TID251 (lazy, inside a plot function)

    return sorted(Figure().canvas.get_supported_filetypes())


def _thin(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    if len(a) <= _MAX_POINTS:
        return a
    return a[np.sort(rng.choice(len(a), _MAX_POINTS, replace=False))]


def plot_walls(result: CalibrationResult, *, calibrated: bool = True,
               title: str | None = None) -> Figure:
    """Figure 9: per wall orientation, each mirror's points against the wall.

    Top row: top view (sensor frame x-y) of the direct points and each mirror's calibrated
    points. Bottom row: signed distance to the wall plane [cm] against the horizontal
    along-wall coordinate [m], with the paper's +-2.25 cm band (``band_m`` of the fit).
    ``calibrated=False`` shows the uncalibrated residuals in the bottom row instead.
    """
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    caps = result.captures
    fig, axes = plt.subplots(2, len(caps), figsize=(4.6 * len(caps), 7.5), squeeze=False)
    rng = np.random.default_rng(0)
    band = next(iter(result.mirrors.values())).after.band_m if result.mirrors else 0.0225
    for k, cap in enumerate(caps):
        top, bot = axes[0, k], axes[1, k]
        n = cap.plane.normal
        along = np.cross([0.0, 0.0, 1.0], n)
        along /= np.linalg.norm(along)
        d = _thin(cap.direct_points, rng)
        top.scatter(d[:, 0], d[:, 1], s=1, c=_colour("direct", 0), label="direct")
        bot.scatter(d @ along, cap.plane.signed_distance(d) * 100, s=1, c=_colour("direct", 0))
        for i, (name, m) in enumerate(result.mirrors.items()):
            sel = (m.capture == k) & m.used
            idx = _thin(np.flatnonzero(sel), rng)
            p = m.points_after[idx]
            res = m.residual_after[idx] if calibrated else m.residual_before[idx]
            top.scatter(p[:, 0], p[:, 1], s=1, c=_colour(name, i), label=name)
            bot.scatter(p @ along, res * 100, s=1, c=_colour(name, i))
        top.scatter([0], [0], marker="^", c="k", s=30)
        top.set_aspect("equal", adjustable="datalim")
        top.set_title(cap.name)
        top.set_xlabel("x [m]")
        top.set_ylabel("y [m]")
        bot.axhspan(-band * 100, band * 100, color="0.85", zorder=0,
                    label=f"+-{band * 100:.2f} cm")
        bot.set_xlabel("along the wall [m]")
        bot.set_ylabel("distance to wall [cm]")
        if calibrated:
            bot.set_ylim(-4 * band * 100, 4 * band * 100)
    axes[0, 0].legend(markerscale=6, fontsize=8, loc="best")
    axes[1, 0].legend(fontsize=8, loc="upper right")
    fig.suptitle(title or f"{result.design_name}: points against the wall "
                 f"({'calibrated' if calibrated else 'uncalibrated'}, model {result.model})")
    fig.tight_layout()
    return fig


def plot_residual_histograms(result: CalibrationResult, *, bins: int = 80) -> Figure:
    """Histogram of each mirror's point-to-wall distances before and after calibration."""
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    names = list(result.mirrors)
    fig, axes = plt.subplots(1, len(names), figsize=(3.8 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        m = result.mirrors[name]
        r0, r1 = m.residual_before[m.used] * 100, m.residual_after[m.used] * 100
        lim = max(np.percentile(np.abs(r0), 99), 3 * m.after.band_m * 100)
        edges = np.linspace(-lim, lim, bins)
        ax.hist(r0, edges, alpha=0.6, label=f"before (rms {m.before.rms_m * 100:.1f} cm)")
        ax.hist(r1, edges, alpha=0.6, label=f"after (rms {m.after.rms_m * 100:.1f} cm)")
        ax.axvspan(-m.after.band_m * 100, m.after.band_m * 100, color="0.9", zorder=0)
        ax.set_title(f"{name}: {m.after.within_band * 100:.1f} % within "
                     f"+-{m.after.band_m * 100:.2f} cm")
        ax.set_xlabel("distance to wall [cm]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig
