"""Foxglove messages from nodlidar data (pure functions; foxglove imported lazily).

Frames (docs/conventions.md): ``sensor`` is the sensor base frame (the cloud's),
``head`` the nodding head (the mirrors are fixed in it; ``sensor <- head`` is the nod about
the pivot), ``world`` the tracking's frame (the sensor base raised by the sensor height, so
the floor is z = 0; the tracks live there).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from foxglove.messages import FrameTransforms, PointCloud, SceneUpdate, Timestamp

__all__ = ["FRAME_WORLD", "FRAME_SENSOR", "FRAME_HEAD", "CLOUD_DTYPE", "CLOUD_FIELDS",
           "pack_points", "point_cloud", "head_transform", "frame_transforms", "mirror_update",
           "track_update", "stamp"]

FRAME_WORLD, FRAME_SENSOR, FRAME_HEAD = "world", "sensor", "head"

#: One point of the published cloud (little endian, 28 bytes): position [m] in float32
#: (what every viewer reads), the measured range [m], the head pitch [rad], the mirror
#: index (-1 direct) and the scan index (colour by any of them in Foxglove).
_LAYOUT = (("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("range", "<f4"), ("nod", "<f4"),
           ("mirror", "<i4"), ("scan", "<i4"))
CLOUD_DTYPE = np.dtype(list(_LAYOUT))
#: (name, byte offset, foxglove PackedElementField numeric type name)
CLOUD_FIELDS = tuple((name, 4 * i, {"<f4": "Float32", "<i4": "Int32"}[t])
                     for i, (name, t) in enumerate(_LAYOUT))


def stamp(t_ns: int) -> Timestamp:
    """A foxglove Timestamp from nanoseconds since the epoch."""
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(t_ns // 1_000_000_000), nsec=int(t_ns % 1_000_000_000))


def pack_points(xyz: np.ndarray, range_m: np.ndarray, nod_rad: np.ndarray, mirror: np.ndarray,
                scan: np.ndarray) -> bytes:
    """Points -> the packed bytes of :data:`CLOUD_DTYPE` (n * 28 bytes).

    ``xyz`` (n, 3) [m]; ``range_m``, ``nod_rad`` (n,) float; ``mirror``, ``scan`` (n,) int.
    """
    xyz = np.asarray(xyz)
    out = np.empty(len(xyz), CLOUD_DTYPE)
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out["range"], out["nod"] = range_m, nod_rad
    out["mirror"], out["scan"] = mirror, scan
    return out.tobytes()


def point_cloud(data: bytes, t_ns: int, frame_id: str = FRAME_SENSOR) -> PointCloud:
    """A ``foxglove.PointCloud`` of packed :data:`CLOUD_DTYPE` points."""
    from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud

    fields = [PackedElementField(name=n, offset=o, type=getattr(PackedElementFieldNumericType, t))
              for n, o, t in CLOUD_FIELDS]
    return PointCloud(timestamp=stamp(t_ns), frame_id=frame_id, point_stride=CLOUD_DTYPE.itemsize,
                      fields=fields, data=bytes(data))


def head_transform(nod_rad: float, pivot_m: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """``sensor <- head`` for head pitch ``nod_rad``: translation (3,) [m] and quaternion
    (x, y, z, w), from ``p_sensor = R_y(nod) (p_head - pivot) + pivot``."""
    from ..geometry import rot_y

    piv = np.asarray(pivot_m, dtype=float)
    t = piv - rot_y(float(nod_rad)) @ piv
    q = np.array([0.0, np.sin(nod_rad / 2.0), 0.0, np.cos(nod_rad / 2.0)])
    return t, q


def frame_transforms(nod_rad: float, pivot_m: Sequence[float], sensor_height_m: float,
                     t_ns: int) -> FrameTransforms:
    """``foxglove.FrameTransforms``: world -> sensor (raised by the sensor height) and
    sensor -> head (the current nod)."""
    from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Vector3

    t, q = head_transform(nod_rad, pivot_m)
    ts = stamp(t_ns)
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=ts, parent_frame_id=FRAME_WORLD, child_frame_id=FRAME_SENSOR,
                       translation=Vector3(x=0.0, y=0.0, z=float(sensor_height_m)),
                       rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
        FrameTransform(timestamp=ts, parent_frame_id=FRAME_SENSOR, child_frame_id=FRAME_HEAD,
                       translation=Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                       rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                           w=float(q[3])))])


def _colour(index: int, alpha: float = 0.6):
    from foxglove.messages import Color

    # tab10, as nodlidar.analysis.plots.mirror_colour, without importing matplotlib
    tab10 = ((0.122, 0.467, 0.706), (1.0, 0.498, 0.055), (0.173, 0.627, 0.173),
             (0.839, 0.153, 0.157), (0.580, 0.404, 0.741), (0.549, 0.337, 0.294),
             (0.890, 0.467, 0.761), (0.498, 0.498, 0.498), (0.737, 0.741, 0.133),
             (0.090, 0.745, 0.812))
    r, g, b = tab10[index % 10]
    return Color(r=r, g=g, b=b, a=alpha)


def _pose(p=(0.0, 0.0, 0.0), yaw_rad: float = 0.0):
    from foxglove.messages import Pose, Quaternion, Vector3

    return Pose(position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=Quaternion(x=0.0, y=0.0, z=float(np.sin(yaw_rad / 2)),
                                       w=float(np.cos(yaw_rad / 2))))


def mirror_update(patches: Iterable[Any], t_ns: int) -> SceneUpdate:
    """``foxglove.SceneUpdate``: one entity per mirror patch (id ``mirror/<name>``), a
    rectangle of two triangles in the ``head`` frame (the four corners of the finite
    patch, :meth:`nodlidar.geometry.MirrorPatch.corners`) and its name, frame-locked so it
    nods with the head."""
    from foxglove.messages import (
        Point3,
        SceneEntity,
        SceneUpdate,
        TextPrimitive,
        TriangleListPrimitive,
    )

    ents = []
    for i, m in enumerate(patches):
        c = np.asarray(m.corners(), dtype=float)
        pts = [Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in c]
        tri = TriangleListPrimitive(pose=_pose(), points=pts, color=_colour(i),
                                    indices=[0, 1, 2, 0, 2, 3])
        label = TextPrimitive(pose=_pose(c.mean(axis=0) + [0.0, 0.0, 0.02]), billboard=True,
                              font_size=14.0, scale_invariant=True, color=_colour(i, 1.0),
                              text=m.name)
        ents.append(SceneEntity(timestamp=stamp(t_ns), frame_id=FRAME_HEAD, id=f"mirror/{m.name}",
                                frame_locked=True, triangles=[tri], texts=[label]))
    return SceneUpdate(entities=ents)


def track_update(states: Iterable[Any], t_ns: int, *, lifetime_s: float = 2.0,
                 height_m: float = 1.0) -> SceneUpdate:
    """``foxglove.SceneUpdate``: one entity per alive track (id ``track/<n>``) in the
    ``world`` frame - a cylinder-like box at its ground position, an arrow along its
    heading scaled by the speed (1 m per m/s) and a label; ended tracks are deleted.
    ``states`` are :class:`nodlidar.tracking.tracker.TrackState`-like (``track_id``,
    ``x_m``, ``y_m``, ``v_m_s``, ``heading_rad``, ``confirmed``, ``alive``)."""
    from foxglove.messages import (
        ArrowPrimitive,
        CubePrimitive,
        Duration,
        SceneEntity,
        SceneEntityDeletion,
        SceneEntityDeletionType,
        SceneUpdate,
        TextPrimitive,
        Vector3,
    )

    ents, dels = [], []
    life = Duration(sec=int(lifetime_s), nsec=int((lifetime_s % 1) * 1e9))
    for st in states:
        tid = f"track/{st.track_id}"
        if not getattr(st, "alive", True):
            dels.append(SceneEntityDeletion(timestamp=stamp(t_ns), id=tid,
                                            type=SceneEntityDeletionType.MatchingId))
            continue
        x, y = float(st.x_m), float(st.y_m)
        v, h = float(st.v_m_s), float(st.heading_rad)
        colour = _colour(3 if getattr(st, "confirmed", False) else 7, 0.5)
        cube = CubePrimitive(pose=_pose((x, y, height_m / 2)), size=Vector3(x=0.3, y=0.3, z=height_m),
                             color=colour)
        arrows = []
        if np.isfinite(v) and np.isfinite(h) and v > 0:
            arrows.append(ArrowPrimitive(pose=_pose((x, y, height_m + 0.05), h), shaft_length=max(v, 0.05),
                                         shaft_diameter=0.03, head_length=0.08, head_diameter=0.08,
                                         color=_colour(3, 1.0)))
        text = (f"track {st.track_id}" + (f": {v:.2f} m/s, {np.degrees(h):.1f} deg"
                                          if np.isfinite(v) and np.isfinite(h) else ""))
        label = TextPrimitive(pose=_pose((x, y, height_m + 0.25)), billboard=True, font_size=14.0,
                              scale_invariant=True, color=_colour(3, 1.0), text=text)
        ents.append(SceneEntity(timestamp=stamp(t_ns), frame_id=FRAME_WORLD, id=tid, lifetime=life,
                                cubes=[cube], arrows=arrows, texts=[label]))
    return SceneUpdate(deletions=dels, entities=ents)
