"""The design report: files exist, the HTML embeds every figure, the Markdown's figures
exist; importing the analysis does not pull in matplotlib or Dask."""

import base64
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from nodlidar.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"
# the chained reading: its split is derived from [layout], so the optimal placement of the
# same split can be built and compared (the default's explicit split refuses it)
CHAINED = ROOT / "design" / "urg04lx-paper-chained.toml"
N_FIGURES = 9


def _report(tmp_path_factory, design):
    out = tmp_path_factory.mktemp("report")
    assert main(["report", str(design), "--out", str(out), "--samples", "300", "--workers",
                 "0", "--force"]) == 0   # mktemp made the directory
    return out


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    return _report(tmp_path_factory, PAPER)


@pytest.fixture(scope="module")
def chained_report_dir(tmp_path_factory):
    return _report(tmp_path_factory, CHAINED)


def test_report_files_exist(report_dir):
    for name in ("report.html", "report.md", "report.json", "urg04lx-paper.toml"):
        assert (report_dir / name).is_file() and (report_dir / name).stat().st_size > 0, name
    assert len(list((report_dir / "figures").glob("*.png"))) == N_FIGURES


def test_html_embeds_every_figure(report_dir):
    text = (report_dir / "report.html").read_text()
    imgs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(imgs) == N_FIGURES
    assert all(len(b) > 1000 for b in imgs)
    # every figure written beside the Markdown is embedded byte for byte, and nothing else
    embedded = {base64.b64decode(b) for b in imgs}
    files = {p.read_bytes() for p in (report_dir / "figures").glob("*.png")}
    assert len(embedded) == N_FIGURES and embedded == files
    assert all(b.startswith(b"\x89PNG\r\n\x1a\n") for b in embedded)
    assert "src=\"figures/" not in text  # self-contained: no file references
    for heading in ("Mirrors", "Verification", "Comparison with the paper", "Drift with range",
                    "Interleave and beam density", "Tolerance analysis", "Sensitivities",
                    "Design file"):
        assert heading in text, heading
    # the paper's published numbers, the optimised design and the TOML are all there
    assert "L1_length_m" in text and "optimal" in text and "design_distance_m = 2.0" in text


def test_markdown_references_existing_pngs(report_dir):
    text = (report_dir / "report.md").read_text()
    refs = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", text)
    assert len(refs) == N_FIGURES
    for ref in refs:
        assert (report_dir / ref).is_file(), ref
    assert "| L1 |" in text and "```toml" in text


def test_report_default_out_dir(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["report", str(PAPER), "--samples", "50", "--workers", "0"]) == 0
    out = capsys.readouterr().out
    html = tmp_path / "out" / "report" / "urg04lx-paper" / "report.html"
    assert html.is_file() and "out/report/urg04lx-paper/report.html" in out


