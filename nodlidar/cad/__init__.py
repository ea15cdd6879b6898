"""CAD of the mirror mounts (cadquery): parametric parts, two states, export and manifest.

Importing :mod:`nodlidar.cad` is cheap: cadquery is only imported when a build or an
export is asked for (``import nodlidar`` never imports it). Public API::

    from nodlidar.cad import MountParams, mount_params_from_spec, export_cad
    manifest = export_cad(design, "cad_out")           # writes cad_out/<design name>/

Frames: the head frame of the solver (x forward, y left, z up, scan plane z = 0), in
millimetres inside the CAD layer (converted from SI metres at the edge). See
:mod:`nodlidar.cad.mounts` for the part geometry and the hinge-axis convention.
"""

from __future__ import annotations

from typing import Any

from .params import SCREW_CLEARANCE_MM, MountParams, mount_params_from_dict, mount_params_from_spec

__all__ = [
    "MountParams",
    "SCREW_CLEARANCE_MM",
    "mount_params_from_dict",
    "mount_params_from_spec",
    "export_cad",
    "Manifest",
    "build_mounts",
    "hinge_axes",
    "mirror_face_poses",
]

_LAZY = {
    "export_cad": "export",
    "Manifest": "export",
    "build_mounts": "mounts",
    "hinge_axes": "mounts",
    "mirror_face_poses": "mounts",
}


def __getattr__(name: str) -> Any:  # PEP 562: heavy modules on first use
    if name in _LAZY:
        import importlib

        mod = importlib.import_module(f"{__name__}.{_LAZY[name]}")
        return getattr(mod, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
