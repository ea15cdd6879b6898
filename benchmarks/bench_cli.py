"""Start-up of the command line: ``nodlidar --help`` and ``nodlidar design`` (the paper's
build, table output), wall time of a fresh process, the min of several runs (the least
disturbed by other load on a shared machine).

Baselines measured in the same run: a bare ``python -c pass`` of the same interpreter (what
no command can go below), and a fresh ``import scipy.optimize`` (what ``design`` paid for
its solvers before issue 16: ``brentq``, ``minimize_scalar`` and SLSQP; the solver now has
its own scalar searches and ``design`` imports no scipy at all, which
``cli.design_imports_scipy`` checks: 0 or 1, from a fresh process's ``sys.modules``).

Goals (issue 16): ``--help`` <= 0.25 s, ``design`` <= 0.6 s. Figures under
``benchmarks/run.py cli``: ``cli.help_s``, ``cli.design_s``, ``cli.python_s``,
``cli.help_over_python_s``, ``cli.design_over_python_s``, ``cli.scipy_optimize_import_s``,
``cli.design_imports_scipy``.

Run: ``.venv/bin/python benchmarks/bench_cli.py``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "design" / "urg04lx-paper.toml"
RUNS = 7


def _nodlidar() -> list[str]:
    """The installed console script next to this interpreter, else ``python -m``."""
    script = Path(sys.executable).with_name("nodlidar")
    return [str(script)] if script.exists() else [sys.executable, "-m", "nodlidar.cli"]


def wall(cmd: list[str], runs: int = RUNS) -> float:
    """Min wall time [s] of ``runs`` fresh processes of ``cmd`` (output discarded)."""
    env = dict(os.environ, MPLBACKEND="Agg")
    best = float("inf")
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True,
                       env=env, cwd=ROOT)
        best = min(best, time.perf_counter() - t0)
    return best


def design_imports_scipy() -> bool:
    """Whether ``nodlidar design PAPER`` (run in a fresh interpreter) imports any scipy."""
    code = ("import contextlib, io, sys\n"
            "from nodlidar.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    main(['design', {str(PAPER)!r}])\n"
            "print(any(m.split('.')[0] == 'scipy' for m in sys.modules))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       check=True, cwd=ROOT, env=dict(os.environ, MPLBACKEND="Agg"))
    return p.stdout.strip() == "True"


def main() -> dict[str, float]:
    cli = _nodlidar()
    py = wall([sys.executable, "-c", "pass"])
    t_help = wall([*cli, "--help"])
    t_design = wall([*cli, "design", str(PAPER)])
    t_scipy = wall([sys.executable, "-c", "import scipy.optimize"]) - py
    scipy_used = design_imports_scipy()
    print(f"fresh processes, min of {RUNS}:")
    print(f"  python -c pass        : {py:6.3f} s")
    print(f"  nodlidar --help       : {t_help:6.3f} s  (goal <= 0.25 s; "
          f"{t_help - py:6.3f} s over the interpreter)")
    print(f"  nodlidar design PAPER : {t_design:6.3f} s  (goal <= 0.6 s; "
          f"{t_design - py:6.3f} s over the interpreter)")
    print(f"  import scipy.optimize : {t_scipy:6.3f} s  (over the interpreter; design "
          f"imports {'some' if scipy_used else 'no'} scipy)")
    return {"help_s": t_help, "design_s": t_design, "python_s": py,
            "help_over_python_s": t_help - py, "design_over_python_s": t_design - py,
            "scipy_optimize_import_s": t_scipy, "design_imports_scipy": float(scipy_used)}


if __name__ == "__main__":
    main()
