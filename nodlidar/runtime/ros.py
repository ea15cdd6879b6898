"""ROS 2 messages of a recording: PointCloud2, TF and the head's URDF.

Frames (docs/conventions.md; the names are what ROS tools see):

``nodlidar_base``
    The sensor (base) frame: fixed to the robot, equal to the head frame at nod = 0.
    Every PointCloud2 is in this frame.
``nodlidar_head``
    The nod joint's child: origin at ``nod.pivot_m``, pitched by the nod angle about y.
    ``/tf`` carries ``nodlidar_base -> nodlidar_head`` at every nod servo sample.
``laser``
    The head frame (origin at the lidar's optical centre, x forward, z up):
    ``nodlidar_head -> laser`` is the fixed offset ``-pivot`` (``/tf_static``). A LaserScan
    in ``laser`` is right for the direct beams; reflected beams are only right in the
    PointCloud2.
``mirror_<name>``
    One per mirror, on a revolute joint about its side's lift axis
    (:func:`nodlidar.hinge.side_lift_axes`, the one hinge model: all mirrors of a side
    turn about the same line; docs/conventions.md, "Mirror lift"): origin on the axis
    abreast of the glass centre, x = the axis direction about which the lift is a
    positive rotation (``LiftAxis.lift_direction``), z = +z (the axis is horizontal). The
    joint angle is 0 deployed and ``mirror.lift_angle_rad`` lifted; ``/tf`` carries it
    at every lift-servo sample. The glass is drawn in the joint frame where the (as
    built) patch is.

Transforms are ``parent -> child`` as ROS has them: the child's pose in the parent, i.e.
``p_parent = R p_child + t`` (the ``A2B`` naming of docs/conventions.md with A = parent).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import ArrayLike

# rot_y/rot_x: geometry's (the one rotation vocabulary), re-exported for callers here
from ..geometry import rot_x, rot_y
from ..hinge import side_lift_axes

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

    from ..design import Design
    from ..geometry import MirrorPatch
    from .servo_angles import MirrorLiftProfile

__all__ = ["BASE_FRAME", "HEAD_FRAME", "LASER_FRAME", "mirror_frame", "POINTFIELD_TYPES",
           "pointcloud2", "pointcloud2_array", "stamp", "quaternion", "quat_axis", "quat_mul",
           "rot_y", "rot_x",
           "nod_transform", "mirror_joint_frames", "mirror_joint_angle", "static_transforms",
           "tf_message", "urdf", "CdrTemplate"]

BASE_FRAME = "nodlidar_base"
HEAD_FRAME = "nodlidar_head"
LASER_FRAME = "laser"

#: numpy dtype string -> sensor_msgs/PointField datatype constant
POINTFIELD_TYPES = {"|i1": 1, "|u1": 2, "<i2": 3, "<u2": 4, "<i4": 5, "<u4": 6, "<f4": 7, "<f8": 8}
_DTYPE_OF = {v: k for k, v in POINTFIELD_TYPES.items()}


def mirror_frame(name: str) -> str:
    return f"mirror_{name}"


def stamp(ts: Any, ns: int) -> Any:
    """builtin_interfaces/Time of ``ns`` [ns since the epoch]."""
    return ts.types["builtin_interfaces/msg/Time"](sec=int(ns) // 1_000_000_000,
                                                    nanosec=int(ns) % 1_000_000_000)


def quaternion(R: ArrayLike) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (a 4-tuple is taken as a quaternion already)."""
    q = np.asarray(R, float)
    if len(q) == 4:
        return float(q[0]), float(q[1]), float(q[2]), float(q[3])
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(q).as_quat()
    return float(x), float(y), float(z), float(w)


