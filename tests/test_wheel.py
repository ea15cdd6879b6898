"""nodlidar as a normal (non-editable) install: build the wheel offline, install it into a
fresh venv, and run the CLI from an empty directory - the design files come from the
package (importlib.resources), not from the checkout."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
IGNORE = shutil.ignore_patterns(".venv", ".git", "build", "dist", "*.egg-info", "cad_out", "out",
                                "__pycache__", ".pytest_cache", ".ruff_cache", ".mypy_cache",
                                ".ipynb_checkpoints")


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, **kw)
    assert r.returncode == 0, f"{cmd}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    # setuptools < 70.1 builds wheels through the `wheel` package (build-system.requires);
    # offline (--no-isolation) it must be in this environment
    if importlib.util.find_spec("wheel") is None:
        pytest.skip("the build requirement `wheel` is not installed in this environment "
                    "(pyproject [build-system] requires it; add it to the dev extra)")
    tmp = tmp_path_factory.mktemp("wheel")
    # build from a copy: an in-tree build writes build/ and *.egg-info into the checkout
    src = tmp / "src"
    shutil.copytree(ROOT, src, symlinks=True, ignore=IGNORE)
    # --skip-dependency-check: build-system.requires pins setuptools>=68; whatever this
    # environment has builds it if it has `wheel` (the contents are checked below)
    _run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--skip-dependency-check",
          "--outdir", str(tmp / "dist")], cwd=src)
    (whl,) = (tmp / "dist").glob("nodlidar-*.whl")
    return whl


def test_wheel_contents(wheel):
    """Every module of the package, the design files and the scenes are in the wheel."""
    names = set(zipfile.ZipFile(wheel).namelist())
    pkg = ROOT / "nodlidar"
    modules = {p.relative_to(ROOT).as_posix() for p in pkg.rglob("*.py")
               if "designs" not in p.relative_to(pkg).parts[:1]}
    assert modules <= names, sorted(modules - names)
    designs = {f"nodlidar/designs/{p.relative_to(ROOT / 'design').as_posix()}"
               for p in (ROOT / "design").rglob("*.toml")}
    assert "nodlidar/designs/urg04lx-paper.toml" in designs and any("/scenes/" in d for d in designs)
    assert designs <= names, sorted(designs - names)
    assert "nodlidar/py.typed" in names
    assert not [n for n in names if n.startswith(("nodlidar/data/", "design/", "tests/"))]


@pytest.mark.slow
def test_installed_wheel_runs_from_an_empty_directory(wheel, tmp_path):
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    py = venv / "bin" / "python"
    site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"])
                .stdout.strip())
    # the dependencies from this environment (nothing is downloaded) - appended after the
    # new venv's own site-packages, and as a plain path: this environment's .pth files
    # (the editable install's finder) are not run, so `nodlidar` can only be the wheel's
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
          "--disable-pip-version-check", "--quiet", str(wheel)])

    empty = tmp_path / "empty"
    empty.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["MPLBACKEND"] = "Agg"
    probe = _run([str(py), "-c", "import nodlidar, nodlidar.paper as p; print(nodlidar.__file__); "
                  "print(p.PAPER_DESIGN); print(p.PAPER_DESIGN.is_file())"], cwd=empty, env=env)
    mod, design, exists = probe.stdout.split("\n")[:3]
    assert Path(mod).is_relative_to(site), mod          # the wheel's copy, not the checkout
    assert Path(design).is_relative_to(site) and exists == "True", design

    nodlidar = str(venv / "bin" / "nodlidar")
    version = _run([nodlidar, "--version"], cwd=empty, env=env).stdout.strip()
    assert version.startswith("nodlidar ") and "unknown" not in version
    table = _run([nodlidar, "design", design], cwd=empty, env=env).stdout
    assert "L1" in table and "R2" in table
    scan = _run([nodlidar, "-q", "scan", "--out", "x.ply", "--sim-rate", "5", "--json"],
                cwd=empty, env=env)
    info = json.loads(scan.stdout)
    assert info["design"] == "urg04lx-paper" and info["points"] > 10_000
    assert (empty / "x.ply").stat().st_size > info["points"] * 12
    # nothing but the output in the working directory
    assert sorted(p.name for p in empty.iterdir()) == ["x.ply"]


def test_packaged_designs_and_scenes_by_name():
    """The package's designs/scenes are the repository's design/ files (one copy), and a
    shipped scene loads by its bare name (what works after a wheel install)."""
    from nodlidar.paper import PAPER_DESIGN, design_resource
    from nodlidar.sim.scene import Scene, load_scene

    assert PAPER_DESIGN.read_bytes() == (ROOT / "design" / "urg04lx-paper.toml").read_bytes()
    scenes = sorted((ROOT / "design" / "scenes").glob("*.toml"))
    assert scenes
    for path in scenes:
        assert design_resource(f"scenes/{path.name}").read_bytes() == path.read_bytes()
        by_name, by_path = load_scene(path.stem), Scene.from_toml(path)
        assert repr(by_name) == repr(by_path), path.stem
