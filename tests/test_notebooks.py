"""Every notebooks/*.py (jupytext percent format) runs the way Jupyter runs it: converted to
an .ipynb notebook, executed cell by cell by nbclient in an IPython kernel started in
``notebooks/`` (so no ``__file__``, and the working directory is not the repository root).
The notebooks assert their own numbers; here we check they ran to the end, wrote their
figures to NODLIDAR_OUT and nothing into the repository."""

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NB_DIR = ROOT / "notebooks"
NOTEBOOKS = sorted(NB_DIR.glob("*.py"))
KERNEL = "nodlidar-test-python"


def _kernel_spec(tmp_path: Path) -> Path:
    """A kernel spec for this interpreter (the venv's, with nodlidar importable), in a
    directory we put first on JUPYTER_PATH, under a name no user spec can shadow."""
    share = tmp_path / "jupyter"
    spec = share / "kernels" / KERNEL
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "nodlidar test (venv python)", "language": "python"}))
    return share


def _snapshot() -> set[Path]:
    """What the kernel could write by accident: notebooks/ (its cwd) and the repo's top level."""
    return set(NB_DIR.rglob("*")) | set(ROOT.iterdir())


@pytest.mark.slow
@pytest.mark.notebook
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_under_jupyter(path, tmp_path, monkeypatch):
    import jupytext
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError

    out = tmp_path / "out"
    # the kernel inherits this process's environment
    for k, v in {"MPLBACKEND": "Agg", "NODLIDAR_OUT": str(out), "TQDM_DISABLE": "1",
                 "JUPYTER_PATH": str(_kernel_spec(tmp_path)),
                 "JUPYTER_RUNTIME_DIR": str(tmp_path / "runtime"),
                 "IPYTHONDIR": str(tmp_path / "ipython")}.items():
        monkeypatch.setenv(k, v)
    nb = jupytext.read(path)   # percent script -> nbformat v4 notebook, as `jupytext --to ipynb`
    assert sum(c.cell_type == "code" for c in nb.cells) >= 3
    # a last cell reporting where the kernel ran and with which interpreter
    import nbformat

    nb.cells.append(nbformat.v4.new_code_cell("import os, sys\nprint(os.getcwd())\nprint(sys.executable)"))
    before = _snapshot()
    client = NotebookClient(nb, kernel_name=KERNEL, timeout=600,
                            resources={"metadata": {"path": str(NB_DIR)}})  # kernel cwd, as Jupyter
    try:
        client.execute()
    except CellExecutionError as exc:   # the failing cell and its traceback
        pytest.fail(f"{path.name} failed under nbclient:\n{str(exc)[-4000:]}")
    # every code cell ran, in order, and none left an error output
    counts = [c.execution_count for c in nb.cells if c.cell_type == "code"]
    assert counts == list(range(1, len(counts) + 1))
    assert not [o for c in nb.cells if c.cell_type == "code" for o in c.outputs
                if o.output_type == "error"]
    # the kernel really ran in notebooks/ with the test's interpreter
    cwd, exe = nb.cells[-1].outputs[0]["text"].split("\n")[:2]
    assert Path(cwd) == NB_DIR and Path(exe) == Path(sys.executable)

    pngs = {p.name for p in out.glob("*.png")}
    if path.stem.startswith("01_"):
        assert len(pngs) >= 5
    if path.stem.startswith("02_"):  # Figure 9 calibrated/uncalibrated, histograms; the file
        assert {"fig9_calibrated.png", "fig9_uncalibrated.png", "residual_histograms.png"} <= pngs
        assert (out / "calibration.toml").stat().st_size > 0
    if path.stem.startswith("03_"):  # Figures 10-13 analogues, the table, the static 3D cloud
        assert {"fig10_12_accumulated_clouds.png", "fig13_convergence.png",
                "segmentation_scan.png", "cloud_3d.png"} <= pngs
        assert "| mirrors | renyi |" in (out / "study_mirrors.md").read_text()
    # nothing written into the repository (other than bytecode caches)
    new = [p for p in _snapshot() - before if "__pycache__" not in p.parts]
    assert not new, new
