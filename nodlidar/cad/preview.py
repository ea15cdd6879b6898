"""Preview image of the mounts: the STL triangles projected with numpy, no mplot3d.

Each view is an orthographic projection with the camera of matplotlib's
``view_init(elev, azim)``; the shaded triangles of every part are depth-sorted together
(painter's algorithm, far to near by their centroids) and handed to the Agg renderer as
one array per view (``draw_gouraud_triangles`` with the three corners of a triangle in its
one shaded colour). mplot3d re-projects and re-sorts every polygon in Python on each draw
and builds Path objects per triangle (137 k for the paper build); here the projection,
shading and sort are a few whole-array operations and no per-triangle object is made.

Library code: nothing is printed; matplotlib is imported only inside :func:`render_preview`
(``import nodlidar`` stays light).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PREVIEW_VIEWS", "read_stl_triangles", "view_basis", "render_preview"]

#: Preview viewpoints (elevation, azimuth) [deg]: from the front right and above (the
#: side the beams leave from), and straight down.
PREVIEW_VIEWS = ((28.0, -50.0, "front-right view"), (90.0, -90.0, "top view"))

_LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])


def read_stl_triangles(path: str | Path) -> np.ndarray:
    """Triangles of an STL file, shape ``(n, 3, 3)`` float64 (file units, here mm).

    Binary STL (what OCCT writes) is read with one ``np.frombuffer``; an ASCII file goes
    through trimesh.
    """
    data = Path(path).read_bytes()
    if len(data) >= 84:
        n = int.from_bytes(data[80:84], "little")
        if len(data) == 84 + 50 * n:  # binary: 80-byte header, count, 50-byte records
            rec = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            return np.frombuffer(data, dtype=rec, count=n, offset=84)["v"].astype(np.float64)
    import trimesh

    mesh: Any = trimesh.load(str(path), force="mesh")  # force="mesh": a Trimesh
    return np.asarray(mesh.triangles, dtype=np.float64)


def view_basis(elev_deg: float, azim_deg: float) -> np.ndarray:
    """Rows: screen right, screen up and towards the eye, shape ``(3, 3)``.

    The camera of matplotlib's ``Axes3D.view_init(elev, azim)``: the eye lies at azimuth
    ``azim`` about z (from +x) and elevation ``elev`` above the xy plane; z is up on
    screen (for ``elev = 90`` the screen's up is the direction azimuth ``azim + 180``).
    """
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.cross(eye, right)
    return np.stack([right, up, eye])


def _shaded(parts: Mapping[str, np.ndarray], colors: Mapping[str, Sequence[float]]
            ) -> tuple[np.ndarray, np.ndarray]:
    """All parts' triangles ``(n, 3, 3)`` and their shaded RGBA face colours ``(n, 4)``."""
    tris, fcs = [], []
    for name, tri in parts.items():
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(nrm, axis=1)
        nrm /= np.where(length > 0, length, 1.0)[:, None]
        shade = 0.45 + 0.55 * np.abs(nrm @ _LIGHT)
        rgba = np.asarray(colors[name], dtype=float)
        fc = np.empty((len(tri), 4))
        fc[:, :3] = np.clip(rgba[None, :3] * shade[:, None], 0, 1)
        fc[:, 3] = rgba[3]
        tris.append(tri)
        fcs.append(fc)
    return np.concatenate(tris), np.concatenate(fcs)


def render_preview(meshes: Mapping[str, Mapping[str, np.ndarray]],
                   colors: Mapping[str, Sequence[float]], path: str | Path, title: str,
                   views: Sequence[tuple[float, float, str]] = PREVIEW_VIEWS) -> None:
    """Render every state's parts into one PNG: a row per state, a column per view.

    Parameters
    ----------
    meshes : mapping state -> (part name -> triangles, shape ``(n, 3, 3)`` [mm])
    colors : mapping part name -> RGBA in [0, 1]
    path : file to write (PNG)
    title : prefix of each panel's title (the design name)
    views : ``(elevation [deg], azimuth [deg], label)`` per column
    """
    import matplotlib  # noqa: TID251 (lazy, inside the preview renderer)

    matplotlib.use("Agg", force=False)
    from matplotlib.artist import Artist  # noqa: TID251 (lazy)
    from matplotlib.collections import LineCollection  # noqa: TID251 (lazy)
    from matplotlib.figure import Figure  # noqa: TID251 (lazy)

    class Triangles(Artist):
        """Flat-coloured triangles in data coordinates, drawn in the given order."""

        def __init__(self, xy: np.ndarray, rgba: np.ndarray):
            super().__init__()
            self._xy = xy                                          # (n, 3, 2)
            self._rgba = np.repeat(rgba[:, None, :], 3, axis=1)   # (n, 3, 4): flat
            self.set_in_layout(False)

        def draw(self, renderer: Any) -> None:
            axes = self.axes
            if not self.get_visible() or not len(self._xy) or axes is None:
                return
            gc = renderer.new_gc()
            gc.set_clip_rectangle(axes.bbox)
            renderer.draw_gouraud_triangles(gc, self._xy, self._rgba,
                                            axes.transData.frozen())
            gc.restore()
            self.stale = False

    states = list(meshes)
    shaded = {st: _shaded(meshes[st], colors) for st in states}
    allpts = np.concatenate([t.reshape(-1, 3) for t, _ in shaded.values()])
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    fig = Figure(figsize=(5.2 * len(views), 4.8 * len(states)), dpi=100)
    for col, (elev, azim, label) in enumerate(views):
        B = view_basis(elev, azim)
        # one frame for every state of a view: the projected box of all parts, same scale
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])]) @ B[:2].T
        c_lo, c_hi = corners.min(axis=0), corners.max(axis=0)
        pad = 0.06 * float(np.max(c_hi - c_lo))
        for row, st in enumerate(states):
            tri, fc = shaded[st]
            q = tri @ B.T                                  # (n, 3, 3): right, up, depth
            order = np.argsort(q[:, :, 2].sum(axis=1), kind="stable")  # far first
            ax = fig.add_subplot(len(states), len(views), row * len(views) + col + 1)
            ax.add_artist(Triangles(q[order, :, :2], fc[order]))
            ax.set_xlim(c_lo[0] - pad, c_hi[0] + pad)
            ax.set_ylim(c_lo[1] - pad, c_hi[1] + pad)
            ax.set_aspect("equal")
            if elev >= 90:  # plan view: the screen axes are world axes
                ax.set_xlabel("x [mm]" if abs(B[0, 0]) > 0.99 else "y [mm]")
                ax.set_ylabel("y [mm]" if abs(B[1, 1]) > 0.99 else "x [mm]")
            else:
                ax.set_xticks([])
                ax.set_yticks([])
                _axis_triad(ax, B, c_lo - pad, 0.12 * float(np.max(c_hi - c_lo)),
                            LineCollection)
            ax.set_title(f"{title}: {st}, {label}", fontsize=9)
    # fixed margins: tight_layout would lay out every tick label once more
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.06, top=0.95, wspace=0.2, hspace=0.2)
    fig.savefig(path)


def _axis_triad(ax, B: np.ndarray, corner: np.ndarray, size: float, LineCollection) -> None:
    """Projected x, y, z arrows of ``size`` [mm] near the lower-left corner, labelled."""
    o = corner + 0.7 * size
    ends = o + size * B[:2].T                              # (3 axes, 2)
    ax.add_collection(LineCollection([[o, e] for e in ends], colors=("C3", "C2", "C0"),
                                     linewidths=1.5))
    for e, name in zip(ends, "xyz", strict=True):
        ax.annotate(name, e, fontsize=8, ha="center", va="center")
