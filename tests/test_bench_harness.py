"""benchmarks/run.py (each benchmark in a fresh process, named figures, peak RSS, min/median
over --repeat) and the CLI's light start-up (issue 16)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "benchmarks" / "run.py"

# a benchmark that returns the number of times it has run (a counter file), allocates
# 64 MiB, and leaves a marker module behind in its interpreter
BENCH_A = '''
import sys, types
from pathlib import Path
import numpy as np

def main():
    f = Path(__file__).with_name("count.txt")
    k = int(f.read_text()) + 1 if f.exists() else 1
    f.write_text(str(k))
    block = np.ones(64 * 2**20 // 8)  # touched: resident
    sys.modules["_bench_marker"] = types.ModuleType("_bench_marker")
    return {"count": float(k), "sum": float(block.sum())}
'''
# run after A: sees A's marker only if both shared one interpreter
BENCH_B = '''
import sys
import numpy  # the same imports as A: the RSS difference is A's block

def main():
    return {"saw_other_benchmark": float("_bench_marker" in sys.modules)}
'''


def _run(args, cwd):
    return subprocess.run([sys.executable, str(RUN), *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow
def test_fresh_process_figures_rss_and_min_median(tmp_path):
    (tmp_path / "bench_a.py").write_text(BENCH_A)
    (tmp_path / "bench_b.py").write_text(BENCH_B)
    out = tmp_path / "out" / "bench.json"
    p = _run(["--dir", str(tmp_path), "--repeat", "3", "--json", str(out)], tmp_path)
    assert p.returncode == 0, p.stderr
    fig = json.loads(out.read_text())["figures"]
    # three runs of A, in order: 1, 2, 3 -> min 1, median 2 (computed here another way)
    assert fig["a.count"]["runs"] == [1.0, 2.0, 3.0]
    assert fig["a.count"]["min"] == 1.0 and fig["a.count"]["median"] == 2.0
    # every benchmark in its own interpreter: B never sees A's module
    assert fig["b.saw_other_benchmark"]["runs"] == [0.0, 0.0, 0.0]
    # peak RSS is the child's own: A holds 64 MiB more than B (an interpreter with numpy
    # is ~30-60 MiB; 64 MiB of touched pages must show, minus slack for allocator reuse)
    assert fig["a.peak_rss_mib"]["min"] >= 64
    assert fig["a.peak_rss_mib"]["min"] - fig["b.peak_rss_mib"]["min"] > 48
    assert "a.wall_s" in fig and "summary" in p.stdout


def test_failing_benchmark_and_bad_arguments(tmp_path):
    (tmp_path / "bench_bad.py").write_text("def main():\n    raise RuntimeError('boom')\n")
    p = _run(["--dir", str(tmp_path), "bad"], tmp_path)
    assert p.returncode == 1 and "benchmark bad failed" in p.stderr
    p = _run(["--dir", str(tmp_path), "nosuch"], tmp_path)
    assert p.returncode == 2 and "unknown benchmark" in p.stderr
    p = _run(["--dir", str(tmp_path), "--repeat", "0", "bad"], tmp_path)
    assert p.returncode == 2 and "--repeat 0" in p.stderr


def test_cli_parser_imports_no_numpy():
    """``nodlidar --help`` builds the whole parser: it must not import numpy (nor scipy),
    which cost most of the start-up (issue 16). A fresh interpreter: this one has numpy."""
    code = ("import sys, nodlidar.cli; nodlidar.cli.build_parser(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'scipy')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]"


# what `nodlidar design` must not import (issue 16): scipy.optimize alone cost ~0.5 s of a
# ~1 s start-up; the plotting, mesh and tracking stacks belong to other commands
DESIGN_FORBIDDEN = ("scipy", "matplotlib", "trimesh", "stonesoup", "cadquery", "open3d",
                    "numba")


@pytest.mark.parametrize("design", ["urg04lx-paper.toml", "urg04lx-paper-chained.toml",
                                    "urg04lx-optimal.toml"])
def test_cli_design_imports_no_scipy(design):
    """``nodlidar design FILE`` (the anchor or optimal placement and the other method for
    comparison, the trace, the table) in a fresh interpreter: neither ``sys.modules`` at
    the end nor ``-X importtime`` (every import, even one removed again) names scipy or
    the plotting/mesh/tracking stacks."""
    code = ("import contextlib, io, sys\n"
            "from nodlidar.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    rc = main(['design', {str(ROOT / 'design' / design)!r}])\n"
            "print(rc, sorted(m for m in sys.modules if m.split('.')[0] in "
            f"{DESIGN_FORBIDDEN!r}))\n")
    p = subprocess.run([sys.executable, "-X", "importtime", "-c", code], capture_output=True,
                       text=True, timeout=180, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.strip() == "0 []"
    imported = [line.rsplit("|", 1)[-1].strip() for line in p.stderr.splitlines()
                if line.startswith("import time:")]
    assert "nodlidar.solver" in imported  # the importtime listing is the real one
    assert [m for m in imported if m.split(".")[0] in DESIGN_FORBIDDEN] == []


def _study_scenes():
    import importlib.util

    spec = importlib.util.spec_from_file_location("study_scenes",
                                                  ROOT / "benchmarks" / "study_scenes.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _study_run(case, config, seed, conv, conv_scan, switches=0, purity=1.0, view=1,
               reported=3):
    return {"case": case, "config": config, "seed": seed, "false_tracks": 0,
            "entropy": "renyi", "gospa_m": 0.2,
            "movers": [{"mover": "P", "conv": conv, "conv_scan": conv_scan, "first_scan": 2,
                        "view_scan": view, "reported_scan": reported,
                        "id_switches": switches, "purity": purity, "final_err_v_m_s": 0.001,
                        "final_err_heading_deg": 0.1}]}


def test_study_scenes_criteria_from_runs():
    """benchmarks/study_scenes.py's summary: medians over seeds (not converged = later than
    any), and the lists of the issue's criteria it fails."""
    mod = _study_scenes()
    runs = []
    for seed in range(4):
        runs += [_study_run("a", "mirrors", seed, 5, 20 + seed),
                 _study_run("a", "lifted", seed, 4, 10)]
        runs += [_study_run("track-crossing", "mirrors", seed, None if seed < 3 else 3, None,
                            switches=int(seed == 1)),
                 _study_run("track-crossing", "lifted", seed, 3, 9)]
        # in the mirrors' view only after lifted converged (scan 12 > 10)
        runs += [_study_run("b", "mirrors", seed, 4, 16, view=12 + seed % 2,
                            reported=13 + seed),
                 _study_run("b", "lifted", seed, 4, 10)]
    crit = mod.summary(runs)["criteria"]
    assert crit["mirrors_later_by_time"] == ["a P: 21.5 / 10", "b P: 16 / 10"]
    assert crit["mirrors_later_by_time_out_of_view"] == ["b P: 16 / 10, in view at 12.5"]
    # converged 3.5 scans after its view met it, lifted 9 (in view at 1): not later so
    assert crit["mirrors_later_after_view"] == ["a P: 20.5 / 9"]
    assert crit["mirrors_later_by_count"] == ["a P: 5 / 4"]
    assert crit["mirrors_reported_later"] == ["b P: 14.5 / 3"]
    assert crit["mirrors_not_converged_where_lifted"] == ["track-crossing P: - / 9"]
    assert crit["mirrors_fewer_seeds_converged"] == ["track-crossing P: 1 / 4"]
    assert crit["identity_failures"] == ["track-crossing P mirrors seeds [1]"]