def test_report_bad_input(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:   # argparse: bounded integer
        main(["report", str(PAPER), "--samples", "0"])
    assert exc.value.code == 2
    assert main(["report", "missing.toml"]) == 2
    # an existing output directory is refused before the Monte Carlo (one --force policy)
    assert main(["report", str(PAPER), "--out", str(tmp_path), "--samples", "10"]) == 2
    assert "--force" in capsys.readouterr().err and not list(tmp_path.iterdir())


def test_tolerance_cli_json(capsys):
    import json

    assert main(["tolerance", str(PAPER), "--samples", "40", "--workers", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_samples"] == 40 and len(out["percentiles"]) == 16
    assert len(out["sensitivities"]) == 4 * 8     # 4 mirrors x 8 parameters


def test_import_stays_light():
    code = ("import sys, nodlidar, nodlidar.analysis, nodlidar.analysis.tolerance, "
            "nodlidar.analysis.plots, nodlidar.analysis.report, nodlidar.commands.report; "
            "bad = [m for m in ('matplotlib', 'dask', 'distributed') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


def test_report_says_why_the_optimised_design_is_refused(report_dir):
    """The default (exact) reading's split has shadowed beams by construction; the optimal
    placement of it is infeasible, and the report says so with the blocked beams."""
    summary = json.loads((report_dir / "report.json").read_text())
    assert summary["other"]["method"] == "optimal" and summary["other"]["mirrors"] == []
    assert "blocked" in summary["other"]["error"]
    assert summary["other"]["error"] in (report_dir / "report.md").read_text()


def test_report_compares_with_the_optimised_design(chained_report_dir):
    """The other placement is really solved and shown: its numbers are in the HTML tables."""
    from nodlidar.analysis.report import _fmt

    report_dir = chained_report_dir
    summary = json.loads((report_dir / "report.json").read_text())
    assert summary["method"] == "anchor" and summary["other"]["method"] == "optimal"
    ours = {m["name"]: m for m in summary["mirrors"]}
    other = {m["name"]: m for m in summary["other"]["mirrors"]}
    assert set(other) == set(ours) == {"L1", "L2", "R1", "R2"}
    text = (report_dir / "report.html").read_text()
    for name in ("L1", "R1"):
        # the optimiser's job: a smaller RMS interleave error at D for the outer mirrors
        assert other[name]["rms_error_deg"] < 0.7 * ours[name]["rms_error_deg"]
        assert f"<td>{_fmt(other[name]['rms_error_deg'])}</td>" in text
    # the paper table has a column for the optimised design, with its own phi(L1)
    opt = {r["quantity"]: r for r in summary["other"]["paper_comparison"]}
    assert set(opt) == {r["quantity"] for r in summary["paper_comparison"]}
    assert "optimal placement</th>" in text
    assert f"<td>{_fmt(opt['L1_phi_deg']['ours'], 6)}</td>" in text
    assert abs(opt["L1_phi_deg"]["ours"] - 80.0397) > 0.1   # not the anchor design's value


@pytest.mark.parametrize("variant", ["paper", "k5"])
def test_drift_figures_have_a_panel_for_every_mirror(variant):
    """Figs 6/7 analogues are drawn for all mirrors, not only L1/L2 (also 8 mirrors, k = 5)."""
    import matplotlib.pyplot as plt  # noqa: TID251 (closing figures in a plot test)

    from nodlidar.analysis import bearing_drift, plots
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    # k = 5 re-derives the split from [layout]: only the chained reading has no explicit one
    spec = load_design(PAPER if variant == "paper" else CHAINED)
    if variant == "k5":
        spec = spec.replace(**{"layout.windows": 5, "layout.mirrors_per_side": 4})
    design = solve(spec)
    drift = bearing_drift(design, [0.4, 2.0, 6.0])
    names = [m.name for m in design.mirrors]
    assert len(names) == (4 if variant == "paper" else 8)
    for plot in (plots.plot_bearing, plots.plot_separation):
        fig = plot(drift)
        axes = [a for a in fig.axes if a.get_visible()]
        assert [a.get_title().split(":")[0] for a in axes] == names, plot.__name__
        for a in axes:   # one line per range plus the reference line
            assert len(a.get_lines()) == len(drift.ranges_m) + 1
        plt.close(fig)


class _Tables:
    """Every <table> of an HTML document as a list of rows of cell texts (header row first)."""

    def __init__(self, text: str):
        from html.parser import HTMLParser

        tables: list[list[list[str]]] = []
        cell: list[str] | None = None

        class P(HTMLParser):
            def handle_starttag(self, tag, attrs):
                nonlocal cell
                if tag == "table":
                    tables.append([])
                elif tag == "tr":
                    tables[-1].append([])
                elif tag in ("td", "th"):
                    cell = []

            def handle_endtag(self, tag):
                nonlocal cell
                if tag in ("td", "th"):
                    tables[-1][-1].append("".join(cell).strip())
                    cell = None

            def handle_data(self, data):
                if cell is not None:
                    cell.append(data)

        P(convert_charrefs=True).feed(text)
        self.tables = tables


@pytest.mark.parametrize("which, n_tables", [("report_dir", 9), ("chained_report_dir", 10)])
def test_markdown_tables_render_like_the_html(request, which, n_tables):
    """The Markdown report parsed by a CommonMark + GFM-tables parser (markdown-it-py) gives
    every table the HTML report has, with the same rows, columns and cell text. A `|` left
    unescaped in a header cell (e.g. ``max |bearing - target|``) makes GitHub drop the
    whole table; one in a body cell shifts the columns. The default design has one table
    fewer: its optimal placement is refused (a sentence, not a table)."""
    from markdown_it import MarkdownIt

    report_dir = request.getfixturevalue(which)

    md_text = (report_dir / "report.md").read_text()
    rendered = MarkdownIt("commonmark").enable("table").render(md_text)
    html_tables = _Tables((report_dir / "report.html").read_text()).tables
    md_tables = _Tables(rendered).tables
    # what _Doc.table wrote: one Markdown table per delimiter row
    written = sum(1 for line in md_text.splitlines() if re.fullmatch(r"\|(---\|)+", line))
    assert len(html_tables) == written >= n_tables
    assert len(md_tables) == written
    for h, m in zip(html_tables, md_tables, strict=True):
        assert [len(r) for r in m] == [len(r) for r in h], h[0]
        assert m == h
    # the headers that used to break, and the absolute-value bars, are there as text
    headers = [t[0] for t in md_tables]
    assert ["mirror", "R [m]", "max |bearing - target| [deg]",
            "max |separation - step| [% of a step]"] in headers
    assert any("|FD - closed form|" in head for head in headers)


def test_markdown_cell_escaping():
    """Cells with a pipe, a backslash before a pipe, or a line break still make one table of
    the right shape, and read back as written."""
    from markdown_it import MarkdownIt

    from nodlidar.analysis.report import _Doc

    doc = _Doc()
    heads = ["a|b", "c\\", "|x|"]
    rows = [["1|2", "ends with \\", "two\nlines"], ["x", "", "\\|"]]
    doc.table(heads, rows)
    tables = _Tables(MarkdownIt("commonmark").enable("table").render("\n".join(doc.m))).tables
    assert tables == [[heads, ["1|2", "ends with \\", "two lines"], ["x", "", "\\|"]]]


def test_report_has_the_bill_of_materials(report_dir):
    """The report lists one glass pane per mirror, sized by the solved patch length and the
    design file's glass height and thickness (read here from the report's own mirror table
    and the TOML it wrote), plus a lift servo per side."""
    import tomllib

    summary = json.loads((report_dir / "report.json").read_text())
    spec = tomllib.loads((report_dir / "urg04lx-paper.toml").read_text())
    bom = {r["item"]: r for r in summary["bill_of_materials"]}
    h, t = spec["mirror"]["glass_height_m"] * 1e3, spec["mirror"]["glass_thickness_m"] * 1e3
    for m in summary["mirrors"]:
        dims = re.search(r"([\d.]+) x ([\d.]+) x ([\d.]+) mm", bom[f"glass {m['name']}"]["spec"])
        # printed to 0.1 mm
        assert [float(x) for x in dims.groups()] == pytest.approx(
            [m["length_m"] * 1e3, h, t], abs=0.051)
    assert bom["lift servo"]["qty"] == 2
    md = (report_dir / "report.md").read_text()
    assert "## Bill of materials" in md and "| glass L1 |" in md
