"""The design report: one self-contained HTML file and a Markdown version.

:func:`compute_report` runs every analysis (solve, verify, drift, interleave, density,
tolerance Monte Carlo, sensitivities, the comparison design) and returns a
:class:`ReportData`; :func:`write_report` renders it. The HTML embeds every figure as a
base64 PNG; the Markdown references PNG files written beside it (``figures/``). The
resolved design TOML is written next to both and quoted in them.
"""

from __future__ import annotations

import base64
import html
import io
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .drift import beam_density, bearing_drift, interleave
from .tolerance import monte_carlo, sensitivities, tolerance_spec

if TYPE_CHECKING:
    from ..solver import Design
    from ..spec import DesignSpec
    from .drift import DensityResult, DriftResult, InterleaveResult
    from .tolerance import SensitivityResult, ToleranceResult

__all__ = ["ReportData", "ReportPaths", "compute_report", "write_report", "build_report",
           "default_out_dir"]


@dataclass(frozen=True, eq=False)
class ReportData:
    """Everything a report shows (results objects, no rendering)."""

    spec: DesignSpec
    design: Design
    other: Design | None
    other_method: str
    mirrors: list[dict[str, Any]]
    other_mirrors: list[dict[str, Any]]
    paper: list[dict[str, Any]]
    verification: dict[str, Any]
    drift: DriftResult
    interleave: InterleaveResult
    density: DensityResult
    tolerance: ToleranceResult
    sensitivity: SensitivityResult
    other_error: str | None = None
    exploration: Any = None  # an analysis.explore.ExploreResult: the design-space section


@dataclass(frozen=True)
class ReportPaths:
    """Files written by :func:`write_report`."""

    html: Path
    markdown: Path
    toml: Path
    json: Path
    figures: list[Path] = field(default_factory=list)


def default_out_dir(spec: DesignSpec) -> Path:
    """``out/report/<design name>/`` (relative to the working directory)."""
    return Path("out") / "report" / spec.name


def compute_report(spec: DesignSpec, *, samples: int | None = None, seed: int | None = None,
                   workers: int | None = None, scheduler: str | None = None,
                   progress: Callable[[int, int], None] | None = None,
                   exploration: Any = None) -> ReportData:
    """Solve ``spec`` and run every analysis the report shows.

    ``samples``/``seed`` override the ``[tolerance]`` table; ``workers``/``scheduler``
    are passed to :func:`~nodlidar.analysis.tolerance.monte_carlo`.
    """
    from ..designio import mirror_table, paper_comparison
    from ..errors import InfeasibleDesignError
    from ..solver import solve
    from ..verify import verify

    design = solve(spec)
    other_method = "optimal" if spec.placement.method != "optimal" else "anchor"
    other, other_error = None, None
    try:
        other = solve(spec.replace(**{"placement.method": other_method}))
    except InfeasibleDesignError as exc:  # still write the report, say why
        other_error = str(exc)
    v = verify(design)
    verification = {"n_blocked": v.n_blocked, "mirrors": v.summary()}
    il = interleave(design, (0.4, 1.0, 2.0, 6.0))
    tol = tolerance_spec(spec)
    return ReportData(
        spec=spec, design=design, other=other, other_method=other_method,
        mirrors=mirror_table(design), other_mirrors=mirror_table(other) if other else [],
        paper=paper_comparison(design), verification=verification,
        drift=bearing_drift(design), interleave=il, density=beam_density(il),
        tolerance=monte_carlo(design, tol, samples=samples, seed=seed, workers=workers,
                              scheduler=scheduler, progress=progress),
        sensitivity=sensitivities(design), other_error=other_error, exploration=exploration)


# ---------------------------------------------------------------------------------------
# rendering helpers


