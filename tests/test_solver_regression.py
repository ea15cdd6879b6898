"""The mirror solver's outputs against a fixture saved before issue 16's start-up work
(tests/data/solver_regression.json).

Issue 16 replaces the solver's scipy.optimize calls (so ``nodlidar design`` does not pay
for importing scipy.optimize): every design file in design/ is solved with both placement
methods and compared field by field with the fixture - every :class:`MirrorSolution`
field (steps, targets, offset, anchor, the patch's origin, normal, along, extents), the
design's direct and shadowed steps, or the refusal message - and so is the whole
``nodlidar design FILE --method M --json`` output (the mirror table, the paper
comparison, the other method's table or refusal, density and interleave).

Tolerance: 1e-12 m for lengths and 1e-12 rad for angles (the same in degrees where a key
says ``_deg``): the anchor construction is closed form plus a root found to
``xtol=1e-15``, so its results are exact to a few ulps of ~0.1 m (~1e-17 m); 1e-12 leaves
room only for an equivalent order of floating-point operations, not for a different
optimum (a changed optimiser stops elsewhere by ~1e-9 or more). Integers and strings
(names, refusal messages) must be equal. Dimensionless floats (density gains) to a
relative 1e-12.

Regenerate the fixture (only from a trusted implementation!) with
``.venv/bin/python tests/test_solver_regression.py``.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = Path(__file__).parent / "data" / "solver_regression.json"
DESIGNS = sorted((ROOT / "design").glob("*.toml"))
METHODS = ("anchor", "optimal")
TOL_M = 1e-12      # m and rad (see the module docstring)
TOL_REL = 1e-12    # dimensionless


def _solution(path: Path, method: str) -> dict:
    """Every field of the solved design (or its refusal) as plain JSON values."""
    from nodlidar.errors import InfeasibleDesignError
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    spec = load_design(path).replace(**{"placement.method": method})
    try:
        design = solve(spec)
    except InfeasibleDesignError as exc:
        return {"refused": str(exc)}
    mirrors = []
    for m in design.mirrors:
        p = m.patch
        mirrors.append({
            "name": m.name, "side": m.side, "index": m.index,
            "steps": m.steps.tolist(), "target_bearing_rad": m.target_bearing.tolist(),
            "offset_index": m.offset_index, "anchor": m.anchor, "target_step": m.target_step,
            "patch": {"name": p.name, "origin_m": list(p.origin), "normal": list(p.normal),
                      "along": list(p.along), "s_min_m": p.s_min, "s_max_m": p.s_max,
                      "z_min_m": p.z_min, "z_max_m": p.z_max, "hinge_z_m": p.hinge_z},
        })
    return {"mirrors": mirrors, "direct_steps": design.direct_steps.tolist(),
            "shadowed_steps": design.shadowed_steps.tolist()}


def _cli_json(path: Path, method: str) -> dict:
    """``nodlidar design PATH --method METHOD --json``, run in this process: its JSON, or
    its exit status and stderr line when it refuses."""
    from nodlidar.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["design", str(path), "--method", method, "--json"])
    if rc != 0:
        return {"exit_status": rc, "stderr": err.getvalue()}
    return json.loads(out.getvalue())


def _current() -> dict:
    return {f"{p.name}:{m}": {"solution": _solution(p, m), "cli_json": _cli_json(p, m)}
            for p in DESIGNS for m in METHODS}


def _tol(key: str) -> tuple[float, float]:
    """(atol, rtol) of a float under ``key``."""
    if key.startswith("density"):
        return 0.0, TOL_REL
    if key in ("relative", "paper", "ours", "difference"):
        # the paper comparison, in its quantity's own unit (m or deg): the looser of the two
        return math.degrees(TOL_M), TOL_REL
    if "_deg" in key:
        return math.degrees(TOL_M), 0.0
    return TOL_M, 0.0


def _compare(got, want, where: str, key: str = "") -> None:
    if isinstance(want, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(want), where
        for k in want:
            _compare(got[k], want[k], f"{where}.{k}", k)
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            _compare(g, w, f"{where}[{i}]", key)
    elif isinstance(want, float):
        atol, rtol = _tol(key)
        np.testing.assert_allclose(got, want, atol=atol, rtol=rtol, err_msg=where)
    else:  # int, str, bool, None: equal
        assert got == want, where


def test_fixture_covers_every_design_file():
    """A design file added later must be added to the fixture (regenerate from a trusted
    implementation), so no file escapes the comparison."""
    want = json.loads(FIXTURE.read_text())
    assert sorted(want) == sorted(f"{p.name}:{m}" for p in DESIGNS for m in METHODS)


@pytest.mark.parametrize("path", DESIGNS, ids=lambda p: p.stem)
@pytest.mark.parametrize("method", METHODS)
def test_solver_and_cli_json_match_fixture(path, method):
    want = json.loads(FIXTURE.read_text())[f"{path.name}:{method}"]
    _compare(_solution(path, method), want["solution"], f"{path.name}:{method}.solution")
    _compare(_cli_json(path, method), want["cli_json"], f"{path.name}:{method}.cli_json")


def test_comparison_detects_a_changed_number():
    """The comparison is not vacuous: a fixture number moved by 1e-11 m fails it."""
    want = json.loads(FIXTURE.read_text())
    case = next(v for v in want.values() if "mirrors" in v["solution"])
    moved = json.loads(json.dumps(case["solution"]))
    moved["mirrors"][0]["patch"]["origin_m"][0] += 1e-11
    with pytest.raises(AssertionError):
        _compare(moved, case["solution"], "moved")


# the solver's own scalar solvers against scipy's: the same algorithm, operation for
# operation, so the same float64 answer bit for bit (which is why the fixture still holds
# to the last bit); functions chosen so both the interpolation/extrapolation and the
# bisection or golden-section branches run
ROOT_CASES = [
    (lambda x: math.cos(x) - x, 0.0, 1.0, 1e-15),
    (lambda x: x ** 3 - 2 * x - 5, 2.0, 3.0, 2e-12),
    (lambda x: math.atan(50 * (x - 0.3)), -1.0, 4.0, 1e-15),   # flat far from the root
    (lambda x: (x - 0.7) ** 3, 0.0, 1.0, 2e-12),                 # a flat, odd root
    (lambda x: math.expm1(x) - 1e-3, -2.0, 1.0, 1e-15),
    (lambda x: x - 0.25, 0.25, 1.0, 1e-15),                      # root at the bracket's end
]
MIN_CASES = [
    (lambda x: (x - 0.3) ** 2, -1.0, 1.0, 1e-12),
    (lambda x: math.cosh(x - 1.2) + 0.1 * x, 0.5, 2.5, 1e-12),
    (lambda x: abs(x - 0.123), -0.2, 0.2, 1e-12),                 # kink: minimum at the bound
    (lambda x: math.sin(3 * x) + 0.2 * x * x, -2.0, 1.0, 1e-5),
    (lambda x: (x * x - 1) ** 2, -0.2, 1.7, 1e-12),
]


@pytest.mark.parametrize("case", range(len(ROOT_CASES)))
def test_brent_root_equals_scipy_brentq(case):
    from scipy.optimize import brentq

    from nodlidar.solver import _brent_root

    f, a, b, xtol = ROOT_CASES[case]
    assert _brent_root(f, a, b, xtol=xtol) == brentq(f, a, b, xtol=xtol)


@pytest.mark.parametrize("case", range(len(MIN_CASES)))
def test_bounded_min_equals_scipy_minimize_scalar(case):
    from scipy.optimize import minimize_scalar

    from nodlidar.solver import _bounded_min

    f, a, b, xatol = MIN_CASES[case]
    want = minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": xatol}).x
    assert _bounded_min(f, a, b, xatol=xatol) == want


def test_brent_root_refuses_a_bracket_without_a_sign_change():
    from nodlidar.solver import _brent_root

    with pytest.raises(ValueError, match="different signs"):
        _brent_root(lambda x: x * x + 1, -1.0, 1.0, xtol=1e-15)


if __name__ == "__main__":
    FIXTURE.write_text(json.dumps(_current(), indent=1) + "\n")
    print(f"wrote {FIXTURE}")

