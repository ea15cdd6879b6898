"""Point-cloud files: PLY (binary little-endian or ASCII) and PCD v0.7 (ASCII or binary).

Every point carries ``x y z`` (float32 by default, float64 on request) plus ``t``
(float64 [s]), ``range`` (float64 [m]), ``step`` (int32), ``mirror`` (int32, -1 direct),
``scan`` (int32) and, for an assembled cloud, ``nod`` (float32 [rad], head pitch at the
beam's time) and ``lifted`` (uint8, 1 = the beam's mirror side was lifted). The cloud's
frame, design name/hash, calibration id and mirror names go into header comments
(``comment nodlidar key=value`` in PLY, ``# nodlidar key=value`` in PCD), so a file read
back is the same :class:`~nodlidar.runtime.assembly.PointCloud`.

Types are the ones every common reader keeps: PCL and Open3D need float32 ``x y z``
(Open3D's legacy reader loads float64 xyz as all zeros, PCL finds no 'x'); Open3D's
tensor PLY reader drops ``char``, ``short``, ``ushort`` and ``uint`` properties and keeps
``float``, ``double``, ``int`` and ``uchar`` (checked with Open3D 0.20), so only those
four are written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import DesignFileError, ParameterError, require
from .assembly import FRAMES, PointCloud

__all__ = ["FIELDS", "structured", "write_cloud", "read_cloud", "write_ply", "read_ply",
           "write_pcd", "read_pcd"]

# name in file, PointCloud attribute, dtype (float32/float64/int32/uint8 only: see above)
_EXTRA = (("t", "t", "<f8"), ("range", "range_m", "<f8"), ("step", "step", "<i4"),
          ("mirror", "mirror", "<i4"), ("scan", "scan", "<i4"))
# written only when the cloud has them (an assembled cloud does)
_OPTIONAL = (("nod", "nod_rad", "<f4"), ("lifted", "lifted", "|u1"))
#: the field names and types written, in file order (x y z first, then these)
FIELDS = tuple(f for f, _, _ in _EXTRA + _OPTIONAL)
_PLY_TYPE = {"<f4": "float", "<f8": "double", "<i4": "int", "<i2": "short", "|u1": "uchar",
             "|i1": "char", "<u2": "ushort", "<u4": "uint"}
_PLY_DTYPE = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
              "int": "<i4", "int32": "<i4", "short": "<i2", "int16": "<i2", "uchar": "<u1",
              "uint8": "<u1", "char": "<i1", "int8": "<i1", "ushort": "<u2", "uint16": "<u2",
              "uint": "<u4", "uint32": "<u4"}


def _names(dt: np.dtype) -> tuple[str, ...]:
    return dt.names or ()


def _meta(cloud: PointCloud) -> dict[str, str]:
    return {"frame": cloud.frame, "design_name": cloud.design_name,
            "design_hash": cloud.design_hash, "calibration_id": cloud.calibration_id,
            "mirror_names": ",".join(cloud.mirror_names),
            "meta": json.dumps(dict(cloud.meta), separators=(",", ":"))}


def structured(cloud: PointCloud, xyz_dtype: str = "<f4") -> np.ndarray:
    """The cloud as a packed structured array ``(n,)`` in file field order (also the
    PointCloud2 layout of :mod:`nodlidar.runtime.ros`)."""
    extra = [(f, a, d) for f, a, d in _EXTRA + _OPTIONAL if getattr(cloud, a) is not None]
    dt = [("x", xyz_dtype), ("y", xyz_dtype), ("z", xyz_dtype)] + [(f, d) for f, _, d in extra]
    a = np.empty(len(cloud), dtype=dt)
    a["x"], a["y"], a["z"] = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    for f, attr, _ in extra:
        a[f] = getattr(cloud, attr)
    return a


_structured = structured


def _from_structured(a: np.ndarray, meta: dict[str, str]) -> PointCloud:
    names = a.dtype.names or ()
    for f in ("x", "y", "z"):
        if f not in names:
            raise DesignFileError(f"point cloud file has no '{f}' field")
    n = len(a)

    def col(f, dtype, default):
        return a[f].astype(dtype) if f in names else np.full(n, default, dtype=dtype)

    xyz = np.stack([a["x"], a["y"], a["z"]], -1).astype(float)
    try:
        extra = json.loads(meta["meta"]) if meta.get("meta") else {}
    except ValueError:
        raise DesignFileError("point cloud file: its 'nodlidar meta' comment is not JSON") from None
    mn = meta.get("mirror_names", "")
    frame = meta.get("frame", "sensor")
    require(frame in FRAMES, "point cloud file: nodlidar frame", frame, ", ".join(FRAMES))
    return PointCloud(xyz, col("t", float, np.nan), col("step", np.int32, -1),
                      col("mirror", np.int16, -1), col("scan", np.int32, -1),
                      col("range", float, np.nan), frame,
                      meta.get("design_name", ""), meta.get("design_hash", ""),
                      meta.get("calibration_id", "none"), tuple(mn.split(",")) if mn else (),
                      extra, a["nod"].astype(float) if "nod" in names else None,
                      a["lifted"].astype(bool) if "lifted" in names else None)


def _check_xyz_type(xyz_type: str) -> str:
    require(xyz_type in ("float32", "float64"), "xyz_type", xyz_type, "'float32' or 'float64'")
    return "<f4" if xyz_type == "float32" else "<f8"


# -- PLY --------------------------------------------------------------------------------
def write_ply(path: str | Path, cloud: PointCloud, *, binary: bool = True,
              xyz_type: str = "float32") -> Path:
    """Write ``cloud`` as PLY (``binary_little_endian`` or ``ascii``); returns the path."""
    a = _structured(cloud, _check_xyz_type(xyz_type))
    fmt = "binary_little_endian" if binary else "ascii"
    head = ["ply", f"format {fmt} 1.0", "comment nodlidar point cloud"]
    head += [f"comment nodlidar {k}={v}" for k, v in _meta(cloud).items()]
    head.append(f"element vertex {len(a)}")
    head += [f"property {_PLY_TYPE[a.dtype[f].str]} {f}" for f in _names(a.dtype)]
    head.append("end_header")
    p = Path(path)
    with p.open("wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("ascii"))
        if binary:
            fh.write(a.tobytes())
        else:
            _write_ascii_rows(fh, a)
    return p


def _write_ascii_rows(fh, a: np.ndarray) -> None:
    # shortest repr-exact digits (9 for float32, 17 for float64): ASCII round trips bit
    # for bit
    fmts = [("%.9g" if a.dtype[f].itemsize == 4 else "%.17g") if a.dtype[f].kind == "f" else "%d"
            for f in _names(a.dtype)]
    if len(a):
        np.savetxt(fh, a, fmt=fmts, delimiter=" ")


def _read_header(fh, first: bytes, end: bytes) -> list[str]:
    lines = [first.decode("ascii", "replace").strip()]
    while True:
        line = fh.readline()
        if not line:
            raise DesignFileError(f"{fh.name}: header has no '{end.decode()}'")
        s = line.decode("ascii", "replace").strip()
        lines.append(s)
        if s.startswith(end.decode()):
            return lines


def read_ply(path: str | Path) -> PointCloud:
    """Read a PLY file with a vertex element (binary little-endian or ASCII)."""
    p = Path(path)
    if not p.is_file():
        raise DesignFileError(f"point cloud file not found: {p}")
    with p.open("rb") as fh:
        magic = fh.readline()
        if magic.strip() != b"ply":
            raise DesignFileError(f"{p}: not a PLY file")
        head = _read_header(fh, magic, b"end_header")
        fmt, n, in_vertex = None, 0, False
        meta: dict[str, str] = {}
        fields: list[tuple[str, str]] = []
        for line in head[1:]:
            w = line.split()
            if not w:
                continue
            if w[0] == "format":
                fmt = w[1]
            elif w[0] == "comment" and len(w) > 1 and w[1] == "nodlidar" and "=" in line:
                k, _, v = line.split(" ", 2)[2].partition("=")
                meta[k] = v
            elif w[0] == "element":
                in_vertex = w[1] == "vertex"
                if in_vertex:
                    n = int(w[2])
                elif not fields:
                    raise DesignFileError(f"{p}: element {w[1]!r} before vertex unsupported")
            elif w[0] == "property" and in_vertex:
                if w[1] == "list" or w[1] not in _PLY_DTYPE:
                    raise DesignFileError(f"{p}: unsupported vertex property {line!r}")
                fields.append((w[2], _PLY_DTYPE[w[1]]))
        if fmt not in ("binary_little_endian", "ascii"):
            raise DesignFileError(f"{p}: PLY format {fmt!r}; allowed: binary_little_endian, ascii")
        dt = np.dtype(fields)
        if fmt == "binary_little_endian":
            buf = fh.read(n * dt.itemsize)
            if len(buf) < n * dt.itemsize:
                raise DesignFileError(f"{p}: truncated ({len(buf)} of {n * dt.itemsize} bytes)")
            a = np.frombuffer(buf, dtype=dt, count=n)
        else:
            a = _read_ascii_rows(fh, dt, n, p)
    return _from_structured(a, meta)


def _read_ascii_rows(fh, dt: np.dtype, n: int, p: Path) -> np.ndarray:
    a = np.empty(n, dtype=dt)
    if n == 0:
        return a
    rows = np.loadtxt(fh, dtype=float, ndmin=2, max_rows=n)
    names = _names(dt)
    if rows.shape != (n, len(names)):
        raise DesignFileError(f"{p}: expected {n} rows of {len(names)} values, got {rows.shape}")
    for i, f in enumerate(names):
        a[f] = rows[:, i]
    return a


# -- PCD --------------------------------------------------------------------------------
def write_pcd(path: str | Path, cloud: PointCloud, *, binary: bool = True,
              xyz_type: str = "float32") -> Path:
    """Write ``cloud`` as PCD v0.7 (``DATA binary`` or ``ascii``); returns the path."""
    a = _structured(cloud, _check_xyz_type(xyz_type))
    names = _names(a.dtype)
    types = ["F" if a.dtype[f].kind == "f" else ("U" if a.dtype[f].kind == "u" else "I")
             for f in names]
    head = ["# .PCD v0.7 - Point Cloud Data file format"]
    head += [f"# nodlidar {k}={v}" for k, v in _meta(cloud).items()]
    head += ["VERSION 0.7", "FIELDS " + " ".join(names),
             "SIZE " + " ".join(str(a.dtype[f].itemsize) for f in names),
             "TYPE " + " ".join(types), "COUNT " + " ".join("1" for _ in names),
             f"WIDTH {len(a)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(a)}",
             f"DATA {'binary' if binary else 'ascii'}"]
    p = Path(path)
    with p.open("wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("ascii"))
        if binary:
            fh.write(a.tobytes())
        else:
            _write_ascii_rows(fh, a)
    return p


def read_pcd(path: str | Path) -> PointCloud:
    """Read a PCD file (``DATA ascii`` or ``binary``; not ``binary_compressed``)."""
    p = Path(path)
    if not p.is_file():
        raise DesignFileError(f"point cloud file not found: {p}")
    with p.open("rb") as fh:
        first = fh.readline()
        head = _read_header(fh, first, b"DATA")
        meta: dict[str, str] = {}
        kv: dict[str, list[str]] = {}
        for line in head:
            if line.startswith("# nodlidar ") and "=" in line:
                k, _, v = line[len("# nodlidar "):].partition("=")
                meta[k] = v
            elif line and not line.startswith("#"):
                w = line.split()
                kv[w[0]] = w[1:]
        try:
            names, sizes, types = kv["FIELDS"], [int(s) for s in kv["SIZE"]], kv["TYPE"]
            counts = [int(c) for c in kv.get("COUNT", ["1"] * len(names))]
            n = int(kv["POINTS"][0])
            data = kv["DATA"][0]
        except (KeyError, IndexError, ValueError) as exc:
            raise DesignFileError(f"{p}: malformed PCD header ({exc})") from None
        if any(c != 1 for c in counts):
            raise DesignFileError(f"{p}: fields with COUNT > 1 are not supported")
        kind = {"F": "f", "I": "i", "U": "u"}
        ok = (len(names) == len(sizes) == len(types) == len(counts) and n >= 0
              and all((t in ("I", "U") and s in (1, 2, 4, 8)) or (t == "F" and s in (4, 8))
                      for t, s in zip(types, sizes)))
        if not ok:
            raise DesignFileError(f"{p}: malformed PCD header (FIELDS/SIZE/TYPE/COUNT do not "
                                  "match, or a SIZE/TYPE PCD v0.7 does not allow)")
        try:
            dt = np.dtype([(nm, f"<{kind[t]}{s}") for nm, t, s in zip(names, types, sizes)])
        except ValueError as exc:  # repeated field names
            raise DesignFileError(f"{p}: malformed PCD header ({exc})") from None
        if data == "binary":
            buf = fh.read(n * dt.itemsize)
            if len(buf) < n * dt.itemsize:
                raise DesignFileError(f"{p}: truncated ({len(buf)} of {n * dt.itemsize} bytes)")
            a = np.frombuffer(buf, dtype=dt, count=n)
        elif data == "ascii":
            a = _read_ascii_rows(fh, dt, n, p)
        else:
            raise DesignFileError(f"{p}: PCD DATA {data!r}; allowed: ascii, binary")
    return _from_structured(a, meta)


# -- by extension ------------------------------------------------------------------------
def write_cloud(path: str | Path, cloud: PointCloud, *, binary: bool = True,
                xyz_type: str = "float32") -> Path:
    """Write a ``.ply`` or ``.pcd`` file (chosen by the extension)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        return write_ply(path, cloud, binary=binary, xyz_type=xyz_type)
    if suffix == ".pcd":
        return write_pcd(path, cloud, binary=binary, xyz_type=xyz_type)
    raise ParameterError("out", str(path), "a .ply or .pcd file name")


def read_cloud(path: str | Path) -> PointCloud:
    """Read a ``.ply`` or ``.pcd`` file (chosen by the extension)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        return read_ply(path)
    if suffix == ".pcd":
        return read_pcd(path)
    raise ParameterError("path", str(path), "a .ply or .pcd file name")