def _figures(data: ReportData) -> list[tuple[str, str, Any]]:
    """``(file stem, caption, figure)`` for every figure of the report."""
    from . import plots

    d = data.design.design_distance_m
    return [
        ("bearing", "Actual bearing of every reflected beam on arcs of radius 0.4-6 m, all "
                    "mirrors (paper Figs 6a/7a; exact trace, eq. 1 agrees to "
                    f"{data.drift.max_closed_vs_trace:.1e} rad).", plots.plot_bearing(data.drift)),
        ("separation", "Angular separation of consecutive reflected beams in native steps "
                       "(paper Figs 6b/7b): it tends to one step as the range grows.",
         plots.plot_separation(data.drift)),
        ("drift_vs_range", f"Drift from the interleave target set for D = {d:g} m, vs range.",
         plots.plot_drift_vs_range(data.drift)),
        ("interleave", "Top view: where direct and reflected beams land (paper Fig. 2b).",
         plots.plot_interleave(data.interleave)),
        ("interleave_strip", "Close-up of the interleave around the front direction.",
         plots.plot_interleave_strip(data.interleave)),
        ("density", "Beam density across the front window with and without mirrors.",
         plots.plot_density(data.density)),
        ("tolerance_hist", f"Largest bearing error per mirror at R = {d:g} m over sampled "
                           "builds.", plots.plot_tolerance_hist(data.tolerance, d)),
        ("tolerance_percentiles", "Percentiles of the largest bearing error vs range.",
         plots.plot_tolerance_percentiles(data.tolerance)),
        ("sensitivities", "Sensitivity of the bearing at D to each mounting parameter.",
         plots.plot_sensitivities(data.sensitivity)),
    ]


def _png(fig) -> bytes:
    import matplotlib.pyplot as plt  # noqa: TID251 (lazy, inside a plot function)

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool | np.bool_):
        return str(bool(v))
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        if not np.isfinite(v):
            return "-"
        return f"{v:.{digits}g}"
    if isinstance(v, list | tuple):
        return ", ".join(_fmt(x, digits) for x in v)
    return str(v)


def _md_inline(text: str) -> str:
    """``text`` as one line of Markdown inline text: backslashes escaped (so a trailing one
    cannot escape what follows) and line breaks folded to spaces."""
    return " ".join(str(text).replace("\\", "\\\\").split("\n"))


def _md_cell(text: str) -> str:
    """``text`` safe inside a GFM table cell: a ``|`` would end the cell (and a header cell
    with one makes the whole table fail to render), a line break would end the row."""
    return _md_inline(text).replace("|", "\\|")


