"""CLI conventions: --version, help on a bare `nodlidar`, plain-text help, -q/-v, --json on
scan/report/info, exit codes documented where users look (docs/cli.md, --help)."""

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from nodlidar.cli import EXIT_CODES, build_parser, main
from nodlidar.commands._output import plain

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"
NODLIDAR = [sys.executable, "-m", "nodlidar.cli"]
MARKUP = re.compile(r"``|:[a-z]+:`")


def _subparsers():
    p = build_parser()
    return p, p._subparsers._group_actions[0].choices


def test_version_is_the_distributions(capsys):
    """--version prints the [project] version of pyproject.toml (read here independently)."""
    want = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"nodlidar {want}"


def test_bare_nodlidar_prints_help_and_exits_2():
    r = subprocess.run(NODLIDAR, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stdout.startswith("usage: nodlidar") and r.stderr == ""
    _, subs = _subparsers()
    for name in subs:   # every command is listed
        assert re.search(rf"^\s+{name}\s", r.stdout, re.M), name


def test_help_is_plain_text():
    """No reST markup in any command's help; the text around the markup survives."""
    parser, subs = _subparsers()
    assert not MARKUP.search(parser.format_help())
    for name, p in subs.items():
        text = p.format_help()
        assert not MARKUP.search(text), (name, MARKUP.search(text))
    assert "nodlidar scan: one full nod sweep" in subs["scan"].format_help()


@pytest.mark.parametrize("src, want", [
    ("``nodlidar scan``: a sweep", "nodlidar scan: a sweep"),
    (":func:`~nodlidar.analysis.tolerance.monte_carlo` runs", "monte_carlo runs"),
    (":mod:`nodlidar.commands` (one each)", "nodlidar.commands (one each)"),
    (":class:`the error <nodlidar.errors.NodlidarError>`", "the error"),
    ("see :data:`nodlidar.paper.PAPER_DESIGN`.", "see nodlidar.paper.PAPER_DESIGN."),
    ("plain `single` and *stars* stay", "plain `single` and *stars* stay"),
])
def test_plain_strips_rest(src, want):
    assert plain(src) == want


def _documented_codes(text: str) -> dict[int, str]:
    return {int(m.group(1)): m.group(2).strip()
            for m in re.finditer(r"^\| (\d+) \| (.+?) \|$", text, re.M)}


def test_exit_codes_documented_in_help_and_docs():
    codes = dict(EXIT_CODES)
    assert set(codes) == {0, 1, 2, 130}
    doc = _documented_codes((ROOT / "docs" / "cli.md").read_text())
    assert doc == codes
    parser, _ = _subparsers()
    helptext = " ".join(parser.format_help().split())   # un-wrap
    for code, meaning in codes.items():
        assert f"- {code}: {' '.join(meaning.split())}" in helptext


def test_docs_list_every_command():
    _, subs = _subparsers()
    doc = (ROOT / "docs" / "cli.md").read_text()
    listed = set(re.findall(r"^\| `([a-z]+)[ `]", doc, re.M))
    assert set(subs) <= listed, set(subs) - listed


def test_exit_status_of_a_usage_error_and_a_missing_port(capsys, tmp_path):
    assert main(["scan", "--out", str(tmp_path / "x.txt")]) == 2           # bad input
    (tmp_path / "x.ply").write_bytes(b"")
    assert main(["scan", "--out", str(tmp_path / "x.ply")]) == 2           # exists, no --force
    assert main(["info", "--port", str(tmp_path / "no-such-tty")]) == 1    # the system refused
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("nodlidar ") for line in err)
    assert "--force" in err[1]


@pytest.mark.slow
def test_quiet_and_verbose_on_a_runtime_command():
    """The simulated sensor's status line is on stderr by default, gone with -q (before or
    after the command); -q never touches stdout."""
    def run(*args):
        r = subprocess.run([*NODLIDAR, *args], capture_output=True, text=True, cwd=ROOT,
                           timeout=300)
        assert r.returncode == 0, r.stderr
        return r

    normal = run("info", "--json")
    assert "using the simulated sensor" in normal.stderr
    for args in (("-q", "info", "--json"), ("info", "--json", "--quiet")):
        q = run(*args)
        assert q.stderr == "" and json.loads(q.stdout)["lidar"] == json.loads(normal.stdout)["lidar"]
    verbose = run("-v", "info").stderr
    assert "using the simulated sensor" in verbose and "nodlidar 0.1" in verbose   # + debug lines