def quat_axis(axis: int, a: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``a`` [rad] about axis 0 (x), 1 (y) or 2 (z)."""
    q = [0.0, 0.0, 0.0, math.cos(a / 2)]
    q[axis] = math.sin(a / 2)
    return q[0], q[1], q[2], q[3]


def quat_mul(p: Sequence[Any], q: Sequence[Any]) -> tuple[Any, Any, Any, Any]:
    """Hamilton product ``p q`` of (x, y, z, w) quaternions (rotation q first, then p).

    Components are floats, or arrays of one shape (elementwise: many products at once)."""
    px, py, pz, pw = p
    qx, qy, qz, qw = q
    return (pw * qx + px * qw + py * qz - pz * qy, pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw, pw * qw - px * qx - py * qy - pz * qz)


# -- PointCloud2 ---------------------------------------------------------------------------
def pointcloud2(ts: Any, points: np.ndarray, frame_id: str, stamp_ns: int) -> Any:
    """sensor_msgs/PointCloud2 of a packed structured array ``(n,)`` (one row, dense).

    Field types must be in :data:`POINTFIELD_TYPES`; field order and offsets are the
    array's (:func:`nodlidar.runtime.cloud.structured` gives the file layout).
    """
    dt = points.dtype
    PointField = ts.types["sensor_msgs/msg/PointField"]
    layout: Mapping[str, Any] = dt.fields or {}
    fields = [PointField(name=name, offset=int(layout[name][1]),
                         datatype=POINTFIELD_TYPES[dt[name].str], count=1) for name in layout]
    data = np.frombuffer(np.ascontiguousarray(points).tobytes(), dtype=np.uint8)
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=ts.types["std_msgs/msg/Header"](stamp=stamp(ts, stamp_ns), frame_id=frame_id),
        height=1, width=len(points), fields=fields, is_bigendian=False,
        point_step=dt.itemsize, row_step=dt.itemsize * len(points), data=data, is_dense=True)


def pointcloud2_array(msg: Any) -> np.ndarray:
    """The structured array ``(height * width,)`` of a PointCloud2 (any reader's message
    object with the standard attributes)."""
    dt = np.dtype({"names": [f.name for f in msg.fields],
                   "formats": [np.dtype(_DTYPE_OF[f.datatype]).newbyteorder(
                       ">" if msg.is_bigendian else "<") for f in msg.fields],
                   "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    return np.frombuffer(bytes(msg.data), dtype=dt, count=msg.height * msg.width)


# -- transforms ------------------------------------------------------------------------------
def nod_transform(nod_rad: float, pivot_m: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``nodlidar_base -> nodlidar_head``: (R (3, 3), t (3,) [m]) at pitch ``nod_rad``."""
    return rot_y(nod_rad), np.asarray(pivot_m, dtype=float)


def mirror_joint_frames(patches: Iterable[MirrorPatch],
                        design: Design) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``laser -> mirror_<name>`` at joint angle 0 for each :class:`MirrorPatch`:
    (name, R (3, 3), t (3,) [m]).

    The joint turns about the patch's side's lift axis (``design``'s
    :func:`~nodlidar.hinge.side_lift_axes`, from its nominal mirrors: the printed
    carrier's hinge): columns of R are ``LiftAxis.lift_direction`` (the lift is a
    positive rotation about it), ``z x`` that, and +z; ``t`` is the point of the axis
    nearest the glass centre. ``patches`` may be as built (perturbed); their names pick
    the side.
    """
    axes = side_lift_axes(design)
    side_of = {m.name: m.side for m in design.mirrors}
    ez = np.array([0.0, 0.0, 1.0])
    out = []
    for m in patches:
        ax = axes[side_of[m.name]]
        x = ax.lift_direction
        R = np.column_stack([x, np.cross(ez, x), ez])
        centre = m.point((m.s_min + m.s_max) / 2, (m.z_min + m.z_max) / 2)
        out.append((m.name, R, ax.nearest_point(centre)))
    return out


def mirror_joint_angle(servo_rad: ArrayLike, profile: MirrorLiftProfile, hinge_z_m: float,
                       lift_angle_rad: float) -> np.ndarray:
    """Mirror joint angle [rad] (0 deployed) from lift-servo angles [rad]: the fraction of
    the way from ``profile.deployed_rad`` to ``profile.lifted_rad`` (not clipped: the
    carrier turns with the horn) times ``lift_angle_rad``, a positive rotation about the
    joint's x axis (:func:`mirror_joint_frames`). ``hinge_z_m`` is not needed any more
    (the joint axis is oriented so that the lift is positive for either hinge height);
    it is kept for callers."""
    frac = (np.asarray(servo_rad, float) - profile.deployed_rad) / (
        profile.lifted_rad - profile.deployed_rad)
    return abs(lift_angle_rad) * frac


def static_transforms(pivot_m: Sequence[float] | np.ndarray) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """The fixed frames: (parent, child, R, t) for ``/tf_static``."""
    return [(HEAD_FRAME, LASER_FRAME, np.eye(3), -np.asarray(pivot_m, dtype=float))]


def tf_message(ts: Any, transforms: Sequence[tuple[int, str, str, ArrayLike, np.ndarray]]) -> Any:
    """tf2_msgs/TFMessage of (stamp_ns, parent, child, R, t) tuples (R a 3x3 matrix or an
    (x, y, z, w) quaternion, t [m])."""
    T = ts.types
    out = []
    for ns, parent, child, R, t in transforms:
        x, y, z, w = quaternion(R)
        out.append(T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=stamp(ts, ns), frame_id=parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]),
                                                           z=float(t[2])),
                rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))))
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


# -- URDF ---------------------------------------------------------------------------------------
def _origin(R: np.ndarray, t: np.ndarray) -> str:
    from scipy.spatial.transform import Rotation

    # URDF rpy: roll about X, pitch about Y, yaw about Z, all fixed axes: R = Rz Ry Rx
    r, p, y = Rotation.from_matrix(np.asarray(R, float)).as_euler("xyz")
    return (f'<origin xyz="{t[0]:.9g} {t[1]:.9g} {t[2]:.9g}" '
            f'rpy="{r:.12g} {p:.12g} {y:.12g}"/>')


def urdf(design: Design, patches: Iterable[MirrorPatch] | None = None, *,
         name: str | None = None) -> str:
    """The head as URDF: ``nodlidar_base``, the nod joint (revolute about y through the
    pivot, the design's pitch limits), ``laser`` and one revolute joint per mirror about
    its side's lift axis (:func:`mirror_joint_frames`; limits 0 .. ``lift_angle_rad``)
    with the glass as a box (length x thickness x height from the solved patches, where
    the patch is; ``patches`` default: the design's nominal ones).
    """
    spec = design.spec
    patches = list(patches if patches is not None else design.patches())
    pivot = np.asarray(spec.nod.pivot_m, float)
    lo, hi = 0.0, abs(spec.mirror.lift_angle_rad)
    thick = spec.mirror.glass_thickness_m
    robot = name or f"nodlidar_{spec.name}"
    x = [f"<robot name={quoteattr(robot)}>",
         '  <material name="glass"><color rgba="0.6 0.8 1.0 0.5"/></material>',
         '  <material name="lidar"><color rgba="0.2 0.2 0.2 1.0"/></material>',
         f'  <link name="{BASE_FRAME}"/>',
         f'  <joint name="nod" type="revolute">\n    <parent link="{BASE_FRAME}"/>'
         f'\n    <child link="{HEAD_FRAME}"/>\n    {_origin(np.eye(3), pivot)}'
         f'\n    <axis xyz="0 1 0"/>\n    <limit lower="{spec.nod.pitch_min_rad:.12g}" '
         f'upper="{spec.nod.pitch_max_rad:.12g}" effort="10" '
         f'velocity="{spec.nod.rate_rad_s:.12g}"/>\n  </joint>',
         f'  <link name="{HEAD_FRAME}"/>',
         f'  <joint name="laser_mount" type="fixed">\n    <parent link="{HEAD_FRAME}"/>'
         f'\n    <child link="{LASER_FRAME}"/>\n    {_origin(np.eye(3), -pivot)}\n  </joint>',
         # the URG-04LX body: a 50 x 50 x 70 mm box whose scan plane is z = 0
         f'  <link name="{LASER_FRAME}">\n    <visual>\n      '
         f'{_origin(np.eye(3), np.array([0.0, 0.0, -0.035]))}\n      <geometry><box size="0.05 '
         '0.05 0.07"/></geometry>\n      <material name="lidar"/>\n    </visual>\n  </link>']
    for (mname, R, t), m in zip(mirror_joint_frames(patches, design), patches):
        # the glass box in the joint frame: its centre (behind the reflecting face by half
        # the thickness) and its axes (along, away from the lidar, up), where the patch is
        c_head = m.point((m.s_min + m.s_max) / 2, (m.z_min + m.z_max) / 2) - thick / 2 * m.normal_
        box = np.column_stack([m.along_, -m.normal_, m.up_])
        size = (m.s_max - m.s_min, thick, m.z_max - m.z_min)
        frame = mirror_frame(mname)
        x += [f'  <joint name="{frame}" type="revolute">\n    <parent link="{LASER_FRAME}"/>'
              f'\n    <child link="{frame}"/>\n    {_origin(R, t)}\n    <axis xyz="1 0 0"/>'
              f'\n    <limit lower="{lo:.12g}" upper="{hi:.12g}" effort="1" velocity="1"/>'
              '\n  </joint>',
              f'  <link name="{frame}">\n    <visual>\n      {_origin(R.T @ box, R.T @ (c_head - t))}\n      '
              f'<geometry><box size="{size[0]:.9g} {size[1]:.9g} {size[2]:.9g}"/></geometry>'
              '\n      <material name="glass"/>\n    </visual>\n  </link>']
    x.append("</robot>")
    return '<?xml version="1.0"?>\n' + "\n".join(x) + "\n"


# -- fast serialisation of many small messages -----------------------------------------------
class CdrTemplate:
    """Serialise many messages that differ only in a few fixed-size numbers (stamps,
    angles) at numpy speed: one message is serialised by the typestore with sentinel
    values, the sentinels' byte offsets are found, and each batch is the template tiled
    with the numbers written at those offsets. Exact: the bytes equal the typestore's for
    the same values (fixed-size fields do not move).

    Parameters
    ----------
    ts : Typestore
    msgtype : str
    build : callable
        ``build(values) -> message`` with ``values`` a dict name -> number.
    fields : dict
        name -> numpy dtype string (``"<i4"``, ``"<u4"``, ``"<f8"``) of each variable.
    """

    _SENTINELS = {"<i4": (0x3A5C7E11, 0x3A5C7E12), "<u4": (0xC3A5E1F1, 0xC3A5E1F2),
                  "<f8": (1.2345678901234567e-250, 2.2345678901234567e-250)}

    def __init__(self, ts: Any, msgtype: str, build: Callable[[dict[str, Any]], Any],
                 fields: dict[str, str]) -> None:
        self.fields = dict(fields)
        # two serialisations with different sentinels: the offsets are where they differ
        # and where the sentinel's bytes are (unique, checked)
        per_kind: dict[str, int] = {}
        vals = {}
        for name, dt in fields.items():
            k = per_kind.get(dt, 0)
            per_kind[dt] = k + 1
            base = self._SENTINELS[dt][0]
            vals[name] = base + k if dt != "<f8" else base * (1 + k)
        data = ts.serialize_cdr(build(vals), msgtype)
        self.template = np.frombuffer(bytes(data), dtype=np.uint8).copy()
        self.offsets = {}
        raw = bytes(data)
        for name, dt in fields.items():
            pat = np.array([vals[name]], dtype=dt).tobytes()
            at = raw.find(pat)
            if at < 0 or raw.find(pat, at + 1) >= 0:
                raise RuntimeError(f"CdrTemplate({msgtype}): field {name} not found once")
            self.offsets[name] = at
        self.msgtype = msgtype

    def batch(self, **columns: np.ndarray) -> np.ndarray:
        """(k, message size) uint8: row i is the message with ``columns[name][i]``."""
        k = len(next(iter(columns.values())))
        out = np.tile(self.template, (k, 1))
        for name, dt in self.fields.items():
            col = np.ascontiguousarray(np.asarray(columns[name]).astype(dt))
            size = np.dtype(dt).itemsize
            o = self.offsets[name]
            out[:, o:o + size] = col.view(np.uint8).reshape(k, size)
        return out
