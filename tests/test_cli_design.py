"""`nodlidar design`: output, JSON fields, and one-line errors with exit status 2."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from nodlidar.cli import main
from nodlidar.spec import design_from_dict, design_to_toml, load_design

ROOT = Path(__file__).resolve().parents[1]
# the chained reading (L1 612..725, an optimal alternative); at the swap of the paper
# files this becomes urg04lx-paper-chained.toml
PAPER = ROOT / "design" / "urg04lx-paper-chained.toml"


def test_design_table_and_json(capsys):
    assert main(["design", str(PAPER)]) == 0
    out = capsys.readouterr().out
    assert "L1" in out and "R2" in out and "against the paper" in out
    assert main(["design", str(PAPER), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    names = [m["name"] for m in data["mirrors"]]
    assert names == ["L1", "L2", "R1", "R2"]
    for m in data["mirrors"]:
        for key in ("name", "steps", "length_m", "phi_deg", "standoff_m", "normal",
                    "rms_error_deg", "max_error_deg"):
            assert key in m
    assert data["alternative"]["method"] == "optimal"
    assert data["mirrors"][0]["steps"] == [612, 725]


def test_out_writes_resolved_toml_that_round_trips(tmp_path, capsys):
    assert main(["design", str(PAPER), "--out", str(tmp_path)]) == 0
    again = load_design(tmp_path / f"{load_design(PAPER).name}.toml")
    assert again == load_design(PAPER)


def test_spec_dict_round_trip():
    spec = load_design(PAPER)
    import tomllib

    assert design_from_dict(tomllib.loads(design_to_toml(spec))) == spec


def _write(tmp_path, text):
    p = tmp_path / "d.toml"
    p.write_text(text)
    return str(p)


BASE = PAPER.read_text()


@pytest.mark.parametrize("edit, needle", [
    (lambda s: s.replace('model = "URG-04LX"', 'model = "LMS111"'), "lidar.model"),
    (lambda s: s.replace("design_distance_m = 2.0", "design_distance_m = -1.0"), "design_distance_m"),
    (lambda s: s.replace("design_distance_m = 2.0", "design_distance_m = 9.0"), "design_distance_m"),
    (lambda s: s.replace("windows = 3", "windows = 4"), "layout.windows"),
    (lambda s: s.replace("windows = 3", "windows = 1"), "layout.windows"),
    (lambda s: s.replace("[layout]", "[layout\n"), "malformed TOML"),
    (lambda s: s.replace("[layout]", "[layoutx]"), "missing required 'layout'"),
    (lambda s: s.replace("windows = 3", "windowz = 3"), "unknown key"),
    (lambda s: s.replace("design_distance_m = 2.0\n", ""), "incomplete"),
    (lambda s: s.replace("mirrors_per_side = 2", "mirrors_per_side = 1"), "blocked"),
    (lambda s: s.replace('model = "URG-04LX"', 'model = "UTM-30LX"'), "180 deg"),
])
def test_bad_input_gives_one_line_and_exit_2(tmp_path, capsys, edit, needle):
    path = _write(tmp_path, edit(BASE))
    assert main(["design", path]) == 2
    err = capsys.readouterr().err
    assert needle in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_missing_file_and_usage_errors(capsys):
    assert main(["design", "/nonexistent.toml"]) == 2
    assert "not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["design"])
    assert e.value.code == 2


def test_console_script_has_no_traceback(tmp_path):
    path = _write(tmp_path, BASE.replace("windows = 3", "windows = 2"))
    exe = Path(sys.executable).with_name("nodlidar")
    r = subprocess.run([str(exe), "design", path], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "layout.windows" in r.stderr


def test_import_nodlidar_stays_light():
    code = ("import sys, nodlidar, nodlidar.solver, nodlidar.beams, nodlidar.verify, "
            "nodlidar.closed_form, nodlidar.cli; nodlidar.cli.build_parser(); "
            "heavy = [m for m in ('cadquery', 'OCP', 'matplotlib', 'dask', 'distributed', "
            "'numba') "
            "if m in sys.modules]; print(heavy); sys.exit(1 if heavy else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def _closed_port() -> int:
    """A loopback TCP port nobody listens on (bound, then released)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("argv", [
    ["info", "--port", "socket://127.0.0.1:{port}"],
    ["scan", "--port", "/nonexistent/ttyACM9", "--servo-port", "/nonexistent/ttyUSB9"],
])
def test_device_that_cannot_be_opened_is_one_line_exit_1(capsys, argv):
    argv = [a.format(port=_closed_port()) for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert argv[2] in err  # names the port the user gave


def test_default_design_is_found_from_any_directory(tmp_path, monkeypatch, capsys):
    # commands whose --design defaults to the paper's build work outside the checkout
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", "--sim", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["design"] == "urg04lx-paper"
    assert main(["study", "mirrors", "--scans", "6", "--out", "s"]) == 0
    assert (tmp_path / "s" / "study_mirrors.md").stat().st_size > 0


PAPER_EXACT = ROOT / "design" / "urg04lx-paper.toml"  # the default: the exact reading


def test_exact_paper_reading_json(capsys):
    assert main(["design", str(PAPER_EXACT), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    spans = {m["name"]: m["steps"] for m in data["mirrors"]}
    assert spans == {"L1": [616, 725], "L2": [498, 611], "R1": [44, 152], "R2": [157, 270]}
    assert data["direct_steps"] == [271, 497]
    # the bounds against the printed numbers (independent check: test_paper_reproduction)
    for r in data["paper_comparison"]:
        tol = 3e-5 if r["quantity"].endswith("length_m") else 0.01  # 0.003 cm, 0.01 deg
        assert abs(r["difference"]) < tol, r
    assert "L1 steps 616..625 blocked by L2" in data["shadowed"]
    # the optimal alternative is refused for this file; the reason is in the JSON
    assert data["alternative"]["mirrors"] == [] and "blocked" in data["alternative"]["refused"]


def test_exact_paper_reading_round_trips(tmp_path, capsys):
    # nested [[placement.mirrors]] and shadowed ranges survive write -> read
    assert main(["design", str(PAPER_EXACT), "--out", str(tmp_path)]) == 0
    spec = load_design(PAPER_EXACT)
    assert load_design(tmp_path / f"{spec.name}.toml") == spec


def test_out_is_refused_when_it_exists_unless_forced(tmp_path, capsys):
    # the one overwrite policy: a second --out into the same place needs --force
    assert main(["design", str(PAPER), "--out", str(tmp_path)]) == 0
    assert main(["design", str(PAPER), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err
    assert main(["design", str(PAPER), "--out", str(tmp_path), "--force"]) == 0