def test_info_json_extra_is_an_object(capsys):
    assert main(["-q", "info", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for part in ("lidar", "params", "state"):
        assert isinstance(out[part]["extra"], dict), part
    assert out["simulated"] is True and [s["role"] for s in out["servos"]][0] == "nod"
    assert out["params"]["ares"] == 1024   # URG-04LX: 1024 steps a turn (PP ARES)


@pytest.mark.slow
def test_scan_json_matches_the_file(tmp_path, capsys):
    """scan --json describes the file it wrote: the point count read back with trimesh's
    PLY reader (not nodlidar's), the reflected count from the file's mirror field."""
    import trimesh

    out = tmp_path / "s.ply"
    assert main(["-q", "scan", "--sim-rate", "5", "--out", str(out), "--json"]) == 0
    std = capsys.readouterr()
    info = json.loads(std.out)
    assert std.err == ""
    assert info["path"] == str(out) and info["format"] == "ply" and info["binary"] is True
    assert info["frame"] == "sensor" and info["mirrors"] == "deployed" and info["simulated"]
    assert (info["nod_lower_rad"], info["nod_upper_rad"]) == (-0.35, 0.35)   # the design's [nod]
    pc = trimesh.load(out)
    assert pc.vertices.shape[0] == info["points"] > 10_000
    mirror = pc.metadata["_ply_raw"]["vertex"]["data"]["mirror"]
    assert int(np.count_nonzero(mirror >= 0)) == info["reflected_points"] > 0


def test_report_json(tmp_path, capsys):
    assert main(["-q", "report", str(PAPER), "--out", str(tmp_path / "r"), "--samples", "40",
                 "--workers", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert Path(out["html"]).is_file() and Path(out["markdown"]).is_file()
    assert len(out["figures"]) == 9 and all(Path(f).is_file() for f in out["figures"])
    assert out["summary"] == json.loads(Path(out["json"]).read_text())
    assert out["summary"]["tolerance"]["n_samples"] == 40


def test_a_swallowed_ctrl_c_still_exits_130(monkeypatch, capsys):
    """A KeyboardInterrupt raised where Python drops it (here a ``__del__``; in the field
    Dask's gc callback during ``tolerance --workers``) must not end in exit 0 with the
    cancelled result: the command stops at its next checkpoint, one line, status 130."""
    import nodlidar.commands.info as info_cmd

    class RaisesOnDelete:
        def __del__(self):
            raise KeyboardInterrupt

    def run(args):
        RaisesOnDelete()   # dropped at once: Python prints "Exception ignored" and goes on
        print("the result")
        return 0

    monkeypatch.setattr(info_cmd, "run", run)
    import sys as _sys

    hook_before = _sys.unraisablehook
    code = main(["info"])
    out, err = capsys.readouterr()
    assert code == 130
    assert err.strip().splitlines() == ["nodlidar info: interrupted"]
    assert "the result" in out   # printed before the interrupt was seen; the status says no
    # outside a command run, unraisable exceptions are reported the usual way again
    assert _sys.unraisablehook is hook_before


def test_what_a_ctrl_c_left_half_built_fails_quietly(monkeypatch, capsys):
    """A Ctrl-C that lands inside a constructor (in the field: Dask's ``Future.__init__``
    while ``tolerance --workers 2`` starts its cluster) leaves an object whose ``__del__``
    fails ("Exception ignored in ... AttributeError") when the interrupted frames are
    freed: the user sees the one line, not that. Outside an interrupt such a failure is
    still reported (to the hook that was there before the command)."""
    import sys as _sys

    import nodlidar.commands.info as info_cmd

    seen = []
    monkeypatch.setattr(_sys, "unraisablehook", lambda u: seen.append(type(u.exc_value)))

    class HalfBuilt:
        def __init__(self):
            raise KeyboardInterrupt   # before ``_cleared`` is set, as in the field

        def __del__(self):
            self._cleared   # noqa: B018 (AttributeError)

    def run(args):
        HalfBuilt()
        return 0

    monkeypatch.setattr(info_cmd, "run", run)
    assert main(["info"]) == 130
    assert capsys.readouterr().err.strip().splitlines() == ["nodlidar info: interrupted"]
    assert seen == []

    class Broken:
        def __del__(self):
            self._cleared   # noqa: B018

    def run_ok(args):
        Broken()
        return 0

    monkeypatch.setattr(info_cmd, "run", run_ok)
    assert main(["info"]) == 0
    assert seen == [AttributeError]
