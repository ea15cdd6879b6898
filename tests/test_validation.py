"""The shared validation layer (nodlidar.validation, commands/_args) and the design-file
checks built on it: each repro of issue 15 is now one clean typed error naming the file
and the field."""

from __future__ import annotations

import argparse
import os
import threading
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest
import tomli_w
from hypothesis import given, settings
from hypothesis import strategies as st

from nodlidar.commands._args import bounded_float, bounded_int, check_output_path, safe_name
from nodlidar.errors import (
    DesignFileError,
    InputFileError,
    NodlidarError,
    ParameterError,
    UnknownKeyError,
)
from nodlidar.paper import PAPER_DESIGN
from nodlidar.spec import design_from_dict, load_design
from nodlidar.validation import check_fields, check_keys, check_number, check_value, read_toml

BASE = Path(PAPER_DESIGN).read_text()


# ---------------------------------------------------------------------------------------
# read_toml


def _one_line(exc: BaseException) -> str:
    msg = str(exc)
    assert "\n" not in msg
    return msg


def test_read_toml_reads_what_an_independent_writer_wrote(tmp_path):
    data = {"name": "x", "a": {"b": [1.5, 2.0], "c": True, "d": "é"}}
    p = tmp_path / "x.toml"
    p.write_text(tomli_w.dumps(data), encoding="utf-8")
    assert read_toml(p, "test") == data


def test_read_toml_refuses_a_fifo_without_blocking(tmp_path):
    fifo = tmp_path / "scene.toml"
    os.mkfifo(fifo)
    box: dict = {}

    def run():
        try:
            read_toml(fifo, "scene")
        except NodlidarError as exc:
            box["exc"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout=10)  # returns at once; a blocking open would wait for a writer forever
    assert not t.is_alive(), "read_toml blocked on a FIFO"
    assert isinstance(box["exc"], InputFileError)
    assert str(fifo) in _one_line(box["exc"]) and "FIFO" in str(box["exc"])


@pytest.mark.parametrize("content, needle", [
    (b'name = "\xff\xfe"\n', "not UTF-8"),
    (b'name = "a"\n\x00\n', "NUL"),
    (b"[layout\n", "malformed TOML"),
    (b"x" * 2000, "bytes"),
])
def test_read_toml_refusals_name_the_file(tmp_path, content, needle):
    p = tmp_path / "bad.toml"
    p.write_bytes(content)
    with pytest.raises(InputFileError) as e:
        read_toml(p, "design", max_bytes=1000)
    assert needle in _one_line(e.value) and str(p) in str(e.value)


