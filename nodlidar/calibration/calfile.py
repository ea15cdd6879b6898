"""Calibration files (TOML): the fitted mirror perturbations the runtime applies.

Layout::

    id = "cal-3f2a9c0d1e4b"
    created = "2026-11-22T08:30:00+00:00"
    model = "exact"
    source = "sim: 3 walls"
    [design]
    name = "urg04lx-paper"
    hash = "0123456789abcdef"     # fit.design_hash: the geometric parameters
    [mirrors.L1]
    dalpha_rad = -0.043
    dbeta_rad = 0.05
    dd_m = 0.01
    sigma_dalpha_rad = 7e-5
    sigma_dbeta_rad = 3e-4
    sigma_dd_m = 1e-4
    [mirrors.L1.residuals]        # after calibration, over all walls
    rms_m = ...; max_abs_m = ...; within_band = ...; band_m = 0.0225; n = ...
    [mirrors.L1.residuals_before]
    ...
    ambiguous_steps = [594, 642, 722]   # beams whose mirror changes within 3 sigma: dropped
    problems = []                       # failed quality gates (only with calibrate --force)
    [lidar]                             # only when fitted: r_measured = (1 + scale) r + offset
    range_offset_m = 0.02
    range_scale = 0.01
    [covariance]                        # the joint fit's full covariance (SI units)
    parameters = ["L1.dalpha_rad", "L1.dbeta_rad", "L1.dd_m", ...]
    matrix = [[...], ...]

The runtime applies it as ``AssemblyModel.from_design(design, cal.perturbations, cal.id)``
and records ``.id`` with every cloud; ``cal.perturbations`` carries ``ambiguous_steps``
(:class:`CalibratedPerturbations`), which the assembly drops. A file made for another
design (different geometric hash) is refused. The lidar's range model, when fitted, is
carried the same way (``cal.perturbations.range_offset_m``/``range_scale``) and inverted by
the runtime assembly before projection.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import CalibrationError, DesignFileError
from ..geometry import Perturbation
from ..spec import DesignSpec
from .fit import CalibrationResult, design_hash

if TYPE_CHECKING:
    from ..solver import Design

__all__ = ["Calibration", "CalibratedPerturbations", "calibration_from_result",
           "write_calibration", "load_calibration", "read_calibration"]


class CalibratedPerturbations(dict):
    """Mirror name -> Perturbation, plus ``ambiguous_steps``: the lidar steps whose mirror
    assignment is uncertain under this calibration (the runtime assembly drops them), and
    the lidar's fitted range model ``r_measured = (1 + range_scale) r + range_offset_m``
    (zero when not fitted; the runtime assembly inverts it)."""

    ambiguous_steps: tuple[int, ...] = ()
    range_offset_m: float = 0.0
    range_scale: float = 0.0

    def __init__(self, perturbations: Mapping[str, Perturbation]
                 | Iterable[tuple[str, Perturbation]] = (), ambiguous_steps: Iterable[int] = (),
                 range_offset_m: float = 0.0, range_scale: float = 0.0):
        super().__init__(perturbations)
        self.ambiguous_steps = tuple(int(s) for s in ambiguous_steps)
        self.range_offset_m = float(range_offset_m)
        self.range_scale = float(range_scale)


@dataclass(frozen=True)
class Calibration:
    """A calibration as stored in a file.

    Attributes
    ----------
    id : str
        Identifier recorded with every cloud made with it.
    design_name, design_hash : str
        The design it belongs to.
    created : str
        ISO 8601 time (UTC).
    model : str
        Point model used by the fit ("exact" or "paper").
    perturbations : dict
        Mirror name -> Perturbation.
    sigma : dict
        Mirror name -> (sigma dalpha [rad], sigma dbeta [rad], sigma dd [m]).
    residuals, residuals_before : dict
        Mirror name -> residual statistics (``ResidualStats.to_dict``).
    source : str
        Where the data came from.
    ambiguous_steps : tuple of int
        Steps whose mirror changes within ``ambiguity_sigma`` of the fit (runtime drops them).
    problems : tuple of str
        Quality gates that failed (a file written with ``--force``).
    intrinsics : dict
        Fitted ``range_offset_m`` / ``range_scale`` (and sigmas), if any.
    parameter_names : tuple of str
    covariance : list of lists
        Full covariance of ``parameter_names`` (SI units).
    """

    id: str
    design_name: str
    design_hash: str
    created: str
    model: str
    perturbations: dict[str, Perturbation]
    sigma: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    residuals: dict[str, dict[str, float]] = field(default_factory=dict)
    residuals_before: dict[str, dict[str, float]] = field(default_factory=dict)
    source: str = ""
    ambiguous_steps: tuple[int, ...] = ()
    problems: tuple[str, ...] = ()
    intrinsics: dict[str, float] = field(default_factory=dict)
    parameter_names: tuple[str, ...] = ()
    covariance: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        # the runtime takes the mirrors and the beams to drop from one object
        object.__setattr__(self, "perturbations",
                           CalibratedPerturbations(self.perturbations, self.ambiguous_steps,
                                                   self.intrinsics.get("range_offset_m", 0.0),
                                                   self.intrinsics.get("range_scale", 0.0)))

    def to_dict(self) -> dict[str, Any]:
        mirrors: dict[str, Any] = {}
        for name, p in self.perturbations.items():
            m: dict[str, Any] = {"dalpha_rad": p.dalpha, "dbeta_rad": p.dbeta, "dd_m": p.dd}
            if name in self.sigma:
                s = self.sigma[name]
                m.update(sigma_dalpha_rad=s[0], sigma_dbeta_rad=s[1], sigma_dd_m=s[2])
            if name in self.residuals:
                m["residuals"] = dict(self.residuals[name])
            if name in self.residuals_before:
                m["residuals_before"] = dict(self.residuals_before[name])
            mirrors[name] = m
        out = {"id": self.id, "created": self.created, "model": self.model, "source": self.source,
               "ambiguous_steps": [int(s) for s in self.ambiguous_steps],
               "problems": list(self.problems),
               "design": {"name": self.design_name, "hash": self.design_hash}, "mirrors": mirrors}
        if self.intrinsics:
            out["lidar"] = dict(self.intrinsics)
        if self.parameter_names:
            out["covariance"] = {"parameters": list(self.parameter_names),
                                 "matrix": [[float(v) for v in row] for row in self.covariance]}
        return out


def calibration_from_result(result: CalibrationResult, *, source: str = "",
                            created: str | None = None) -> Calibration:
    """Wrap a fit result as a :class:`Calibration` (id = hash of design, time, parameters)."""
    created = created or datetime.now(UTC).replace(microsecond=0).isoformat()
    key = repr((result.design_hash, created, sorted((k, tuple(p.as_array())) for k, p in
                                                    result.perturbations.items())))
    cid = "cal-" + hashlib.sha256(key.encode()).hexdigest()[:12]
    return Calibration(
        id=cid, design_name=result.design_name, design_hash=result.design_hash, created=created,
        model=result.model, perturbations=result.perturbations,
        sigma={k: (float(m.sigma[0]), float(m.sigma[1]), float(m.sigma[2]))
               for k, m in result.mirrors.items()},
        residuals={k: m.after.to_dict() for k, m in result.mirrors.items()},
        residuals_before={k: m.before.to_dict() for k, m in result.mirrors.items()},
        source=source, ambiguous_steps=tuple(result.ambiguous_steps),
        problems=tuple(result.problems), intrinsics=dict(result.intrinsics),
        parameter_names=tuple(result.parameter_names),
        covariance=tuple(tuple(float(v) for v in row) for row in np.asarray(result.covariance)))


def write_calibration(path: str | Path, cal: Calibration | CalibrationResult, **kw: Any) -> Calibration:
    """Write a calibration TOML file; returns the :class:`Calibration` written."""
    import tomli_w

    if isinstance(cal, CalibrationResult):
        cal = calibration_from_result(cal, **kw)
    Path(path).write_text(tomli_w.dumps(cal.to_dict()))
    return cal


def _num(table: dict, key: str, where: str) -> float:
    v = table.get(key)
    if not isinstance(v, int | float) or isinstance(v, bool):
        raise DesignFileError(f"{where}: '{key}' must be a number, got {v!r}")
    return float(v)


def read_calibration(path: str | Path) -> Calibration:
    """Read a calibration file without checking which design it belongs to."""
    from ..validation import read_toml

    p = Path(path)
    data = read_toml(p, "calibration", error=DesignFileError)
    for key in ("id", "design", "mirrors"):
        if key not in data:
            raise DesignFileError(f"{p}: not a calibration file (missing '{key}')")
    des = data["design"]
    if not isinstance(des, dict) or not {"name", "hash"} <= set(des):
        raise DesignFileError(f"{p}: [design] needs 'name' and 'hash'")
    perts, sig, res, res0 = {}, {}, {}, {}
    for name, m in data["mirrors"].items():
        where = f"{p} [mirrors.{name}]"
        if not isinstance(m, dict):
            raise DesignFileError(f"{where} must be a table")
        perts[name] = Perturbation(_num(m, "dalpha_rad", where), _num(m, "dbeta_rad", where),
                                   _num(m, "dd_m", where))
        if "sigma_dalpha_rad" in m:
            sig[name] = (_num(m, "sigma_dalpha_rad", where), _num(m, "sigma_dbeta_rad", where),
                         _num(m, "sigma_dd_m", where))
        if "residuals" in m:
            res[name] = dict(m["residuals"])
        if "residuals_before" in m:
            res0[name] = dict(m["residuals_before"])
    amb = data.get("ambiguous_steps", [])
    if not isinstance(amb, list) or not all(isinstance(v, int) and not isinstance(v, bool)
                                            for v in amb):
        raise DesignFileError(f"{p}: 'ambiguous_steps' must be a list of integers (lidar steps)")
    lidar = data.get("lidar", {})
    if not isinstance(lidar, dict):
        raise DesignFileError(f"{p}: [lidar] must be a table")
    intr = {k: _num(lidar, k, f"{p} [lidar]") for k in lidar}
    cov = data.get("covariance", {})
    names, matrix = tuple(cov.get("parameters", ())), tuple(tuple(r) for r in cov.get("matrix", ()))
    if len(matrix) != len(names) or any(len(r) != len(names) for r in matrix):
        raise DesignFileError(f"{p}: [covariance] matrix must be {len(names)} x {len(names)} "
                              "(one row and column per parameter)")
    return Calibration(id=str(data["id"]), design_name=str(des["name"]), design_hash=str(des["hash"]),
                       created=str(data.get("created", "")), model=str(data.get("model", "exact")),
                       perturbations=perts, sigma=sig, residuals=res, residuals_before=res0,
                       source=str(data.get("source", "")), ambiguous_steps=tuple(amb),
                       problems=tuple(str(x) for x in data.get("problems", [])),
                       intrinsics=intr, parameter_names=names, covariance=matrix)


def load_calibration(path: str | Path, design: Design | DesignSpec) -> Calibration:
    """Read a calibration file and check it belongs to ``design`` (a Design or DesignSpec).

    Raises
    ------
    CalibrationError
        The file was made for a different design (other geometric parameters), or names
        mirrors the design does not have.
    DesignFileError
        Missing or malformed file.
    """
    cal = read_calibration(path)
    spec = design if isinstance(design, DesignSpec) else design.spec
    h = design_hash(spec)
    if cal.design_hash != h:
        raise CalibrationError(
            f"{path}: calibration {cal.id} was made for design '{cal.design_name}' "
            f"(hash {cal.design_hash}), not for '{spec.name}' (hash {h}); recalibrate this design")
    if hasattr(design, "mirrors"):
        names = {m.name for m in design.mirrors}
        extra = sorted(set(cal.perturbations) - names)
        if extra:
            raise CalibrationError(f"{path}: calibration names mirror(s) {', '.join(extra)} that "
                                   f"design '{spec.name}' does not have ({', '.join(sorted(names))})")
    return cal
