"""`nodlidar explore`: the design space (issue 17, item 3).

Rows are checked against the solver and the ray trace called directly, the Pareto front
against a brute-force loop, the Dask run against the in-process run, and the CLI's CSV
against its JSON.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.analysis.explore import Sweep, evaluate_design, explore, pareto_front
from nodlidar.cli import main
from nodlidar.errors import ParameterError
from nodlidar.solver import solve
from nodlidar.spec import load_design
from nodlidar.verify import verify

ROOT = Path(__file__).resolve().parents[1]
# the chained reading (one standoff to sweep); urg04lx-paper-chained.toml after the swap
PAPER = ROOT / "design" / "urg04lx-paper-chained.toml"


@pytest.fixture(scope="module")
def spec():
    return load_design(PAPER)


def test_sweep_parsing(spec):
    s = Sweep.parse("layout.design_distance_m=0.5:5:0.25", spec)
    assert len(s.values) == 19 and s.values[0] == 0.5 and s.values[-1] == 5.0
    assert s.values[3] == 1.25  # no float drift (0.5 + 3 * 0.25 exactly)
    assert Sweep.parse("layout.windows=3,5", spec).values == (3, 5)
    assert isinstance(Sweep.parse("layout.windows=3,5", spec).values[0], int)
    with pytest.raises(ParameterError, match="did you mean layout.design_distance_m"):
        Sweep.parse("layout.design_distanc=1:2:0.5", spec)
    for bad in ("layout.design_distance_m", "layout.design_distance_m=1:x:0.5",
                "layout.design_distance_m=2:1:0.5", "layout.design_distance_m=1:2:0",
                "layout.windows=3.5", "layout.design_distance_m=nan"):
        with pytest.raises(ParameterError):
            Sweep.parse(bad, spec)


def test_rows_against_the_solver_and_trace(spec):
    for changes in ({"layout.design_distance_m": 2.0}, {"layout.design_distance_m": 3.5,
                                                        "placement.standoff_m": (0.03,)}):
        s = spec.replace(**changes)
        row = evaluate_design(s)
        d = solve(s)
        summ = verify(d).summary()
        # pooled RMS from the per-mirror RMS of verify (different aggregation path)
        n = np.array([summ[m]["beams"] for m in summ])
        rms = np.array([summ[m]["rms_error_rad"] for m in summ])
        assert row["feasible"] and row["blocked_beams"] == 0 and row["mirrors"] == 4
        assert_allclose(row["rms_error_deg"], np.degrees(np.sqrt(np.sum(n * rms**2) / n.sum())),
                        rtol=1e-12)
        assert_allclose(row["max_error_deg"],
                        np.degrees(max(summ[m]["max_error_rad"] for m in summ)), rtol=1e-12)
        # the 2 m column comes from explore's own arc crossing; at D = 2 m it is the D column
        if s.layout.design_distance_m == 2.0:
            assert_allclose(row["rms_error_2m_deg"], row["rms_error_deg"], rtol=1e-12)
        assert_allclose(row["glass_area_cm2"],
                        sum(m.length_m for m in d.mirrors) * s.mirror.glass_height_m * 1e4,
                        rtol=1e-12)
        # the footprint holds every mirror end and the housing, plus the base margin
        ends = np.vstack([m.patch.point(np.array([m.patch.s_min, m.patch.s_max]))[:, :2]
                          for m in d.mirrors]) * 1e3
        assert row["footprint_w_mm"] >= np.ptp(ends[:, 0]) + 20 - 1e-9
        assert row["footprint_d_mm"] >= np.ptp(ends[:, 1]) + 20 - 1e-9
    # a refused design keeps its reason and has no metrics
    row = evaluate_design(spec.replace(**{"placement.standoff_m": (0.005,)}))
    assert not row["feasible"] and "housing" in row["reason"] and math.isnan(row["rms_error_deg"])


def test_pareto_front_against_brute_force():
    rng = np.random.default_rng(3)
    rows = [{"feasible": bool(rng.random() > 0.2), "rms_error_deg": float(rng.integers(0, 6)),
             "footprint_area_mm2": float(rng.integers(0, 6)),
             "glass_area_cm2": float(rng.integers(0, 3)),
             "density_gain": float(rng.integers(0, 3))} for _ in range(300)]
    keys = (("rms_error_deg", 1), ("footprint_area_mm2", 1), ("glass_area_cm2", 1),
            ("density_gain", -1))

    def dominates(a, b):
        va = [s * a[k] for k, s in keys]
        vb = [s * b[k] for k, s in keys]
        return all(x <= y for x, y in zip(va, vb, strict=True)) and va != vb

    expect = [r["feasible"] and not any(o["feasible"] and dominates(o, r) for o in rows)
              for r in rows]
    assert list(pareto_front(rows)) == expect
    assert any(expect)


@pytest.mark.slow
def test_large_sweep_in_process_equals_local_dask_cluster(spec):
    sweeps = [Sweep.parse("layout.design_distance_m=0.5:5:0.25", spec),
              Sweep.parse("placement.standoff_m=0.015:0.04:0.0025", spec)]
    seen = []
    a = explore(spec, sweeps, workers=0, progress=lambda done, n: seen.append((done, n)))
    assert a.n_designs == 19 * 11 >= 200
    assert seen[-1] == (209, 209) and all(x[0] < y[0] for x, y in zip(seen, seen[1:]))
    # sweep order: the first sweep varies slowest
    assert [r["layout.design_distance_m"] for r in a.rows[:12]] == [0.5] * 11 + [0.75]
    assert 0 < a.n_feasible < a.n_designs and any(r["pareto"] for r in a.rows)
    # a local Dask cluster reached as an existing scheduler (the --scheduler path), the
    # designs cut into other chunks than in process
    from nodlidar.analysis.tolerance import _local_cluster

    cluster = _local_cluster(2, True)
    try:
        b = explore(spec, sweeps, scheduler=cluster.scheduler_address, chunk=7)
    finally:
        cluster.close()
    # nothing random and rows put back in sweep order: equal to the last bit, whichever
    # process ran which chunk (NaN compared as NaN)
    assert len(a.rows) == len(b.rows)
    for ra, rb in zip(a.rows, b.rows, strict=True):
        assert ra.keys() == rb.keys()
        for k in ra:
            va, vb = ra[k], rb[k]
            if isinstance(va, float) and math.isnan(va):
                assert isinstance(vb, float) and math.isnan(vb), k
            else:
                assert va == vb, (k, va, vb)


@pytest.mark.slow
def test_cli_writes_csv_json_plots_and_the_report_section(tmp_path, capsys):
    out = tmp_path / "ex"
    argv = ["explore", str(PAPER), "--sweep", "layout.design_distance_m=1.5,2,3",
            "--sweep", "placement.standoff_m=0.02,0.03", "--out", str(out), "--json"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_designs"] == 6
    data = json.loads((out / "explore.json").read_text())
    with open(out / "explore.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == len(data["rows"]) == 6
    for r, c in zip(data["rows"], table, strict=True):  # CSV and JSON: the same numbers
        for k in ("layout.design_distance_m", "rms_error_deg", "density_gain", "glass_area_cm2"):
            assert float(c[k]) == pytest.approx(r[k], rel=1e-12)
    assert {p.name for p in (out / "figures").iterdir()} == {
        "pareto_footprint.png", "pareto_glass.png", "pareto_density.png"}
    # one overwrite policy: the existing directory is refused without --force
    assert main(argv) == 2
    assert "--force" in capsys.readouterr().err
    assert main([*argv, "--force"]) == 0
    capsys.readouterr()
    # into the design report
    rep = tmp_path / "rep"
    assert main(["report", str(PAPER), "--samples", "50", "--out", str(rep), "--explore",
                 str(out / "explore.json")]) == 0
    md = (rep / "report.md").read_text()
    assert "## Design space" in md and "figures/pareto_footprint.png" in md
    js = json.loads((rep / "report.json").read_text())
    assert js["design_space"]["n_designs"] == 6
    assert len(js["design_space"]["pareto"]) == sum(r["pareto"] for r in data["rows"])


def test_cli_refusals_are_one_line(tmp_path, capsys):
    for argv, needle in (
            (["--sweep", "layout.nope=1,2"], "--sweep"),
            (["--sweep", "layout.design_distance_m=1:2"], "LO:HI:STEP"),
            (["--sweep", "layout.design_distance_m=1,2", "--scheduler", "tcp://127.0.0.1:9"],
             "--scheduler")):
        assert main(["explore", str(PAPER), *argv, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and needle in err, err
