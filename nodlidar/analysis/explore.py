"""The design space: solve and verify every combination of swept design-file parameters.

``explore(spec, [Sweep.parse("layout.design_distance_m=0.5:5:0.25"), ...])`` evaluates
the Cartesian product of the sweeps (first sweep slowest), one row per design:

* ``feasible`` and the ``reason`` when not (the solver's refusal, or the blocked beams);
* the interleave error (traced bearing minus the slot target) over every reflected beam
  that arrives unblocked: RMS and max at D and at 1, 2 and 6 m [deg];
* ``density_gain``: unblocked beams landing in the front window at D per direct beam;
* ``blocked_beams``: beams that hit the wrong mirror or whose path is blocked;
* ``footprint_mm``: the xy bounding box of the glass (with its thickness behind the face)
  and the lidar housing, grown by the ``[cad]`` base margin on every side - the plate the
  mounts need, without building the CAD (which takes seconds a design);
* ``glass_area_cm2``: the glass to order (sum of length x height).

Rows are computed in chunks, in this process or on Dask (a local cluster or an existing
scheduler, as :func:`nodlidar.analysis.tolerance.monte_carlo` does); they are put back in
sweep order, and nothing is random, so every way of running gives the same table.
:func:`pareto_front` marks the rows no other feasible row beats on every objective.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import NodlidarError, ParameterError, require
from ..spec import DesignSpec

__all__ = ["Sweep", "ExploreResult", "explore", "evaluate_design", "pareto_front",
           "load_exploration", "report_section", "nan_to_none", "EXPLORE_RANGES_M", "OBJECTIVES",
           "MAX_DESIGNS"]

#: Arc radii [m] besides D at which the interleave error is tabulated.
EXPLORE_RANGES_M = (1.0, 2.0, 6.0)
#: Pareto objectives: (column, +1 minimise / -1 maximise).
OBJECTIVES = (("rms_error_deg", 1), ("footprint_area_mm2", 1), ("glass_area_cm2", 1),
              ("density_gain", -1))
#: Largest sweep accepted (the product of all sweeps).
MAX_DESIGNS = 100_000
#: Designs per chunk (one Dask task; one progress step).
CHUNK = 16
#: Sweeps larger than this go to a local Dask cluster unless told otherwise.
IN_PROCESS_MAX = 2000

_SECTIONS = ("layout", "placement", "mirror", "nod")


@dataclass(frozen=True)
class Sweep:
    """One swept parameter: a dotted design-file key and its values (in file units)."""

    key: str
    values: tuple[Any, ...]

    @classmethod
    def parse(cls, text: str, spec: DesignSpec | None = None) -> Sweep:
        """``"key=lo:hi:step"`` (both ends included), ``"key=a,b,c"`` or ``"key=a"``.

        With ``spec`` the key is checked against the design file's fields and the values
        take the field's type (integers stay integers).
        """
        key, sep, rhs = str(text).partition("=")
        key, rhs = key.strip(), rhs.strip()
        require(bool(sep and key and rhs), "--sweep", text,
                "KEY=LO:HI:STEP or KEY=A,B,C (e.g. layout.design_distance_m=0.5:5:0.25)")
        kind = _field_kind(key, spec) if spec is not None else float
        try:
            if ":" in rhs:
                parts = [float(p) for p in rhs.split(":")]
                require(len(parts) == 3, "--sweep", text, "LO:HI:STEP with three numbers")
                lo, hi, step = parts
                require(step > 0 and hi >= lo and all(map(math.isfinite, parts)), "--sweep", text,
                        "finite LO <= HI and STEP > 0")
                n = int(math.floor((hi - lo) / step + 1e-9)) + 1
                require(n <= MAX_DESIGNS, "--sweep", text, f"at most {MAX_DESIGNS} values")
                # round away the float drift of lo + i*step (0.5 + 3*0.1 = 0.8000000000000002)
                vals = [round(lo + i * step, 12) for i in range(n)]
            else:
                vals = [float(p) for p in rhs.split(",")]
        except ValueError:
            raise ParameterError("--sweep", text, "numbers: KEY=LO:HI:STEP or KEY=A,B,C") from None
        require(all(map(math.isfinite, vals)), "--sweep", text, "finite numbers")
        if kind is int:
            require(all(float(v).is_integer() for v in vals), "--sweep", text,
                    f"integers for {key}")
            vals = [int(v) for v in vals]
        return cls(key=key, values=tuple(vals))


def _field_kind(key: str, spec: DesignSpec) -> type:
    """The scalar type a swept key takes, refusing keys the design file does not have."""
    from ..validation import suggest

    sec, _, name = key.partition(".")
    allowed = [f"{s}.{f.name}" for s in _SECTIONS for f in fields(getattr(spec, s))
               if isinstance(getattr(getattr(spec, s), f.name), (int, float))
               and not isinstance(getattr(getattr(spec, s), f.name), bool)
               or (s, f.name) == ("placement", "standoff_m")]
    if key not in allowed:
        hint = suggest(key, allowed)
        raise ParameterError("--sweep", key, (f"did you mean {hint}? " if hint else "")
                             + "a numeric design-file field: " + ", ".join(allowed))
    if key == "placement.standoff_m":
        return float
    return int if isinstance(getattr(getattr(spec, sec), name), int) else float


def _apply(spec: DesignSpec, changes: dict[str, Any]) -> DesignSpec:
    """``spec`` with the swept values; a swept standoff sets every entry of the list."""
    ch = dict(changes)
    if "placement.standoff_m" in ch:
        n = len(spec.placement.standoff_m)
        ch["placement.standoff_m"] = (float(ch["placement.standoff_m"]),) * n
    return spec.replace(**ch)


def _footprint(design, margin_mm: float) -> tuple[float, float]:
    """Width (x) and depth (y) [mm] of the glass + housing envelope plus the base margin."""
    lid = design.lidar
    h = lid.housing_half_width_m
    pts = [np.array([[-h, -h], [h, h]])]
    t = design.spec.mirror.glass_thickness_m
    for m in design.mirrors:
        p = m.patch
        ends = p.point(np.array([p.s_min, p.s_max]))[:, :2]
        n_out = -p.normal_[:2] if p.origin_ @ p.normal_ < 0 else p.normal_[:2]
        pts.append(np.vstack([ends, ends + t * n_out]))
    allp = np.vstack(pts)
    size = allp.max(0) - allp.min(0)
    return float(size[0] * 1e3 + 2 * margin_mm), float(size[1] * 1e3 + 2 * margin_mm)


def evaluate_design(spec: DesignSpec) -> dict[str, Any]:
    """Solve and trace one design; the row of :func:`explore` (without the swept values)."""
    from ..geometry import arc_point, bearing_of, directions_from_bearings, wrap_angle
    from ..solver import solve
    from ..verify import trace_beams, verify

    row: dict[str, Any] = {"feasible": False, "reason": "", "mirrors": 0,
                           "rms_error_deg": math.nan, "max_error_deg": math.nan}
    for r in EXPLORE_RANGES_M:
        row[f"rms_error_{r:g}m_deg"] = math.nan
        row[f"max_error_{r:g}m_deg"] = math.nan
    row.update({"density_gain": math.nan, "blocked_beams": -1, "footprint_w_mm": math.nan,
                "footprint_d_mm": math.nan, "footprint_area_mm2": math.nan,
                "glass_area_cm2": math.nan})
    try:
        design = solve(spec, check=False)
    except NodlidarError as exc:  # refused before the trace (turn, clearance, slots...)
        row["reason"] = str(exc)
        return row
    v = verify(design)
    bad = v.unexpected_blocked()
    row["mirrors"] = len(design.mirrors)
    row["blocked_beams"] = int(np.count_nonzero(v.bad))
    row["feasible"] = not bad.any()
    if bad.any():
        row["reason"] = f"{int(bad.sum())} beams blocked: {v.describe_blocked(bad)}"
    ok = (v.expected >= 0) & ~v.bad
    e = np.degrees(np.abs(v.error[ok]))
    row["rms_error_deg"] = float(np.sqrt(np.mean(e**2))) if e.size else math.nan
    row["max_error_deg"] = float(e.max()) if e.size else math.nan
    lid = design.lidar
    th = lid.bearing_from_step(lid.steps)
    dirs = directions_from_bearings(th)
    hit, t, out, _ = trace_beams(design.patches(), dirs, lid.range_max_m, lid.housing_radius_m)
    start = np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
    for r in EXPLORE_RANGES_M:
        with np.errstate(invalid="ignore"):
            b = bearing_of(arc_point(start[ok], out[ok], r))
        er = np.degrees(np.abs(wrap_angle(b - design.target_bearing[ok])))
        er = er[np.isfinite(er)]  # an arc nearer than the mirror is never crossed
        row[f"rms_error_{r:g}m_deg"] = float(np.sqrt(np.mean(er**2))) if er.size else math.nan
        row[f"max_error_{r:g}m_deg"] = float(er.max()) if er.size else math.nan
    row["density_gain"] = v.density_gain()
    margin = float(spec.sections.get("cad", {}).get("base_margin_mm", 10.0))
    w, d = _footprint(design, margin)
    row.update({"footprint_w_mm": w, "footprint_d_mm": d, "footprint_area_mm2": w * d,
                "glass_area_cm2": float(sum(m.patch.length * m.patch.height
                                            for m in design.mirrors) * 1e4)})
    return row


def _run_chunk(spec_dict: dict[str, Any], combos: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows of one chunk (a module-level function, so Dask can ship it)."""
    from ..spec import design_from_dict

    base = design_from_dict(spec_dict)
    rows = []
    for ch in combos:
        try:
            spec = _apply(base, ch)
        except NodlidarError as exc:  # a swept value the design file refuses
            rows.append({**ch, "feasible": False, "reason": str(exc)})
            continue
        rows.append({**ch, **evaluate_design(spec)})
    return rows


