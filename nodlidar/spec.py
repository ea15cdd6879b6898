"""Design files: frozen, validated parameter dataclasses loaded from and written to TOML.

A design file (``design/*.toml``) describes one sensor build::

    name = "urg04lx-paper"
    [lidar]      model
    [layout]     design_distance_m, windows (odd k >= 3), mirrors_per_side
    [placement]  method ("anchor" | "optimal"), standoff_m, chain, clearance_m, margin_steps
    [mirror]     glass_height_m, glass_thickness_m, hinge_z_m, lift_angle_rad
    [nod]        pitch_min_rad, pitch_max_rad, rate_rad_s, pivot_m
    [reference]  optional published numbers to compare against (free-form)

Other top-level tables (``[cad]``, ``[tolerance]``, ...) are kept verbatim in
:attr:`DesignSpec.sections` for the modules that own them. Unknown keys inside the
tables above are errors, so a typo never silently falls back to a default.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DesignFileError, ParameterError, require
from .lidar import LidarModel, lidar_model

__all__ = [
    "LayoutSpec",
    "PlacementSpec",
    "MirrorSpec",
    "NodSpec",
    "DesignSpec",
    "load_design",
    "design_from_dict",
    "design_to_toml",
]

PLACEMENT_METHODS = ("anchor", "optimal")


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
    """

    design_distance_m: float
    windows: int = 3
    mirrors_per_side: int = 2

    def __post_init__(self) -> None:
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
    """

    method: str = "anchor"
    standoff_m: tuple[float, ...] = (0.02,)
    chain: bool = True
    clearance_m: float = 0.005
    margin_steps: float = 0.5

    def __post_init__(self) -> None:
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
        require(isinstance(self.name, str) and self.name.strip() != "" and "/" not in self.name,
                "name", self.name, "a non-empty name without '/'")
        model = lidar_model(self.lidar)  # raises with the allowed names
        object.__setattr__(self, "lidar", model.name)
        D = self.layout.design_distance_m
        require(model.range_min_m < D <= model.range_max_m, "layout.design_distance_m", D,
                f"{model.range_min_m} < D <= {model.range_max_m} m for {model.name}")
        for x in self.placement.standoff_m:
            require(x < D, "placement.standoff_m", x, f"< design distance {D} m")
        if not self.placement.chain:
            m = self.layout.mirrors_per_side
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
            out[sec] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}
        if self.reference:
            out["reference"] = self.reference
        out.update(self.sections)
        return out


_SECTION_TYPES = {"layout": LayoutSpec, "placement": PlacementSpec, "mirror": MirrorSpec,
                  "nod": NodSpec}


def _build(cls, table: Any, section: str):
    if not isinstance(table, dict):
        raise DesignFileError(f"[{section}] must be a table, got {type(table).__name__}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise DesignFileError(
            f"[{section}] has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(known))}"
        )
    try:
        return cls(**table)
    except TypeError as exc:  # missing required field
        missing = [f.name for f in fields(cls)
                   if f.name not in table and f.default is f.default_factory]  # noqa: E721
        raise DesignFileError(
            f"[{section}] is incomplete: missing {', '.join(missing) or exc}"
        ) from None


def design_from_dict(data: dict[str, Any], source: str = "<dict>") -> DesignSpec:
    """Build and validate a :class:`DesignSpec` from a parsed TOML dict."""
    data = dict(data)
    for req in ("name", "lidar", "layout"):
        if req not in data:
            raise DesignFileError(f"{source}: missing required '{req}'"
                                  + (" table" if req != "name" else " key"))
    lidar = data.pop("lidar")
    if not isinstance(lidar, dict) or "model" not in lidar:
        raise DesignFileError(f"{source}: [lidar] needs 'model'")
    extra_lidar = sorted(set(lidar) - {"model"})
    if extra_lidar:
        raise DesignFileError(f"{source}: [lidar] has unknown key(s) {', '.join(extra_lidar)}; "
                              "allowed: model")
    kw: dict[str, Any] = {"name": data.pop("name"), "lidar": lidar["model"],
                          "description": data.pop("description", ""),
                          "reference": data.pop("reference", {})}
    for sec, cls in _SECTION_TYPES.items():
        if sec in data:
            try:
                kw[sec] = _build(cls, data.pop(sec), sec)
            except DesignFileError as exc:
                raise DesignFileError(f"{source}: {exc}") from None
    kw["sections"] = data
    return DesignSpec(**kw)


def load_design(path: str | Path) -> DesignSpec:
    """Read a design TOML file; errors name the file and the offending field."""
    p = Path(path)
    if not p.is_file():
        raise DesignFileError(f"design file not found: {p}")
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise DesignFileError(f"{p}: malformed TOML: {exc}") from None
    try:
        return design_from_dict(data, source=str(p))
    except ParameterError as exc:
        raise ParameterError(exc.field, exc.value, exc.allowed + f" (in {p})") from None


def design_to_toml(spec: DesignSpec) -> str:
    """Serialise a spec to TOML text (written beside every output that it made)."""
    import tomli_w

    return tomli_w.dumps(spec.to_dict())
