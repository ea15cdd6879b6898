"""The design report: files exist, the HTML embeds every figure, the Markdown's figures
exist; importing the analysis does not pull in matplotlib or Dask."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from nodlidar.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"
N_FIGURES = 9


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    assert main(["report", str(PAPER), "--out", str(out), "--samples", "300", "--workers", "0"]) == 0
    return out


def test_report_files_exist(report_dir):
    for name in ("report.html", "report.md", "report.json", "urg04lx-paper.toml"):
        assert (report_dir / name).is_file() and (report_dir / name).stat().st_size > 0, name
    assert len(list((report_dir / "figures").glob("*.png"))) == N_FIGURES


def test_html_embeds_every_figure(report_dir):
    text = (report_dir / "report.html").read_text()
    imgs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(imgs) == N_FIGURES
    assert all(len(b) > 1000 for b in imgs)
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


def test_report_bad_input(capsys):
    assert main(["report", str(PAPER), "--samples", "0"]) == 2
    assert main(["report", "missing.toml"]) == 2


def test_tolerance_cli_json(capsys):
    import json

    assert main(["tolerance", str(PAPER), "--samples", "40", "--workers", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_samples"] == 40 and len(out["percentiles"]) == 16
    assert len(out["sensitivities"]) == 28


def test_import_stays_light():
    code = ("import sys, nodlidar, nodlidar.analysis, nodlidar.analysis.tolerance, "
            "nodlidar.analysis.plots, nodlidar.analysis.report, nodlidar.commands.report; "
            "bad = [m for m in ('matplotlib', 'dask', 'distributed') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
