"""Fabrication parameters of the mirror mounts (millimetres), from a design's ``[cad]`` table.

Design numbers (mirror poses, glass size, hinge height) come from the solved
:class:`~nodlidar.solver.Design` in SI units; everything here is a *fabrication* number in
millimetres (``_mm`` names) and is kept in a separate frozen dataclass (STYLE §2.1). Only
the CAD layer converts metres to millimetres.

This module must not import cadquery: it is validated by the CLI before any CAD work.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

from ..errors import ParameterError, require

__all__ = ["MountParams", "SCREW_CLEARANCE_MM", "mount_params_from_spec", "mount_params_from_dict"]

#: ISO 273 "medium" clearance-hole diameters [mm] for metric screws.
SCREW_CLEARANCE_MM: dict[str, float] = {
    "M2": 2.4, "M2.5": 2.9, "M3": 3.4, "M4": 4.5, "M5": 5.5, "M6": 6.6,
}


@dataclass(frozen=True)
class MountParams:
    """Printable dimensions of the mounts, all in millimetres unless the name says otherwise.

    Attributes
    ----------
    wall_mm : float
        Thickness of the carrier's back plate behind the glass and of the servo cradle walls.
    min_wall_mm : float
        Thinnest wall the printer/machinist accepts; every wall is checked against it.
    base_thickness_mm : float
        Thickness of the base plate under the lidar.
    base_margin_mm : float
        Width of the base plate's rim around the lidar footprint (holds the base screws).
    base_screw : str
        Screws fixing the base to the nodding platform (4 holes in the rim).
    lidar_screw : str
        Screws fixing the lidar to the base (4 holes under the housing).
    lidar_hole_spacing_mm : float
        Side of the square pattern of the lidar holes (must fit under the housing).
    hinge_pin : str
        Screw used as hinge pin; sets the hinge bore (its clearance diameter).
    hinge_boss_radius_mm : float
        Outer radius of the carrier's hinge tube and of the front pillar's boss.
    pillar_thickness_mm : float
        Thickness of the front hinge pillar along the hinge axis.
    flange_thickness_mm : float
        Thickness of the carrier's horn flange (the servo interface).
    servo_width_mm, servo_length_mm, servo_depth_mm : float
        Servo body: across, long side (perpendicular to the shaft), along the shaft.
        Defaults: Dynamixel XL430-W250 (28.5 x 46.5 x 34).
    servo_shaft_offset_mm : float
        Distance from the shaft axis to the near short end of the body.
    servo_screw : str
        Screws fixing the servo into its cradle (2 holes through the cradle floor).
    horn_radius_mm, horn_thickness_mm : float
        Servo horn disc; the carrier flange has the same radius.
    horn_bolt_circle_mm : float
        Diameter of the horn's bolt circle (4 holes of ``horn_screw``).
    horn_screw : str
        Screws fixing the horn to the carrier flange.
    servo_clearance_mm : float
        Gap around the servo body in its cradle pocket.
    pocket_clearance_mm : float
        Length play of each glass in its pocket: the pocket is the solved mirror length
        plus this, half of it at each end (between the glass end and the end stop, or at
        a chained joint between the glass's back edge and the back plate's joint face).
        At a chained joint it must stay below ``2 * glass thickness * tan(joint angle / 2)``
        (the room the wedge between the two glass ends leaves behind the faces).
    end_stop_length_mm : float
        Length (along the mirror) of the end stop at each free end of a pocket (the outer
        end of a side's outermost mirror, the inner end of its innermost one, both ends of
        an unchained mirror). The stop lies beyond the patch (outside its ``s`` range).
    end_stop_height_mm : float
        Height of the end stop above the glass seat. The stop stays below the beams:
        ``glass_height / 2 - end_stop_height_mm >= beam_band_mm`` (checked at build time).
    end_stop_depth_mm : float
        How far the end stop stands in front of the glass datum, towards the glass face:
        less than the glass thickness (checked at build time), so the stop stays behind the
        mirror's face plane and the STEP has one face in that plane, the mirror's.
    clearance_mm : float
        Minimum gap between parts that move against each other (carrier/base/pillar).
    beam_band_mm : float
        Half-height of the band around the scan plane that beams may use (divergence);
        mount solids outside the mirrors' shadows stay out of it.
    stl_tolerance_mm : float
        STL linear deflection.
    stl_angular_tolerance_rad : float
        STL angular deflection [rad].
    bed_x_mm, bed_y_mm : float
        The printer bed; printable parts larger than it (in any rotation about the
        vertical) are split into pieces that fit (default 250 x 210 mm).
    lap_mm : float
        Overlap of the half-lap joint at each split.
    joint_screw : str
        Screws through each half-lap joint.
    dowel_mm, dowel_fit_mm : float
        Alignment dowels in each half-lap joint and the extra diameter of their holes.
    """

    wall_mm: float = 3.0
    min_wall_mm: float = 1.2
    base_thickness_mm: float = 5.0
    base_margin_mm: float = 10.0
    base_screw: str = "M4"
    lidar_screw: str = "M3"
    lidar_hole_spacing_mm: float = 40.0
    hinge_pin: str = "M3"
    hinge_boss_radius_mm: float = 6.0
    pillar_thickness_mm: float = 6.0
    flange_thickness_mm: float = 3.0
    servo_width_mm: float = 28.5
    servo_length_mm: float = 46.5
    servo_depth_mm: float = 34.0
    servo_shaft_offset_mm: float = 13.5
    servo_screw: str = "M2"
    horn_radius_mm: float = 11.0
    horn_thickness_mm: float = 2.5
    horn_bolt_circle_mm: float = 16.0
    horn_screw: str = "M2"
    servo_clearance_mm: float = 0.3
    pocket_clearance_mm: float = 0.3
    end_stop_length_mm: float = 3.0
    end_stop_height_mm: float = 10.0
    end_stop_depth_mm: float = 1.5
    clearance_mm: float = 1.0
    beam_band_mm: float = 3.0
    stl_tolerance_mm: float = 0.02
    stl_angular_tolerance_rad: float = 0.1
    bed_x_mm: float = 250.0
    bed_y_mm: float = 210.0
    lap_mm: float = 20.0
    joint_screw: str = "M3"
    dowel_mm: float = 3.0
    dowel_fit_mm: float = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type == "str" or isinstance(f.default, str):
                require(isinstance(v, str) and v in SCREW_CLEARANCE_MM, f"cad.{f.name}", v,
                        "one of " + ", ".join(SCREW_CLEARANCE_MM))
                continue
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            require(ok and v >= 0, f"cad.{f.name}", v, "a finite number >= 0")
            object.__setattr__(self, f.name, float(v))
        positive = [f.name for f in fields(self) if not isinstance(f.default, str)
                    and not f.name.endswith("clearance_mm")]
        for name in positive:
            require(getattr(self, name) > 0, f"cad.{name}", getattr(self, name), "> 0")
        mw = self.min_wall_mm
        for name in ("wall_mm", "base_thickness_mm", "pillar_thickness_mm",
                     "flange_thickness_mm", "end_stop_length_mm", "end_stop_height_mm"):
            require(getattr(self, name) >= mw, f"cad.{name}", getattr(self, name),
                    f">= cad.min_wall_mm = {mw}")
        pin = self.clearance_dia_mm(self.hinge_pin)
        require(self.hinge_boss_radius_mm - pin / 2 >= mw, "cad.hinge_boss_radius_mm",
                self.hinge_boss_radius_mm,
                f">= hinge bore radius {pin / 2} + min_wall_mm {mw} = {pin / 2 + mw}")
        horn_hole = self.clearance_dia_mm(self.horn_screw)
        need = self.horn_bolt_circle_mm / 2 + horn_hole / 2 + mw
        require(self.horn_radius_mm >= need, "cad.horn_radius_mm", self.horn_radius_mm,
                f">= horn bolt circle/2 + hole radius + min wall = {need:.3g}")
        require(self.horn_bolt_circle_mm / 2 - horn_hole / 2 - pin / 2 >= mw,
                "cad.horn_bolt_circle_mm", self.horn_bolt_circle_mm,
                f"large enough to leave {mw} mm between the horn holes and the hinge bore")
        need = self.clearance_dia_mm(self.base_screw) + 2 * mw
        require(self.base_margin_mm >= need, "cad.base_margin_mm", self.base_margin_mm,
                f">= base screw clearance + 2 * min wall = {need:.3g}")
        require(self.servo_shaft_offset_mm < self.servo_length_mm, "cad.servo_shaft_offset_mm",
                self.servo_shaft_offset_mm, f"< servo_length_mm = {self.servo_length_mm}")
        require(self.stl_tolerance_mm <= min(0.5, mw / 4), "cad.stl_tolerance_mm",
                self.stl_tolerance_mm, f"<= min(0.5, min_wall_mm/4 = {mw / 4})")
        require(0.01 <= self.stl_angular_tolerance_rad <= 0.5, "cad.stl_angular_tolerance_rad",
                self.stl_angular_tolerance_rad, "0.01 .. 0.5 rad (finer explodes the mesh)")
        # the linear deflection is absolute: finer than 1 um, or parts larger than 1 m
        # (any *_mm), make meshes of millions of triangles per part
        require(self.stl_tolerance_mm >= 0.001, "cad.stl_tolerance_mm", self.stl_tolerance_mm,
                ">= 0.001 mm (finer explodes the mesh)")
        for name in positive:
            require(getattr(self, name) <= 1000, f"cad.{name}", getattr(self, name), "<= 1000 mm")

    @staticmethod
    def clearance_dia_mm(screw: str) -> float:
        """Clearance-hole diameter [mm] of a metric screw name (``"M3"`` -> 3.4)."""
        return SCREW_CLEARANCE_MM[screw]

    @property
    def hinge_bore_mm(self) -> float:
        """Diameter of the hinge bore [mm]."""
        return self.clearance_dia_mm(self.hinge_pin)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict in the ``[cad]`` layout (round-trips through :func:`mount_params_from_dict`)."""
        return asdict(self)


def mount_params_from_dict(table: Any) -> MountParams:
    """Validate a ``[cad]`` table; unknown keys are errors naming the allowed ones."""
    if table is None:
        table = {}
    if not isinstance(table, dict):
        raise ParameterError("cad", table, "a TOML table of fabrication parameters")
    from ..validation import check_keys  # unknown keys: the nearest valid one named

    check_keys(table, [f.name for f in fields(MountParams)], "cad")
    return MountParams(**table)


def mount_params_from_spec(spec: Any) -> MountParams:
    """The :class:`MountParams` of a :class:`~nodlidar.spec.DesignSpec` (defaults if no ``[cad]``)."""
    return mount_params_from_dict(spec.sections.get("cad", {}))