def pareto_front(rows: list[dict[str, Any]],
                 objectives: Sequence[tuple[str, int]] = OBJECTIVES) -> np.ndarray:
    """``(n,) bool``: feasible rows that no other feasible row dominates.

    A row dominates another if it is at least as good on every objective and better on
    one (``objectives``: (column, +1 minimise | -1 maximise)).
    """
    n = len(rows)
    feas = np.array([bool(r.get("feasible")) for r in rows], bool)
    if not feas.any():
        return np.zeros(n, bool)
    F = np.array([[s * float(r.get(c, math.nan)) for c, s in objectives] for r in rows])
    feas &= np.all(np.isfinite(F), axis=1)
    idx = np.nonzero(feas)[0]
    G = F[idx]
    # pairwise: j dominates i  <=>  all(G[j] <= G[i]) and any(G[j] < G[i])
    le = np.all(G[:, None, :] <= G[None, :, :], axis=2)
    lt = np.any(G[:, None, :] < G[None, :, :], axis=2)
    dominated = np.any(le & lt, axis=0)
    out = np.zeros(n, bool)
    out[idx[~dominated]] = True
    return out


@dataclass(frozen=True, eq=False)
class ExploreResult:
    """The table of an exploration (rows in sweep order) and how it was made."""

    design_name: str
    sweeps: tuple[Sweep, ...]
    rows: list[dict[str, Any]]
    base: dict[str, Any] = field(default_factory=dict)

    @property
    def n_designs(self) -> int:
        return len(self.rows)

    @property
    def n_feasible(self) -> int:
        return sum(bool(r["feasible"]) for r in self.rows)

    @property
    def columns(self) -> list[str]:
        keys = [s.key for s in self.sweeps]
        rest: list[str] = []
        for r in self.rows:
            for k in r:
                if k not in keys and k not in rest:
                    rest.append(k)
        return keys + rest

    def to_dict(self) -> dict[str, Any]:
        return {"design": self.design_name, "n_designs": self.n_designs,
                "n_feasible": self.n_feasible,
                "sweeps": [{"key": s.key, "values": list(s.values)} for s in self.sweeps],
                "objectives": [{"column": c, "sense": "min" if s > 0 else "max"}
                               for c, s in OBJECTIVES],
                "ranges_m": list(EXPLORE_RANGES_M), "base": self.base, "rows": self.rows}

    def write_json(self, path: str | Path) -> Path:
        p = Path(path)
        # NaN is not JSON: missing metrics of refused designs are written as null
        p.write_text(json.dumps(nan_to_none(self.to_dict()), indent=1))
        return p

    def write_csv(self, path: str | Path) -> Path:
        p = Path(path)
        cols = self.columns
        with p.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
            w.writeheader()
            for r in self.rows:
                w.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v)
                            for k, v in r.items()})
        return p

    def figures(self) -> list[tuple[str, str, Any]]:
        """``(stem, caption, matplotlib figure)`` of the Pareto plots (matplotlib lazily)."""
        import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

        rows = self.rows
        feas = np.array([bool(r["feasible"]) for r in rows])
        front = np.array([bool(r.get("pareto")) for r in rows])

        def col(c):
            return np.array([float(r.get(c, math.nan)) for r in rows])

        out = []
        for stem, (xc, xl), (yc, yl) in (
                ("pareto_footprint", ("footprint_area_mm2", "mount footprint [cm^2]"),
                 ("rms_error_deg", "RMS interleave error at D [deg]")),
                ("pareto_glass", ("glass_area_cm2", "glass area [cm^2]"),
                 ("rms_error_deg", "RMS interleave error at D [deg]")),
                ("pareto_density", ("density_gain", "density gain in the front window"),
                 ("rms_error_deg", "RMS interleave error at D [deg]"))):
            x, y, c = col(xc), col(yc), col("density_gain")
            if xc == "footprint_area_mm2":
                x = x / 100.0
            fig, ax = plt.subplots(figsize=(6.4, 4.2))
            sc = ax.scatter(x[feas], y[feas], c=c[feas], s=14, cmap="viridis", label="feasible")
            ax.scatter(x[front], y[front], s=46, facecolors="none", edgecolors="red",
                       label="Pareto front")
            if (~feas).any():
                ax.scatter(x[~feas], y[~feas], marker="x", s=12, color="0.6", label="refused")
            fig.colorbar(sc, ax=ax, label="density gain")
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            ax.legend(fontsize=8)
            ax.set_title(f"{self.design_name}: {self.n_feasible} of {self.n_designs} feasible")
            fig.tight_layout()
            out.append((stem, f"{yl} against {xl}; red rings: the Pareto front "
                              "(RMS error, footprint and glass area down, density up).", fig))
        return out