def test_study_scenes_runs_and_resumes(tmp_path):
    """One case, one seed: two runs appended to the JSON lines file, not run again."""
    out = tmp_path / "runs.jsonl"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "study_scenes.py"), str(out), "--only",
           "track-range-1m", "--seeds", "1", "--jobs", "1"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "| track-range-1m | cylinder |" in p.stdout
    lines = out.read_text().splitlines()
    assert sorted(json.loads(x)["config"] for x in lines) == ["lifted", "mirrors"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0 and "0 runs (2 already in" in p.stderr, p.stderr
    assert out.read_text().splitlines() == lines


def test_the_harness_takes_every_set_flag_and_refuses_to_summarise_nothing(tmp_path):
    # two --set flags: both apply (the second used to replace the first, silently), so a
    # malformed first one is refused even with a well-formed second
    root = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, str(root / "benchmarks" / "study_scenes.py"), str(tmp_path / "o.jsonl"),
           "--summary", "--set", "tracker.newton_recentre", "--set", "tracker.round_fuse=true"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "--set 'tracker.newton_recentre': expected" in p.stderr, p.stderr
    # well-formed, but nothing to summarise: one line, no traceback
    p = subprocess.run(cmd[:-4], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "does not exist" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr


def test_the_held_out_style_scenes_load_and_are_listed():
    # benchmarks/heldout: scenes the harness runs only with --extra; kept loadable as the
    # scene format evolves, each listed once with the scans its comment asks for
    import re
    from pathlib import Path

    from nodlidar.sim.scene import load_scene

    root = Path(__file__).resolve().parents[1]
    folder = root / "benchmarks" / "heldout"
    listed = (folder / "list.txt").read_text().split()
    files = sorted(folder.glob("*.toml"))
    assert len(files) >= 20 and len(listed) == len(files)
    for entry in listed:
        path, _, scans = entry.partition("@")
        text = (root / path).read_text()
        assert int(scans) == int(re.search(r"Run (\d+) scans", text).group(1)), entry
        assert load_scene(root / path).movers, entry


@pytest.mark.slow
def test_ab_tracking_runs_a_revision_beside_this_tree_and_compares_every_scan():
    # this tree against itself as committed (HEAD): where the package has no uncommitted
    # change (CI's clean checkout), the same code, so every scan's output is identical; with
    # a change in progress, the run still completes with its figures (exit 1 if the change
    # moves an output). A revision that is not one, and a scene that does not exist, are
    # one-line refusals
    if subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"],
                      capture_output=True).returncode:
        pytest.fail("the repository's git history is needed (benchmarks/ab_tracking.py)")
    clean = not subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "nodlidar"],
                               capture_output=True, text=True).stdout.strip()
    ab = ROOT / "benchmarks" / "ab_tracking.py"
    r = subprocess.run([sys.executable, str(ab), "--scans", "64", "--json"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode in ((0,) if clean else (0, 1)), r.stderr[-2000:]
    fig = json.loads(r.stdout.strip().splitlines()[-1])
    assert fig["scans_timed"] == 4
    assert fig["outputs_identical"] == (r.returncode == 0)
    if clean:
        assert fig["outputs_identical"]
    assert fig["median_ratio"] > 0 and fig["base_median_ms"] > 0
    for bad, says in ((["--base", "no-such-revision"], "--base 'no-such-revision'"),
                      (["--scene", "no-such-scene"], "--scene 'no-such-scene'")):
        r = subprocess.run([sys.executable, str(ab), *bad], capture_output=True, text=True,
                           cwd=ROOT)
        assert r.returncode != 0 and "Traceback" not in r.stderr
        assert says in r.stderr.strip().splitlines()[-1]


def test_ab_tracking_compares_not_a_number_as_equal():
    # a track's speed is NaN before its first velocity: the same state twice compares equal
    import importlib.util

    import numpy as np

    from nodlidar.tracking.tracker import TrackState

    spec = importlib.util.spec_from_file_location("ab_tracking",
                                                  ROOT / "benchmarks" / "ab_tracking.py")
    ab = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ab)
    s = [TrackState(1, 3, 0.25, 1.0, 2.0, float("nan"), float("nan"), np.eye(4), 2, 40, False)]
    t = [TrackState(1, 3, 0.25, 1.0, 2.0, float("nan"), float("nan"), np.eye(4), 2, 40, False)]
    assert ab._state_key(s) == ab._state_key(t)
    t[0].cov[0, 0] = np.nextafter(1.0, 2.0)  # one bit off
    assert ab._state_key(s) != ab._state_key(t)