class _Doc:
    """Builds the HTML and the Markdown side by side."""

    def __init__(self) -> None:
        self.h: list[str] = []
        self.m: list[str] = []

    def heading(self, text: str, level: int = 2) -> None:
        self.h.append(f"<h{level}>{html.escape(text)}</h{level}>")
        self.m.append(f"\n{'#' * level} {text}\n")

    def para(self, text: str) -> None:
        self.h.append(f"<p>{html.escape(text)}</p>")
        self.m.append(f"{text}\n")

    def table(self, headers: list[str], rows: list[list[Any]], digits: int = 4) -> None:
        cells = [[_fmt(c, digits) for c in r] for r in rows]
        self.h.append("<table><thead><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in headers)
                      + "</tr></thead><tbody>"
                      + "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>"
                                for r in cells) + "</tbody></table>")
        self.m.append("| " + " | ".join(_md_cell(h) for h in headers) + " |")
        self.m.append("|" + "|".join("---" for _ in headers) + "|")
        for r in cells:
            self.m.append("| " + " | ".join(_md_cell(c) for c in r) + " |")
        self.m.append("")

    def figure(self, png: bytes, rel_path: str, caption: str) -> None:
        b64 = base64.b64encode(png).decode("ascii")
        self.h.append(f'<figure><img src="data:image/png;base64,{b64}" alt="{html.escape(caption)}">'
                      f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        alt = caption.replace("\\", "\\\\").replace("[", "\\[").replace("]", "\\]")
        self.m.append(f"![{alt}]({rel_path})\n\n*{_md_inline(caption)}*\n")

    def code(self, text: str, lang: str = "toml") -> None:
        self.h.append(f"<pre><code>{html.escape(text)}</code></pre>")
        self.m.append(f"```{lang}\n{text.rstrip()}\n```\n")


_CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;
color:#222}table{border-collapse:collapse;margin:0.5em 0 1.5em;font-size:0.85em}
th,td{border:1px solid #ccc;padding:2px 6px;text-align:right}th{background:#f2f2f2}
figure{margin:1em 0}img{max-width:100%}figcaption{font-size:0.9em;color:#555}
pre{background:#f7f7f7;padding:0.8em;overflow-x:auto;font-size:0.85em}"""


def _mirror_rows(rows: list[dict[str, Any]]) -> list[list[Any]]:
    return [[r["name"], f"{r['steps'][0]}..{r['steps'][1]}", r["beams"], r["beam_span_m"] * 100,
             r["length_m"] * 100, r["phi_deg"], r["standoff_m"] * 1e3, r["oa_m"] * 1e3,
             r["oz_m"] * 1e3, r["rms_error_deg"], r["max_error_deg"], r["blocked_beams"]]
            for r in rows]


_MIRROR_HEAD = ["mirror", "steps", "beams", "span QZ [cm]", "length [cm]", "phi [deg]",
                "d [mm]", "OA [mm]", "OZ [mm]", "rms err at D [deg]", "max err at D [deg]",
                "blocked"]


def write_report(data: ReportData, out_dir: str | Path) -> ReportPaths:
    """Render ``data`` to ``out_dir``: report.html, report.md, figures/*.png, the TOML, JSON."""
    from ..spec import design_to_toml

    out = Path(out_dir)
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    spec, design = data.spec, data.design
    toml_text = design_to_toml(spec)
    toml_path = out / f"{spec.name}.toml"
    toml_path.write_text(toml_text)

    doc = _Doc()
    doc.heading(f"Design report: {spec.name}", 1)
    if spec.description:
        doc.para(spec.description)
    doc.para(f"Lidar {spec.lidar}; design distance D = {spec.layout.design_distance_m:g} m; "
             f"{spec.layout.windows} windows, {spec.layout.mirrors_per_side} mirrors a side; "
             f"placement = {spec.placement.method}. Direct steps "
             f"{int(design.direct_steps[0])}..{int(design.direct_steps[-1])}.")

    doc.heading("Design parameters")
    prow = []
    for sec in ("layout", "placement", "mirror", "nod"):
        for k, v in spec.to_dict()[sec].items():
            prow.append([f"{sec}.{k}", v])
    doc.table(["parameter", "value"], prow)

    doc.heading("Mirrors")
    doc.table(_MIRROR_HEAD, _mirror_rows(data.mirrors))
    doc.para("span QZ: distance between the first and last beam's hit points (the paper's "
             "L); length: the patch including half-step margins; d: perpendicular distance "
             "from the lidar origin to the mirror; errors: exact ray trace against the "
             "interleave target on the arc of radius D.")

    doc.heading("Verification")
    vs = data.verification
    doc.para(f"Every valid beam ray-traced through the finite mirrors: {vs['n_blocked']} "
             "blocked or caught by the wrong mirror.")
    doc.table(["mirror", "beams", "blocked", "rms error [deg]", "max error [deg]"],
              [[n, s["beams"], s["blocked"], np.degrees(s["rms_error_rad"]),
                np.degrees(s["max_error_rad"])] for n, s in vs["mirrors"].items()])

    doc.heading("Comparison with the paper and the " + data.other_method + " placement")
    other_paper: dict[str, dict[str, Any]] = {}
    if data.paper and data.other is not None:
        from ..designio import paper_comparison

        other_paper = {r["quantity"]: r for r in paper_comparison(data.other)}
    if data.paper:
        heads = ["quantity", "paper", f"this design ({spec.placement.method})", "difference",
                 "relative [%]"]
        if other_paper:
            heads += [f"{data.other_method} placement", f"{data.other_method} relative [%]"]
        rows = []
        for r in data.paper:
            row = [r["quantity"], r["paper"], r["ours"], r["difference"], r["relative"] * 100]
            if other_paper:
                o = other_paper.get(r["quantity"])
                row += [o["ours"], o["relative"] * 100] if o else [None, None]
            rows.append(row)
        doc.table(heads, rows, digits=6)   # the paper prints 6 significant digits
    else:
        doc.para("The design file has no [reference] table of published numbers.")
    if data.other is not None:
        crow = []
        for a, b in zip(data.mirrors, data.other_mirrors, strict=True):
            for key, label, scale in (("beam_span_m", "span QZ [cm]", 100),
                                      ("length_m", "length [cm]", 100),
                                      ("phi_deg", "phi [deg]", 1),
                                      ("standoff_m", "d [mm]", 1e3),
                                      ("rms_error_deg", "rms err at D [deg]", 1),
                                      ("max_error_deg", "max err at D [deg]", 1)):
                crow.append([a["name"], label, a[key] * scale, b[key] * scale])
        doc.table(["mirror", "quantity", spec.placement.method, data.other_method], crow)
    else:
        doc.para(f"The {data.other_method} placement of this spec is infeasible: "
                 f"{data.other_error}")

    doc.heading("Drift with range")
    figs = _figures(data)
    pngs: list[Path] = []

    def put(stem: str, caption: str, fig) -> None:
        png = _png(fig)
        path = fig_dir / f"{stem}.png"
        path.write_bytes(png)
        pngs.append(path)
        doc.figure(png, f"figures/{stem}.png", caption)

    by = {stem: (cap, fig) for stem, cap, fig in figs}
    for stem in ("bearing", "separation", "drift_vs_range"):
        put(stem, *by[stem])
    dr = data.drift
    res = dr.resolution_rad
    rows = []
    for m in dr.mirrors:
        exc = np.max(np.abs(m.separation_trace - res), axis=1) / res
        err = np.degrees(np.max(np.abs(m.error_from_target), axis=1))
        for j, r in enumerate(dr.ranges_m):
            rows.append([m.name, r, err[j], exc[j] * 100])
    doc.table(["mirror", "R [m]", "max |bearing - target| [deg]",
               "max |separation - step| [% of a step]"], rows)

    doc.heading("Interleave and beam density")
    for stem in ("interleave", "interleave_strip", "density"):
        put(stem, *by[stem])
    de = data.density
    doc.table(["R [m]", "beams in window / no mirrors", "median gap [steps]", "max gap [steps]"],
              [[r, de.density_per_rad[j].mean() / de.density_no_mirrors_per_rad.mean(),
                de.median_gap_rad[j] / res, de.max_gap_rad[j] / res]
               for j, r in enumerate(de.ranges_m)])

    doc.heading("Tolerance analysis")
    tr = data.tolerance
    t = tr.tolerance
    doc.para(f"{tr.n_samples} sampled builds (seed {tr.seed}, chunks of {tr.chunk_size}), "
             f"{t.distribution} distributions ({'1-sigma' if t.distribution == 'normal' else 'half-width'}"
             f" values below). Bearing and projected-range errors are what the nominal runtime "
             "model reports minus the truth for a target on the arc; elevation is the "
             "reflected beam's angle out of the scan plane (the paper's 2 dbeta at normal "
             "incidence); edge misses are beams falling off their own mirror.")
    srow = [[n, np.degrees(t.sigma_for(n).dalpha_rad), np.degrees(t.sigma_for(n).dbeta_rad),
             t.sigma_for(n).dd_m * 1e3] for n in tr.mirror_names]
    doc.table(["mirror", "dalpha [deg]", "dbeta [deg]", "dd [mm]"], srow)
    doc.para(f"Lidar mounting: yaw {np.degrees(t.lidar.yaw_rad):.4g} deg, pitch "
             f"{np.degrees(t.lidar.pitch_rad):.4g} deg, roll {np.degrees(t.lidar.roll_rad):.4g} "
             f"deg, offset {t.lidar.offset_m * 1e3:.4g} mm per axis.")
    trows = tr.table()
    qs = t.percentiles
    heads = (["mirror", "R [m]"] + [f"bearing p{q:g} [deg]" for q in qs]
             + [f"range p{q:g} [mm]" for q in qs] + [f"elevation p{q:g} [deg]" for q in qs]
             + ["edge-miss builds"])
    doc.table(heads, [[r["mirror"], r["range_m"]]
                      + [r[f"bearing_err_p{q:g}_deg"] for q in qs]
                      + [r[f"range_err_p{q:g}_mm"] for q in qs]
                      + [r[f"elevation_p{q:g}_deg"] for q in qs]
                      + [r["edge_miss_fraction"]] for r in trows])
    for stem in ("tolerance_hist", "tolerance_percentiles"):
        put(stem, *by[stem])

    doc.heading("Sensitivities")
    doc.para(f"d(bearing on the arc of radius D = {data.sensitivity.design_distance_m:g} m) / "
             "d(parameter) by central finite differences through the geometry core, over each "
             "mirror's beams; the last column is the largest difference from the closed form "
             "(eq. 1 differentiated; none for the lidar pitch and roll).")
    doc.table(["mirror", "parameter", "unit", "mean", "min", "max", "|FD - closed form|"],
              [[r["mirror"], r["parameter"], r["unit"], r["mean"], r["min"], r["max"],
                r["closed_form_max_diff"]] for r in data.sensitivity.table()])
    put("sensitivities", *by["sensitivities"])

    design_space = None
    if data.exploration is not None:  # nodlidar explore's table and Pareto plots
        from .explore import report_section

        design_space = report_section(data.exploration, doc, put)

    from ..cad.params import mount_params_from_spec
    from ..cad.printable import bill_of_materials

    doc.heading("Bill of materials")
    bom = bill_of_materials(design, mount_params_from_spec(spec))
    doc.para("What to order for the mirror mounts (from the solved mirrors and the [cad] "
             "section). The screws and dowels that join a base split to fit the print bed "
             "depend on the cut CAD and are listed by `nodlidar cad` in its bom.md.")
    doc.table(["item", "spec", "qty", "note"], [[r["item"], r["spec"], r["qty"], r["note"]]
                                                for r in bom])

    doc.heading("Design file")
    doc.code(toml_text)

    html_path = out / "report.html"
    md_path = out / "report.md"
    html_path.write_text("<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
                         f"<title>{html.escape(spec.name)} design report</title>"
                         f"<style>{_CSS}</style></head><body>\n" + "\n".join(doc.h)
                         + "\n</body></html>\n")
    md_path.write_text("\n".join(doc.m) + "\n")
    summary = {
        "name": spec.name, "method": spec.placement.method, "mirrors": data.mirrors,
        "paper_comparison": data.paper, "verification": data.verification,
        "other": {"method": data.other_method, "mirrors": data.other_mirrors,
                  "paper_comparison": list(other_paper.values()),
                  "error": data.other_error},
        "drift": {"ranges_m": [float(x) for x in dr.ranges_m],
                  "eq1_max_difference_rad": dr.max_closed_vs_trace,
                  "first_last": dr.first_last_table()},
        "tolerance": {"spec": t.to_dict(), "n_samples": tr.n_samples, "table": trows},
        "sensitivities": data.sensitivity.table(),
        "design_space": design_space,
        "bill_of_materials": bom,
    }
    json_path = out / "report.json"
    json_path.write_text(json.dumps(summary, indent=2, default=float))
    return ReportPaths(html=html_path, markdown=md_path, toml=toml_path, json=json_path,
                       figures=pngs)


def build_report(design: str | Path | DesignSpec, out_dir: str | Path | None = None,
                 **kwargs: Any) -> ReportPaths:
    """Load (if a path), analyse and write the report; ``kwargs`` go to :func:`compute_report`."""
    from ..spec import DesignSpec, load_design

    spec = design if isinstance(design, DesignSpec) else load_design(design)
    data = compute_report(spec, **kwargs)
    return write_report(data, default_out_dir(spec) if out_dir is None else out_dir)