def test_read_toml_missing_and_directory(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_toml(tmp_path / "nope.toml", "design")
    with pytest.raises(InputFileError, match="is a directory"):
        read_toml(tmp_path, "design")
    with pytest.raises(DesignFileError):  # the caller chooses the error type
        read_toml(tmp_path, "design", error=DesignFileError)


# ---------------------------------------------------------------------------------------
# strict fields


@dataclass(frozen=True)
class _Demo:
    x_m: float
    n: int = 1
    on: bool = True
    label: str = ""
    pair: tuple[float, float] = (0.0, 0.0)
    many: tuple[float, ...] = ()


@pytest.mark.parametrize("table, field, allowed", [
    ({"x_m": True}, "x_m", "finite number"),
    ({"x_m": "1"}, "x_m", "finite number"),
    ({"x_m": float("nan")}, "x_m", "finite number"),
    ({"x_m": float("inf")}, "x_m", "finite number"),
    ({"x_m": 1, "n": 2.5}, "n", "integer"),
    ({"x_m": 1, "n": False}, "n", "integer"),
    ({"x_m": 1, "on": "false"}, "on", "true or false"),
    ({"x_m": 1, "on": 0}, "on", "true or false"),
    ({"x_m": 1, "label": "a\x00b"}, "label", "control"),
    ({"x_m": 1, "pair": [1.0]}, "pair", "2 values"),
    ({"x_m": 1, "pair": [1.0, float("nan")]}, "pair[1]", "finite"),
    ({"x_m": 1, "many": [1.0, "2"]}, "many[1]", "finite number"),
])
def test_check_fields_refuses_wrong_types(table, field, allowed):
    with pytest.raises(ParameterError) as e:
        check_fields(_Demo, table, "demo", "f.toml")
    assert e.value.field == f"demo.{field}"
    assert allowed in e.value.allowed and "f.toml" in e.value.allowed


def test_check_fields_converts_and_bounds():
    kw = check_fields(_Demo, {"x_m": 2, "pair": [1, 2], "many": 3.0}, "demo")
    assert kw == {"x_m": 2.0, "pair": (1.0, 2.0), "many": (3.0,)}
    assert type(kw["x_m"]) is float
    with pytest.raises(ParameterError, match=r"0 .. 1 m"):
        check_fields(_Demo, {"x_m": 1.5}, "demo", bounds={"x_m": (0, 1, "m")})
    with pytest.raises(ParameterError, match="demo.many"):
        check_fields(_Demo, {"x_m": 0.5, "many": [0.1, 7]}, "demo", bounds={"many": (0, 1, "m")})
    with pytest.raises(DesignFileError, match="missing x_m"):
        check_fields(_Demo, {}, "demo")


def test_unknown_keys_suggest_the_nearest_valid_name():
    with pytest.raises(UnknownKeyError) as e:
        check_keys({"tolerence": {}}, ["tolerance", "cad"], "", "x.toml", sections=True)
    assert str(e.value) == "unknown section [tolerence] in x.toml; did you mean [tolerance]?"
    with pytest.raises(UnknownKeyError) as e:
        check_keys({"chian": True}, ["chain", "method"], "placement", "x.toml")
    assert str(e.value) == "unknown key placement.chian in x.toml; did you mean placement.chain?"
    with pytest.raises(UnknownKeyError, match="allowed: placement.chain, placement.method"):
        check_keys({"zzzz": 1}, ["chain", "method"], "placement")
    with pytest.raises(ParameterError, match="a table"):
        check_keys([1, 2], ["a"], "placement")


def test_check_number():
    assert check_number(3, "n", lo=1, hi=5, integer=True) == 3
    assert check_number(2.0, "x", lo=0, lo_open=True) == 2.0
    for bad in (0, float("nan"), True, "1", 1e9):
        with pytest.raises(ParameterError, match="x = "):
            check_number(bad, "x", lo=0, hi=1e6, lo_open=True)
    with pytest.raises(ParameterError, match="an integer"):
        check_number(2.5, "n", integer=True)


def test_check_value_optional():
    assert check_value(None, float | None, "x") is None
    with pytest.raises(ParameterError):
        check_value(True, float | None, "x")


# ---------------------------------------------------------------------------------------
# design files: every repro of issue 15


def _design(tmp_path, old, new):
    assert old in BASE, old
    p = tmp_path / "d.toml"
    p.write_text(BASE.replace(old, new, 1))
    return p


@pytest.mark.parametrize("old, new, exc, needle", [
    ("chain = false", 'chain = "false"', ParameterError, "placement.chain = 'false'"),
    ("design_distance_m = 2.0", "design_distance_m = true", ParameterError,
     "layout.design_distance_m = True"),
    ("windows = 3", "windows = 3.0", ParameterError, "layout.windows"),
    ("[tolerance]\n", "[tolerence]\n", UnknownKeyError, "did you mean [tolerance]?"),
    ("[calibration]\n", "[calibraton]\n", UnknownKeyError, "did you mean [calibration]?"),
    ("[cad]\n", "[cadd]\n", UnknownKeyError, "did you mean [cad]?"),
    ("description =", "descripton =", UnknownKeyError, "did you mean description?"),
    ("chain = false", "chian = false", UnknownKeyError, "did you mean placement.chain?"),
    ("hinge_z_m = -0.025", "hinge_z_m = 1e9", ParameterError, "mirror.hinge_z_m"),
    ("pivot_m = [0.0, 0.0, 0.0]", "pivot_m = [nan, 0.0, 0.0]", ParameterError, "nod.pivot_m[0]"),
    ("pivot_m = [0.0, 0.0, 0.0]", "pivot_m = [0.0, 0.0]", ParameterError, "nod.pivot_m"),
    ("pivot_m = [0.0, 0.0, 0.0]", "pivot_m = [5.0, 0.0, 0.0]", ParameterError, "nod.pivot_m"),
    ("rate_rad_s = 0.35", "rate_rad_s = 1e-9", ParameterError, "nod.rate_rad_s"),
    ('name = "urg04lx-paper"', 'name = ".."', ParameterError, "name = '..'"),
    ('name = "urg04lx-paper"', 'name = "a\\\\b"', ParameterError, "name = "),
    ('name = "urg04lx-paper"', 'name = "a\\u0000b"', ParameterError, "control characters"),
    ('name = "urg04lx-paper"', "name = 3", ParameterError, "a string"),
    ('dalpha_rad = 0.001', 'dalpha_rad = true', ParameterError, "tolerance.dalpha_rad"),
    ('samples = 10000', 'sample = 10000', UnknownKeyError, "did you mean tolerance.samples?"),
])
def test_design_repros_are_refused_naming_file_and_field(tmp_path, old, new, exc, needle):
    p = _design(tmp_path, old, new)
    with pytest.raises(exc) as e:
        load_design(p)
    msg = _one_line(e.value)
    assert needle in msg and str(p) in msg, msg


def test_paper_design_loads_and_round_trips_through_an_independent_writer():
    spec = load_design(PAPER_DESIGN)
    # tomli_w writes, tomllib reads: the strict loader accepts what the spec itself wrote
    assert design_from_dict(tomllib.loads(tomli_w.dumps(spec.to_dict()))) == spec


def test_scalar_standoff_is_still_one_value():
    data = tomllib.loads(BASE)
    data["placement"]["standoff_m"] = 0.03
    assert design_from_dict(data).placement.standoff_m == (0.03,)


# ---------------------------------------------------------------------------------------
# commands/_args


def _parser(**kw):
    p = argparse.ArgumentParser(exit_on_error=False)
    p.add_argument("--x", **kw)
    return p


@pytest.mark.parametrize("text", ["1e-9", "inf", "nan", "-1", "2000", "abc"])
def test_bounded_float_refuses(text):
    p = _parser(type=bounded_float(0.01, 1000))
    with pytest.raises(argparse.ArgumentError) as e:
        p.parse_args(["--x", text])
    assert "--x" in str(e.value) and "0.01 .. 1000" in str(e.value)


def test_bounded_float_accepts_and_open_bound():
    assert _parser(type=bounded_float(0.01, 1000)).parse_args(["--x", "5"]).x == 5.0
    p = _parser(type=bounded_float(0, None, lo_open=True))
    assert p.parse_args(["--x", "1e300"]).x == 1e300
    with pytest.raises(argparse.ArgumentError, match="> 0"):
        p.parse_args(["--x", "0"])


@pytest.mark.parametrize("text", ["1e11", "-1", "0", "2.5", "x", "inf"])
def test_bounded_int_refuses(text):
    p = _parser(type=bounded_int(1, 1_000_000))
    with pytest.raises(argparse.ArgumentError) as e:
        p.parse_args(["--x", text])
    assert "--x" in str(e.value) and "1 .. 1000000" in str(e.value)


def test_bounded_int_accepts_exponent_notation():
    p = _parser(type=bounded_int(1, 1_000_000))
    assert p.parse_args(["--x", "1e5"]).x == 100_000
    assert p.parse_args(["--x", "12"]).x == 12


def test_check_output_path(tmp_path):
    f = tmp_path / "a.ply"
    assert check_output_path(f, force=False) == f            # new file in an existing dir
    f.write_text("x")
    with pytest.raises(ParameterError, match="--force"):
        check_output_path(f, force=False)
    assert check_output_path(f, force=True) == f
    with pytest.raises(ParameterError, match="not an existing directory"):
        check_output_path(tmp_path, force=True)
    with pytest.raises(ParameterError, match="does not exist"):
        check_output_path(tmp_path / "no" / "a.ply", force=True)
    with pytest.raises(ParameterError, match="is a file"):
        check_output_path(f / "b.ply", force=True)
    with pytest.raises(ParameterError, match="--cloud"):
        check_output_path(f, force=False, option="--cloud")
    with pytest.raises(ParameterError, match="not an existing file"):
        check_output_path(f, force=True, kind="directory")
    assert check_output_path(tmp_path / "bag", force=False, kind="directory")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_check_output_path_unwritable_parent(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(ParameterError, match="not writable"):
            check_output_path(ro / "x.ply", force=False)
    finally:
        ro.chmod(0o700)


@pytest.mark.parametrize("name", ["", ".", "..", "a/b", "../x", "a\\b", "-rf", " a", "a\nb",
                                  "a\x00b"])
def test_safe_name_refuses(name):
    with pytest.raises(ParameterError):
        safe_name(name)


@settings(max_examples=300, deadline=None)
@given(st.text(min_size=1, max_size=20))
def test_safe_name_never_escapes_the_folder(tmp_path_factory, name):
    # every name safe_name accepts is exactly one component directly inside the root
    root = tmp_path_factory.getbasetemp() / "root"
    try:
        ok = safe_name(name)
    except ParameterError:
        return
    target = root / ok
    assert os.path.normpath(target).startswith(str(root) + os.sep)
    assert Path(os.path.normpath(target)).parent == root


# ---------------------------------------------------------------------------------------
# tolerance: bounds, the Dask scheduler, Ctrl-C


def test_tolerance_table_bounds():
    from nodlidar.analysis.tolerance import MAX_SAMPLES, ToleranceSpec, tolerance_spec

    with pytest.raises(ParameterError, match="tolerance.samples"):
        ToleranceSpec(samples=MAX_SAMPLES + 1)
    with pytest.raises(ParameterError, match="tolerance.dalpha_rad"):
        tolerance_spec({"dalpha_rad": 1.0})
    with pytest.raises(ParameterError, match="tolerance.lidar.offset_m"):
        tolerance_spec({"lidar": {"offset_m": 1.0}})
    with pytest.raises(ParameterError, match="tolerance.ranges_m"):
        tolerance_spec({"ranges_m": [1e9]})
    with pytest.raises(UnknownKeyError, match="did you mean tolerance.lidar.yaw_rad"):
        tolerance_spec({"lidar": {"yaw_rd": 0.001}})


def test_scheduler_refusals_are_quick_and_name_the_address():
    import http.server
    import time

    from nodlidar.analysis.tolerance import _check_scheduler

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        http_addr = f"tcp://127.0.0.1:{srv.server_address[1]}"
        for addr, needle in (("not a url", "port"), (http_addr, "no answer"), ("", "Dask"),
                             ("foo://127.0.0.1:1", "scheme")):
            t0 = time.monotonic()
            with pytest.raises(ParameterError, match=needle) as e:
                _check_scheduler(addr, timeout_s=2.0)
            # the HTTP server waits for a request that never comes: refused at the timeout
            assert time.monotonic() - t0 < 10.0
            assert e.value.field == "scheduler" and e.value.value == addr
    finally:
        srv.shutdown()


@pytest.mark.slow
def test_scheduler_accepts_a_real_scheduler():
    from distributed import LocalCluster

    from nodlidar.analysis.tolerance import _check_scheduler

    with LocalCluster(n_workers=0, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster:
        _check_scheduler(cluster.scheduler_address, timeout_s=10.0)  # no exception


def _group_workers(pgid: int) -> int:
    """Dask worker processes (multiprocessing spawn) in process group ``pgid``."""
    n = 0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if os.getpgid(int(d.name)) != pgid:
                continue
            if b"spawn_main" in (d / "cmdline").read_bytes():
                n += 1
        except (OSError, ProcessLookupError):
            continue
    return n


def _ignores_sigint(pid: int) -> bool:
    """Whether process ``pid`` ignores SIGINT (bit 1 of SigIgn in /proc/PID/status)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            return bool(int(line.split()[1], 16) & (1 << (2 - 1)))
    return False


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to see the workers")
def test_ctrl_c_with_dask_workers_is_one_line(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    exe = Path(sys.executable).with_name("nodlidar")
    p = subprocess.Popen([str(exe), "tolerance", str(PAPER_DESIGN), "--samples", "400000",
                          "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, start_new_session=True, stdin=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        # Ctrl-C goes to the whole foreground group: wait until both workers exist and the
        # cluster is up (the main process ignores SIGINT while it starts them)
        while (_group_workers(p.pid) < 2 or _ignores_sigint(p.pid)) and p.poll() is None \
                and time.monotonic() < deadline:
            time.sleep(0.2)
        assert p.poll() is None and _group_workers(p.pid) == 2, "workers did not start"
        assert not _ignores_sigint(p.pid)
        os.killpg(p.pid, signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip()]
    assert p.returncode == 130, err[-2000:]
    assert lines == ["nodlidar tolerance: interrupted"], err[-2000:]


EXACT = Path(PAPER_DESIGN)  # the default design is the per-mirror (exact) reading


@pytest.mark.skipif(not EXACT.is_file(), reason="no per-mirror design file")
@pytest.mark.parametrize("old, new, needle", [
    ("standoff_m = 0.02", "standoff_m = true", "placement.mirrors[0].standoff_m = True"),
    ("target_offset = 1\n", 'target_offset = "1"\n', "placement.mirrors[0].target_offset = '1'"),
    ("anchor_step = 725", "anchr_step = 725",
     "did you mean placement.mirrors[0].anchor_step?"),
])
def test_nested_tables_get_the_same_strict_checks(tmp_path, old, new, needle):
    text = EXACT.read_text()
    assert old in text
    p = tmp_path / "x.toml"
    p.write_text(text.replace(old, new, 1))
    with pytest.raises(ParameterError) as e:
        load_design(p)
    assert needle in _one_line(e.value) and str(p) in str(e.value)
    load_design(EXACT)  # the unedited file loads


@pytest.mark.parametrize("bad", ["..", ".", "a/b", "a\\b", "x\ny", "-rf"])
def test_design_name_made_in_code_cannot_escape_an_output_folder(bad):
    """The name becomes cad_out/<name> and out/report/<name>: DesignSpec itself refuses
    names that are not one safe path component, not only the file loader."""
    import dataclasses

    from nodlidar.paper import PAPER_DESIGN
    from nodlidar.spec import load_design

    spec = load_design(PAPER_DESIGN)
    with pytest.raises(ParameterError, match="name"):
        dataclasses.replace(spec, name=bad)


def test_parameter_errors_survive_pickling():
    # a worker process's error reaches the parent through pickle (multiprocessing): before,
    # unpickling called ParameterError(message) and died with a TypeError, and the harness
    # lost the error and the run (benchmarks/study_scenes.py: "BrokenProcessPool")
    import pickle

    for e in (ParameterError("scene.file", "x.toml", "an existing file"),
              UnknownKeyError("unknown key foo in x.toml", "foo", "foo", "bar, baz")):
        back = pickle.loads(pickle.dumps(e))
        assert type(back) is type(e) and str(back) == str(e)
        assert (back.field, back.value, back.allowed) == (e.field, e.value, e.allowed)
