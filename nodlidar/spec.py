"""Design files: frozen, validated parameter dataclasses loaded from and written to TOML.

A design file (``design/*.toml``) describes one sensor build::

    name = "urg04lx-paper"
    [lidar]      model
    [layout]     design_distance_m, windows (odd k >= 3), mirrors_per_side
    [placement]  method ("anchor" | "optimal"), standoff_m, chain, clearance_m, margin_steps
    [mirror]     glass_height_m, glass_thickness_m, hinge_z_m, lift_angle_rad
    [nod]        pitch_min_rad, pitch_max_rad, rate_rad_s, pivot_m
    [reference]  optional published numbers to compare against (free-form)

The owned tables ``[tolerance]``, ``[calibration]`` and ``[cad]`` are kept verbatim in
:attr:`DesignSpec.sections` for the modules that own them, and parsed by them on load.
Loading goes through :mod:`nodlidar.validation`: unknown sections and keys are errors
naming the nearest valid one (a typo never silently falls back to a default), values are
typed strictly (no ``true`` for a number, no ``"false"`` for a boolean, finite numbers) and
bounded physically, and the name must be usable as a folder name.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DesignFileError, ParameterError, require
from .lidar import LidarModel, lidar_model
from .validation import safe_name

__all__ = [
    "LayoutSpec",
    "SideWindow",
    "MirrorPlan",
    "PlacementSpec",
    "MirrorSpec",
    "NodSpec",
    "DesignSpec",
    "load_design",
    "design_from_dict",
    "design_to_toml",
]

PLACEMENT_METHODS = ("anchor", "optimal")


def _table(cls, value: Any, name: str):
    """``cls(**value)`` for a TOML sub-table, unknown keys named."""
    if not isinstance(value, dict):
        raise ParameterError(name, value, f"a table with keys {', '.join(f.name for f in fields(cls))}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(value) - known)
    require(not unknown, name, unknown, f"keys {', '.join(sorted(known))}")
    return cls(**value)


def _edges(obj: Any, attr: str, name: str, kind: type) -> None:
    """Normalise an optional ``(first, last)`` pair of ``kind`` on a frozen dataclass."""
    val = getattr(obj, attr)
    if val is None or (hasattr(val, "__len__") and len(val) == 0):
        object.__setattr__(obj, attr, ())
        return
    ok = hasattr(val, "__len__") and len(val) == 2
    if ok and kind is int:
        ok = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in val)
    if ok:
        vals = tuple(kind(v) for v in val)
        ok = bool(np.all(np.isfinite(vals))) and vals[0] <= vals[1]
    require(ok, name, val, f"[first, last] ({'integer steps' if kind is int else 'degrees'}), "
            "first <= last")
    object.__setattr__(obj, attr, vals)


@dataclass
class _Pair:
    v: Any


@dataclass(frozen=True)
class SideWindow:
    """One reflected window of the field of view, given by its edges.

    Attributes
    ----------
    steps, deg : (first, last) or ()
        Edge steps (inclusive) or edge bearings [deg]; exactly one of the two. The window
        lies wholly on one side of the front window; that fixes its side (L: above it).
    mirrors : int
        How many mirrors split it (evenly; the outermost takes any extra beam).
    offsets : tuple of int
        Interleave slot ``q`` of each mirror, outermost first, in ``1/slots_per_step`` of a
        step (default ``1, 2, ..``). Mirrors of a side with the same ``q`` fill the front
        window one after the other: left-side beams from its first step up, right-side
        beams from its last step down.
    """

    steps: tuple[int, ...] = ()
    deg: tuple[float, ...] = ()
    mirrors: int = 1
    offsets: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        require(bool(len(self.steps)) != bool(len(self.deg)), "layout.side_windows.steps/deg",
                (list(self.steps), list(self.deg)), "exactly one of steps = [first, last] or "
                "deg = [first, last]")
        _edges(self, "steps", "layout.side_windows.steps", int)
        _edges(self, "deg", "layout.side_windows.deg", float)
        require(isinstance(self.mirrors, int) and self.mirrors >= 1,
                "layout.side_windows.mirrors", self.mirrors, "an integer >= 1")
        offs = tuple(self.offsets) if len(self.offsets) else tuple(range(1, self.mirrors + 1))
        require(len(offs) == self.mirrors and all(isinstance(q, int) and q >= 1 for q in offs),
                "layout.side_windows.offsets", list(self.offsets),
                f"{self.mirrors} integers >= 1 (one per mirror, outermost first)")
        object.__setattr__(self, "offsets", offs)


@dataclass(frozen=True)
class MirrorPlan:
    """One mirror given explicitly (``[[placement.mirrors]]``), bypassing the window split.

    Attributes
    ----------
    name : str
        ``"L1"``, ``"R2"``...: side letter and position from the outside.
    steps : (first, last)
        The beams the mirror takes (inclusive).
    target_step : int
        The direct step ``g`` beside which the anchor beam lands.
    target_offset : int
        The anchor beam lands ``target_offset / slots_per_step`` of a step anticlockwise of
        ``g`` (may be negative: clockwise). The other beams follow the reversed fan: step
        ``anchor + i`` lands beside ``g - i``.
    anchor_step : int
        The beam constructed to land exactly on its target (default: the outermost of
        ``steps``). It may lie outside ``steps`` or the lidar's valid steps: it is then a
        construction ray only (the paper's right side, mirrored from step 725 to 43).
    standoff_m : float
        OA for this mirror [m] (0: chained).
    chain : bool
        The mirror starts where the previous mirror of its side (in file order) ends.
    """

    name: str
    steps: tuple[int, ...]
    target_step: int
    target_offset: int = 1
    anchor_step: int = -1
    standoff_m: float = 0.0
    chain: bool = False

    @property
    def side(self) -> str:
        return self.name[0]

    @property
    def index(self) -> int:
        return int(self.name[1:])

    @property
    def anchor(self) -> int:
        """The anchor step (resolving the default)."""
        if self.anchor_step >= 0:
            return self.anchor_step
        return self.steps[1] if self.side == "L" else self.steps[0]

    def __post_init__(self) -> None:
        require(isinstance(self.name, str) and len(self.name) >= 2 and self.name[0] in "LR"
                and self.name[1:].isdigit() and int(self.name[1:]) >= 1,
                "placement.mirrors.name", self.name, "'L<n>' or 'R<n>', n >= 1")
        _edges(self, "steps", f"placement.mirrors[{self.name}].steps", int)
        require(len(self.steps) == 2, f"placement.mirrors[{self.name}].steps", list(self.steps),
                "[first, last]")
        for key in ("target_step", "target_offset", "anchor_step"):
            v = getattr(self, key)
            require(isinstance(v, (int, np.integer)) and not isinstance(v, bool),
                    f"placement.mirrors[{self.name}].{key}", v, "an integer")
        require(self.standoff_m >= 0 and np.isfinite(self.standoff_m),
                f"placement.mirrors[{self.name}].standoff_m", self.standoff_m,
                "> 0 m (0 only with chain = true)")
        require(self.chain or self.standoff_m > 0,
                f"placement.mirrors[{self.name}].standoff_m", self.standoff_m,
                "> 0 m unless chain = true")


@dataclass(frozen=True)
class LayoutSpec:
    """How the field of view is split.

    Attributes
    ----------
    design_distance_m : float
        Radius D of the arc on which reflected beams interleave exactly [m].
    windows : int
        Odd number k >= 3 of equal windows; the middle one is unreflected.
    mirrors_per_side : int
        Mirrors on each side: ``k-1`` (each side fills half the middle window, as in the
        paper) or ``(k-1)/2`` (each side's mirrors span the whole middle window).
    front_window_steps, front_window_deg : (first, last) or ()
        The unreflected front window by its edge steps (inclusive) or edge bearings [deg]
        (steps whose bearing lies within). Default: the middle of ``windows`` equal ones.
    side_windows : tuple of :class:`SideWindow`
        The reflected windows by their edges (``[[layout.side_windows]]``). Given, they
        replace the ``windows``/``mirrors_per_side`` split: sides may differ, one side may
        be absent, a window may cover part of a side and have any number of mirrors.
    slots_per_step : int
        Interleave slots per native step: reflected beams land ``q / slots_per_step`` of a
        step beside a direct beam (0: ``windows``).
    """

    design_distance_m: float
    windows: int = 3
    mirrors_per_side: int = 2
    front_window_steps: tuple[int, ...] = ()
    front_window_deg: tuple[float, ...] = ()
    side_windows: tuple[SideWindow, ...] = ()
    slots_per_step: int = 0

    @property
    def slots(self) -> int:
        """Interleave slots per native step (``slots_per_step``, default ``windows``)."""
        return self.slots_per_step or self.windows

    @property
    def max_mirrors_per_side(self) -> int:
        """Most mirrors on one side (sizes ``placement.standoff_m`` when not chained)."""
        if not self.side_windows:
            return self.mirrors_per_side
        return max(w.mirrors for w in self.side_windows)

    def __post_init__(self) -> None:
        object.__setattr__(self, "side_windows", tuple(
            w if isinstance(w, SideWindow) else _table(SideWindow, w, "layout.side_windows")
            for w in self.side_windows))
        require(not (self.front_window_steps and self.front_window_deg),
                "layout.front_window_steps/front_window_deg",
                (list(self.front_window_steps), list(self.front_window_deg)), "one of the two")
        _edges(self, "front_window_steps", "layout.front_window_steps", int)
        _edges(self, "front_window_deg", "layout.front_window_deg", float)
        require(isinstance(self.slots_per_step, int) and self.slots_per_step >= 0,
                "layout.slots_per_step", self.slots_per_step,
                "an integer >= 2 (0: the number of windows)")
        require(self.slots_per_step != 1, "layout.slots_per_step", self.slots_per_step,
                "an integer >= 2 (0: the number of windows)")
        require(
            np.isfinite(self.design_distance_m) and self.design_distance_m > 0,
            "layout.design_distance_m", self.design_distance_m, "> 0 m",
        )
        require(
            isinstance(self.windows, int) and self.windows >= 3 and self.windows % 2 == 1,
            "layout.windows", self.windows, "an odd integer >= 3",
        )
        k = self.windows
        allowed = sorted({k - 1, (k - 1) // 2})
        require(
            self.mirrors_per_side in allowed,
            "layout.mirrors_per_side", self.mirrors_per_side,
            f"one of {allowed} for windows = {k}",
        )


@dataclass(frozen=True)
class PlacementSpec:
    """Where the mirrors go: the free parameters the paper leaves open.

    Attributes
    ----------
    method : str
        ``"anchor"``: the paper's construction (each mirror's anchor beam lands exactly on
        its target at D). ``"optimal"``: standoff and angle chosen to minimise the RMS
        bearing error over all of a mirror's beams at D.
    standoff_m : tuple of float
        The paper's OA: perpendicular distance [m] from the lidar origin O to the reflected
        ray of a mirror's anchor beam. With ``chain`` only the first entry (the outermost
        mirror of each side) is used; otherwise one entry per mirror of a side.
    chain : bool
        Each inner mirror starts where the next outer one ends (no gap for beams to leak
        through); this is what reproduces the paper's L2 from its L1.
    clearance_m : float
        Minimum gap between a mirror and the lidar housing cylinder [m].
    margin_steps : float
        A mirror patch extends this many steps beyond its first and last beam (0.5: patch
        edges fall halfway between beams, so neighbouring mirrors meet exactly).
    mirrors : tuple of :class:`MirrorPlan`
        Every mirror given explicitly (``[[placement.mirrors]]``); replaces the split of
        ``[layout]`` and ``standoff_m``/``chain``. Empty: mirrors follow from the layout.
    shadowed_steps : tuple of (first, last)
        Beams the design knowingly gives up: reflected beams in these step ranges may be
        blocked by another mirror; any other blocked beam still refuses the design.
    """

    method: str = "anchor"
    standoff_m: tuple[float, ...] = (0.02,)
    chain: bool = True
    clearance_m: float = 0.005
    margin_steps: float = 0.5
    mirrors: tuple[MirrorPlan, ...] = ()
    shadowed_steps: tuple[tuple[int, ...], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "mirrors", tuple(
            m if isinstance(m, MirrorPlan) else _table(MirrorPlan, m, "placement.mirrors")
            for m in self.mirrors))
        names = [m.name for m in self.mirrors]
        require(len(set(names)) == len(names), "placement.mirrors.name", names, "unique names")
        for m in self.mirrors:
            first = [p for p in self.mirrors if p.side == m.side][0]
            require(not (m.chain and m is first), f"placement.mirrors[{m.name}].chain", m.chain,
                    "false for the first mirror of its side (nothing to chain to)")
        ranges = []
        for r in self.shadowed_steps:
            holder = _Pair(r)
            _edges(holder, "v", "placement.shadowed_steps", int)
            ranges.append(holder.v)
        object.__setattr__(self, "shadowed_steps", tuple(ranges))
        require(self.method in PLACEMENT_METHODS, "placement.method", self.method,
                " or ".join(PLACEMENT_METHODS))
        object.__setattr__(self, "standoff_m", tuple(float(x) for x in np.atleast_1d(self.standoff_m)))
        require(len(self.standoff_m) >= 1 and all(x > 0 for x in self.standoff_m),
                "placement.standoff_m", list(self.standoff_m), "one or more values > 0 m")
        require(self.clearance_m >= 0, "placement.clearance_m", self.clearance_m, ">= 0 m")
        require(0 <= self.margin_steps <= 0.5, "placement.margin_steps", self.margin_steps,
                "0 .. 0.5 steps")


@dataclass(frozen=True)
class MirrorSpec:
    """Physical mirror parameters shared by all mirrors.

    Attributes
    ----------
    glass_height_m : float
        Height of the reflecting surface [m], centred on the scan plane.
    glass_thickness_m : float
        Glass thickness behind the reflecting surface [m] (CAD).
    hinge_z_m : float
        Height of the hinge axis relative to the scan plane [m] (negative: below). The
        paper's ``h``; a tilt error ``dbeta`` shifts the mirror in the scan plane by
        ``-hinge_z * tan(dbeta)``.
    lift_angle_rad : float
        Angle the lift motor turns a mirror to take it out of the beams [rad].
    """

    glass_height_m: float = 0.030
    glass_thickness_m: float = 0.002
    hinge_z_m: float = -0.025
    lift_angle_rad: float = 1.5707963267948966

    def __post_init__(self) -> None:
        require(self.glass_height_m > 0, "mirror.glass_height_m", self.glass_height_m, "> 0 m")
        require(self.glass_thickness_m > 0, "mirror.glass_thickness_m", self.glass_thickness_m,
                "> 0 m")
        require(abs(self.hinge_z_m) > self.glass_height_m / 2,
                "mirror.hinge_z_m", self.hinge_z_m,
                f"|hinge_z_m| > glass_height_m/2 = {self.glass_height_m / 2} (hinge outside the glass)")
        require(0 < self.lift_angle_rad <= np.pi, "mirror.lift_angle_rad", self.lift_angle_rad,
                "0 < angle <= pi")


@dataclass(frozen=True)
class NodSpec:
    """The nodding actuator's profile: a linear ramp between two pitch limits.

    Attributes
    ----------
    pitch_min_rad, pitch_max_rad : float
        Pitch limits [rad] (rotation about the sensor y axis; positive tips x down).
    rate_rad_s : float
        Nod speed [rad/s].
    pivot_m : tuple of float
        The nod axis passes through this point of the head frame [m].
    """

    pitch_min_rad: float = -0.35
    pitch_max_rad: float = 0.35
    rate_rad_s: float = 0.35
    pivot_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        require(-np.pi / 2 < self.pitch_min_rad < self.pitch_max_rad < np.pi / 2,
                "nod.pitch_min_rad/pitch_max_rad", (self.pitch_min_rad, self.pitch_max_rad),
                "-pi/2 < min < max < pi/2")
        require(self.rate_rad_s > 0, "nod.rate_rad_s", self.rate_rad_s, "> 0 rad/s")
        object.__setattr__(self, "pivot_m", tuple(float(x) for x in self.pivot_m))
        require(len(self.pivot_m) == 3, "nod.pivot_m", self.pivot_m, "3 numbers [m]")

    @property
    def sweep_period_s(self) -> float:
        """Time of one sweep from one limit to the other [s]."""
        return (self.pitch_max_rad - self.pitch_min_rad) / self.rate_rad_s

    def pitch_at(self, t: np.ndarray | float, t0: float = 0.0) -> np.ndarray:
        """Pitch [rad] of the triangle-wave ramp at times ``t`` [s], starting at the minimum."""
        T = self.sweep_period_s
        phase = np.mod(np.asarray(t, dtype=float) - t0, 2 * T)
        tri = np.where(phase < T, phase, 2 * T - phase)
        return self.pitch_min_rad + tri * self.rate_rad_s


@dataclass(frozen=True)
class DesignSpec:
    """A complete design file."""

    name: str
    lidar: str
    layout: LayoutSpec
    placement: PlacementSpec = field(default_factory=PlacementSpec)
    mirror: MirrorSpec = field(default_factory=MirrorSpec)
    nod: NodSpec = field(default_factory=NodSpec)
    description: str = ""
    reference: dict[str, Any] = field(default_factory=dict)
    sections: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # the name becomes an output folder (cad_out/<name>, out/report/<name>): never '..',
        # a separator or a control character, however the spec was made
        safe_name(self.name, "name")
        model = lidar_model(self.lidar)  # raises with the allowed names
        object.__setattr__(self, "lidar", model.name)
        D = self.layout.design_distance_m
        require(model.range_min_m < D <= model.range_max_m, "layout.design_distance_m", D,
                f"{model.range_min_m} < D <= {model.range_max_m} m for {model.name}")
        for x in self.placement.standoff_m:
            require(x < D, "placement.standoff_m", x, f"< design distance {D} m")
        for mp in self.placement.mirrors:
            require(mp.standoff_m < D, f"placement.mirrors[{mp.name}].standoff_m",
                    mp.standoff_m, f"< design distance {D} m")
        if not self.placement.chain and not self.placement.mirrors:
            m = self.layout.max_mirrors_per_side
            require(len(self.placement.standoff_m) == m, "placement.standoff_m",
                    list(self.placement.standoff_m), f"{m} values (one per mirror) when chain = false")

    @property
    def lidar_model(self) -> LidarModel:
        return lidar_model(self.lidar)

    def replace(self, **changes: Any) -> DesignSpec:
        """A copy with top-level fields or dotted section fields changed.

        ``spec.replace(**{"layout.design_distance_m": 3.0, "placement.method": "optimal"})``
        """
        top: dict[str, Any] = {}
        per_section: dict[str, dict[str, Any]] = {}
        for key, val in changes.items():
            if "." in key:
                sec, fld = key.split(".", 1)
                per_section.setdefault(sec, {})[fld] = val
            else:
                top[key] = val
        for sec, vals in per_section.items():
            old = getattr(self, sec)
            top[sec] = type(old)(**{**asdict(old), **vals})
        return DesignSpec(**{**{f.name: getattr(self, f.name) for f in fields(self)}, **top})

    def to_dict(self) -> dict[str, Any]:
        """Plain dict in the TOML layout (round-trips through :func:`design_from_dict`)."""
        out: dict[str, Any] = {"name": self.name}
        if self.description:
            out["description"] = self.description
        out["lidar"] = {"model": self.lidar}
        for sec in ("layout", "placement", "mirror", "nod"):
            d = asdict(getattr(self, sec))
            # empty optional tables/pairs are left out (TOML has no null, and they are the
            # defaults); nested tables (side windows, mirror plans) become arrays of tables
            out[sec] = {k: _plain(v) for k, v in d.items()
                        if not (isinstance(v, tuple) and len(v) == 0)}
        if self.reference:
            out["reference"] = self.reference
        out.update(self.sections)
        return out


def _plain(v: Any) -> Any:
    """Tuples to lists and nested dicts to plain dicts, recursively (for TOML output)."""
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items() if not (isinstance(x, tuple) and len(x) == 0)}
    return v


_SECTION_TYPES = {"layout": LayoutSpec, "placement": PlacementSpec, "mirror": MirrorSpec,
                  "nod": NodSpec}


#: Top-level keys a design file may have: those read here, the free-form [reference], and
#: the sections other modules own (:data:`OWNED_SECTIONS`, checked by their parsers when
#: the file is loaded). Anything else is refused with the nearest valid name.
_TOP_KEYS = ("name", "description", "lidar", "layout", "placement", "mirror", "nod", "reference")
OWNED_SECTIONS = ("tolerance", "calibration", "cad")

#: Physical bounds checked when a file is loaded (section -> field -> (lo, hi, unit); None:
#: that side is left to the dataclass). Beyond them the geometry breaks down silently
#: (e.g. a hinge 1e9 m away gives an all-NaN tolerance table) rather than with an error.
_LOAD_BOUNDS: dict[str, dict[str, tuple]] = {
    "layout": {"windows": (3, 21, "")},
    "placement": {"standoff_m": (None, 1.0, "m"), "clearance_m": (None, 0.5, "m")},
    "mirror": {"glass_height_m": (None, 0.5, "m"), "glass_thickness_m": (None, 0.05, "m"),
               "hinge_z_m": (-0.5, 0.5, "m")},
    "nod": {"rate_rad_s": (1e-3, 2 * np.pi, "rad/s"), "pivot_m": (-1.0, 1.0, "m")},
}


def _build(cls, table: Any, section: str, source: str | None = None):
    """``cls`` from a TOML table: keys, strict types and physical bounds checked first
    (:func:`nodlidar.validation.check_fields`)."""
    from .validation import check_fields

    if not isinstance(table, dict):
        raise DesignFileError(f"[{section}] must be a table, got {type(table).__name__}"
                              + (f" in {source}" if source else ""))
    return cls(**check_fields(cls, table, section, source, bounds=_LOAD_BOUNDS.get(section)))


def _check_owned_sections(spec: DesignSpec) -> None:
    """Parse the owned sections now, so a bad [tolerance]/[calibration]/[cad] value is
    refused on load by every command, not only by the one that reads it."""
    if "tolerance" in spec.sections:
        from .analysis.tolerance import tolerance_spec

        tolerance_spec(spec)
    if "calibration" in spec.sections:
        from .calibration.fit import calibration_config

        calibration_config(spec)
    if "cad" in spec.sections:
        from .cad.params import mount_params_from_spec

        mount_params_from_spec(spec)


def design_from_dict(data: dict[str, Any], source: str = "<dict>") -> DesignSpec:
    """Build and validate a :class:`DesignSpec` from a parsed TOML dict.

    Unknown top-level keys, sections and keys are refused with the nearest valid name;
    values are type-checked strictly (no boolean for a number, no string for a boolean,
    finite numbers, tuples of the right length) and bounded physically; the owned
    sections (:data:`OWNED_SECTIONS`) are parsed by their modules.
    """
    from .validation import check_keys, check_value, safe_name, suggest

    src = None if source == "<dict>" else source
    if not isinstance(data, dict):
        raise DesignFileError(f"{source}: a design must be a table, got {type(data).__name__}")
    data = dict(data)
    for req in ("name", "lidar", "layout"):
        if req not in data:
            near = suggest(req, [k for k in data if k not in _TOP_KEYS + OWNED_SECTIONS])
            raise DesignFileError(f"{source}: missing required '{req}'"
                                  + (" table" if req != "name" else " key")
                                  + (f"; did you mean [{near}]?" if near else ""))
    check_keys(data, _TOP_KEYS + OWNED_SECTIONS, "", src, sections=True)
    name = safe_name(check_value(data.pop("name"), str, "name", src))
    lidar = check_keys(data.pop("lidar"), ("model",), "lidar", src)
    if "model" not in lidar:
        raise DesignFileError(f"{source}: [lidar] needs 'model'")
    kw: dict[str, Any] = {"name": name, "lidar": check_value(lidar["model"], str, "lidar.model", src),
                          "description": check_value(data.pop("description", ""), str,
                                                     "description", src),
                          "reference": check_value(data.pop("reference", {}), dict, "reference",
                                                   src)}
    for sec, cls in _SECTION_TYPES.items():
        if sec in data:
            kw[sec] = _build(cls, data.pop(sec), sec, src)
    kw["sections"] = data
    spec = DesignSpec(**kw)
    _check_owned_sections(spec)
    return spec


def load_design(path: str | Path) -> DesignSpec:
    """Read a design TOML file; errors name the file and the offending field.

    The file must be a regular UTF-8 text file of sane size (a FIFO, a directory or a
    binary file is refused, not read; :func:`nodlidar.validation.read_toml`).
    """
    from .errors import UnknownKeyError
    from .validation import read_toml

    p = Path(path)
    data = read_toml(p, "design", error=DesignFileError)
    try:
        return design_from_dict(data, source=str(p))
    except UnknownKeyError as exc:
        if str(p) in str(exc):
            raise
        # an owned section's parser does not know the file: say where, before the hint
        head, sep, hint = str(exc).partition(";")
        raise UnknownKeyError(f"{head} in {p}{sep}{hint}", exc.field, exc.value,
                              exc.allowed) from None
    except ParameterError as exc:
        where = f" in {p}"
        allowed = exc.allowed if exc.allowed.endswith(where) else exc.allowed + where
        raise ParameterError(exc.field, exc.value, allowed) from None


def design_to_toml(spec: DesignSpec) -> str:
    """Serialise a spec to TOML text (written beside every output that it made)."""
    import tomli_w

    return tomli_w.dumps(spec.to_dict())