def nan_to_none(x: Any) -> Any:
    """``x`` with every float NaN, also inside dicts and lists, replaced by ``None`` (JSON has
    no NaN: strict readers refuse it)."""
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, dict):
        return {k: nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [nan_to_none(v) for v in x]
    return x


def _none_to_nan(x: Any) -> Any:
    if x is None:
        return math.nan
    if isinstance(x, dict):
        return {k: (v if k == "reason" else _none_to_nan(v)) for k, v in x.items()}
    if isinstance(x, list):
        return [_none_to_nan(v) for v in x]
    return x


def load_exploration(path: str | Path) -> ExploreResult:
    """Read back what :meth:`ExploreResult.write_json` wrote (``nodlidar report --explore``)."""
    p = Path(path)
    if not p.is_file():
        raise ParameterError("--explore", str(path), "an explore.json written by nodlidar explore")
    try:
        data = json.loads(p.read_text())
        sweeps = tuple(Sweep(s["key"], tuple(s["values"])) for s in data["sweeps"])
        rows = [_none_to_nan(r) for r in data["rows"]]
        return ExploreResult(design_name=str(data["design"]), sweeps=sweeps, rows=rows,
                             base=data.get("base", {}))
    except (ValueError, KeyError, TypeError) as exc:
        raise ParameterError("--explore", str(path),
                             f"an explore.json written by nodlidar explore ({exc})") from None


def explore(spec: DesignSpec, sweeps: list[Sweep] | tuple[Sweep, ...], *,
            workers: int | None = None, scheduler: str | None = None, client: Any = None,
            processes: bool = True, chunk: int = CHUNK,
            progress: Callable[[int, int], None] | None = None) -> ExploreResult:
    """Evaluate every combination of ``sweeps`` on ``spec``.

    Parameters
    ----------
    spec : DesignSpec
        The base design; each row changes only the swept keys.
    sweeps : list of Sweep
        Cartesian product, the first sweep varying slowest.
    workers : int, optional
        0: in this process; n >= 1: a local Dask cluster of n workers. Default: in
        process up to :data:`IN_PROCESS_MAX` designs, else a local cluster.
    scheduler, client, processes :
        As for :func:`nodlidar.analysis.tolerance.monte_carlo` (its cluster helpers).
    chunk : int
        Designs per task.
    progress : callable, optional
        ``progress(done_designs, total_designs)`` after each chunk.

    Returns
    -------
    ExploreResult
        Rows in sweep order with a ``pareto`` column; identical however it was run.
    """
    require(len(sweeps) >= 1, "--sweep", [], "at least one sweep")
    keys = [s.key for s in sweeps]
    require(len(set(keys)) == len(keys), "--sweep", keys, "each key once")
    n = math.prod(len(s.values) for s in sweeps)
    require(n <= MAX_DESIGNS, "--sweep", n, f"at most {MAX_DESIGNS} designs in all")
    require(isinstance(chunk, int) and chunk >= 1, "chunk", chunk, "an integer >= 1")
    combos = [dict(zip(keys, vals, strict=True))
              for vals in itertools.product(*(s.values for s in sweeps))]
    chunks = [combos[i: i + chunk] for i in range(0, n, chunk)]
    base = spec.to_dict()
    results: list[list[dict[str, Any]] | None] = [None] * len(chunks)
    use_dask = client is not None or scheduler is not None or (
        workers is not None and workers > 0) or (workers is None and n > IN_PROCESS_MAX)
    done = 0
    if not use_dask:
        for i, c in enumerate(chunks):
            results[i] = _run_chunk(base, c)
            done += len(c)
            if progress:
                progress(done, n)
    else:
        for i, res in _dask_map(base, chunks, workers=workers, scheduler=scheduler,
                                client=client, processes=processes):
            results[i] = res
            done += len(chunks[i])
            if progress:
                progress(done, n)
    rows = [r for res in results for r in res]  # type: ignore[union-attr]
    for r, p in zip(rows, pareto_front(rows), strict=True):
        r["pareto"] = bool(p)
    return ExploreResult(design_name=spec.name, sweeps=tuple(sweeps), rows=rows, base=base)


def _dask_map(base, chunks, *, workers, scheduler, client, processes):
    """Yield ``(chunk index, rows)`` as chunks finish (the tolerance module's cluster way)."""
    from .tolerance import dask_map

    yield from dask_map(_run_chunk, base, [(c,) for c in chunks], workers=workers,
                        scheduler=scheduler, client=client, processes=processes)


def report_section(result: ExploreResult, doc: Any, put: Callable[[str, str, Any], None]) -> dict:
    """Write the design-space section into a report (``doc``: its Markdown/HTML builder,
    ``put(stem, caption, fig)``: its figure writer). Returns the JSON summary."""
    doc.heading("Design space")
    doc.para(f"{result.n_designs} designs around {result.design_name} "
             f"({', '.join(f'{s.key} x {len(s.values)}' for s in result.sweeps)}), each solved "
             f"and ray traced; {result.n_feasible} feasible. Errors are the traced bearing minus "
             "the interleave target over every unblocked reflected beam; the footprint is the "
             "glass and lidar envelope plus the base margin; the Pareto front minimises RMS "
             "error at D, footprint and glass area and maximises the density gain.")
    for stem, cap, fig in result.figures():
        put(stem, cap, fig)
    front = [r for r in result.rows if r.get("pareto")]
    front.sort(key=lambda r: r["rms_error_deg"])
    keys = [s.key for s in result.sweeps]
    doc.table(keys + ["RMS at D [deg]", "max at D [deg]", "RMS at 6 m [deg]", "density gain",
                      "footprint [mm]", "glass [cm^2]"],
              [[r[k] for k in keys] + [r["rms_error_deg"], r["max_error_deg"],
                                       r.get("rms_error_6m_deg", math.nan), r["density_gain"],
                                       f"{r['footprint_w_mm']:.0f} x {r['footprint_d_mm']:.0f}",
                                       r["glass_area_cm2"]] for r in front[:40]])
    if len(front) > 40:
        doc.para(f"({len(front) - 40} more Pareto designs in the exploration's CSV/JSON.)")
    return {"n_designs": result.n_designs, "n_feasible": result.n_feasible,
            "sweeps": [{"key": s.key, "values": list(s.values)} for s in result.sweeps],
            "pareto": nan_to_none(front)}
