"""Compiled scalar formulas of :mod:`nodlidar.geometry`, shared by the per-point kernels.

The point assembly (:mod:`nodlidar.runtime._assembly_kernel`) and the simulator
(:mod:`nodlidar.sim._kernel`) loop over beams in numba and need geometry's rotation and
reflection on one vector at a time; this module is that one copy (issue 16; issue 18's
"one rotation implementation": :func:`rodrigues` is :func:`nodlidar.geometry.rotate_columns`
for one vector, operation for operation, and :func:`reflect` is
:func:`nodlidar.geometry.reflect`; tests/test_assembly.py and tests/test_sim_kernel.py
compare them to 1e-12).

The helpers are ``inline="always"``: numba inlines them into the calling kernel at IR
level (as separate compiled calls each cost ~13 ns per point). numba's on-disk cache keys
a kernel on its own source file only, so after editing this module delete the kernels'
caches (``make clean`` deletes them) - an installed upgrade replaces every
file and invalidates them anyway.

numba is imported here: only the kernel modules import this one (never ``import nodlidar``).
"""

from __future__ import annotations

import math

import numba

__all__ = ["cos_sin", "rodrigues", "reflect"]

_inline = numba.njit(cache=True, nogil=True, inline="always")


@_inline
def cos_sin(a: float) -> tuple[float, float]:
    """``cos a``, ``sin a`` [rad] from one ``tan`` of the half angle, as
    :func:`nodlidar.beams.cos_sin` (exact for ``|a| <= pi``; within a few ulp)."""
    t = math.tan(a * 0.5)
    t2 = t * t
    den = 1.0 / (1.0 + t2)
    return (1.0 - t2) * den, (2.0 * den) * t


@_inline
def rodrigues(x: float, y: float, z: float, kx: float, ky: float, kz: float, c: float,
              s: float) -> tuple[float, float, float]:
    """Vector ``(x, y, z)`` turned about unit axis ``k`` by the angle of cosine ``c`` and
    sine ``s``: ``v c + (k x v) s + k (k.v)(1 - c)``, :func:`nodlidar.geometry.rotate_columns`
    for one vector."""
    kv = kx * x + ky * y + kz * z
    kv = kv * (1.0 - c)
    qx = x * c + (ky * z - kz * y) * s + kx * kv
    qy = y * c + (kz * x - kx * z) * s + ky * kv
    qz = z * c + (kx * y - ky * x) * s + kz * kv
    return qx, qy, qz


@_inline
def reflect(dx: float, dy: float, dz: float, nx: float, ny: float, nz: float
            ) -> tuple[float, float, float]:
    """Direction ``d`` mirrored in the plane of unit normal ``n``: ``d - 2 (d.n) n``,
    :func:`nodlidar.geometry.reflect` for one vector."""
    dn = dx * nx + dy * ny + dz * nz
    return dx - 2.0 * dn * nx, dy - 2.0 * dn * ny, dz - 2.0 * dn * nz
