"""The solver against independent computations: exact traces, triangle geometry,
continuity, invariances and the BeamModel round trip."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar import lidar as lidar_mod
from nodlidar.closed_form import eq1_bearing_from_range, eq1_bearing_on_arc
from nodlidar.errors import InfeasibleDesignError, ParameterError
from nodlidar.geometry import Perturbation, bearing_of
from nodlidar.solver import solve, window_steps
from nodlidar.spec import load_design
from nodlidar.verify import verify

ROOT = Path(__file__).resolve().parents[1]
# the chained, equal-split reading (these tests exercise chaining and the auto split)
PAPER = ROOT / "design" / "urg04lx-paper-chained.toml"


@pytest.fixture(scope="module")
def spec():
    return load_design(PAPER)


@pytest.fixture(scope="module", params=["anchor", "optimal"])
def design(request, spec):
    return solve(spec.replace(**{"placement.method": request.param}))


def test_windows_partition_the_valid_steps(spec):
    r, m, left = window_steps(spec.lidar_model, 3)
    assert (r[0], r[-1], m[0], m[-1], left[0], left[-1]) == (44, 270, 271, 498, 499, 725)


def test_every_beam_hits_its_own_mirror_and_nothing_is_blocked(design):
    v = verify(design)
    assert v.n_blocked == 0
    assert np.array_equal(v.hit, design.mirror_of_step)


def test_targets_interleave_at_a_third_of_a_step(design):
    # Every reflected target sits q/3 of a step anticlockwise of a direct beam, and no
    # two beams share a slot.
    lid = design.lidar
    frac = lid.step_from_bearing(design.target_bearing) - lid.step_front
    q = np.round((frac - np.floor(frac + 1e-9)) * 3).astype(int) % 3
    for m in design.mirrors:
        assert np.all(q[m.steps - lid.step_min] == m.offset_index)
    slots = np.round(lid.step_from_bearing(design.target_bearing) * 3).astype(int)
    assert len(np.unique(slots)) == lid.n_steps


def test_anchor_beams_land_exactly_on_target(spec):
    design = solve(spec)
    v = verify(design)
    for m in design.mirrors:
        i = m.anchor_step - design.lidar.step_min
        # exact construction: only rounding error (1e-12 rad ~ 2e-12 m at 2 m)
        assert abs(v.error[i]) < 1e-12, m.name


def test_oa_is_the_perpendicular_distance_of_the_anchor_reflection(spec):
    # OA in the file -> triangle ZOM (solver) -> mirror; measured back from the exact
    # reflected ray by a cross product.
    design = solve(spec)
    for m in design.mirrors:
        if m.index == 1:
            assert_allclose(m.oa_m, spec.placement.standoff_m[0], rtol=1e-12)


def test_chained_mirrors_meet_without_a_gap(design):
    for side in "LR":
        m1, m2 = design.mirror(f"{side}1"), design.mirror(f"{side}2")
        e1 = m1.patch.point(np.array([m1.patch.s_min, m1.patch.s_max]))
        e2 = m2.patch.point(np.array([m2.patch.s_min, m2.patch.s_max]))
        gap = np.min(np.linalg.norm(e1[:, None] - e2[None], axis=-1))
        assert gap < 1e-12


def test_eq1_matches_the_exact_trace_at_many_ranges(design):
    # Eq. 1 is exact plane geometry: agreement to round-off (1e-9 rad asked; we see ~1e-14).
    lid = design.lidar
    bm = design.beam_model()
    for D in (0.4, 1.0, 2.0, 6.0):
        for m in design.mirrors:
            th = lid.bearing_from_step(m.steps)
            closed = eq1_bearing_on_arc(th, m.incidence_rad, m.hit_ranges_m, D, m.sign)
            start, d, off = bm.rays(m.steps)
            # where the exact reflected ray crosses |p| = D, from the BeamModel's rays
            b = 2 * np.sum(start[:, :2] * d[:, :2], 1)
            c = np.sum(start[:, :2] ** 2, 1) - D**2
            t = (-b + np.sqrt(b * b - 4 * np.sum(d[:, :2] ** 2, 1) * c)) / (2 * np.sum(d[:, :2] ** 2, 1))
            exact = bearing_of(start + t[:, None] * d)
            assert_allclose(closed, exact, rtol=0, atol=1e-9)
            # and the measured-range form recovers D and the bearing
            theta_a, Dr = eq1_bearing_from_range(th, m.incidence_rad, m.hit_ranges_m, off + t, m.sign)
            assert_allclose(Dr, D, rtol=1e-12)
            assert_allclose(theta_a, exact, atol=1e-9)


def test_round_trip_design_trace_beammodel(design):
    # design -> exact finite-patch trace (verify) -> total path to the arc -> BeamModel
    # points: the point is on the arc, at the traced bearing.
    v = verify(design)
    bm = design.beam_model()
    steps = design.lidar.steps
    start, d, off = bm.rays(steps)
    b = 2 * np.sum(start[:, :2] * d[:, :2], 1)
    c = np.sum(start[:, :2] ** 2, 1) - 4.0
    t = (-b + np.sqrt(b * b - 4 * c)) / 2
    p = bm.points(steps, off + t)
    assert_allclose(np.linalg.norm(p[:, :2], axis=1), 2.0, rtol=1e-12)
    assert_allclose(bearing_of(p), v.bearing_at_d, atol=1e-12)


def test_nod_rotates_points_about_the_pivot(design):
    bm = design.beam_model()
    steps = design.lidar.steps[::50]
    r = np.full(len(steps), 3.0)
    p0 = bm.points(steps, r)
    nod = np.linspace(-0.3, 0.3, len(steps))
    p = bm.points(steps, r, nod)
    from nodlidar.geometry import rot_y

    assert_allclose(p, np.einsum("nij,nj->ni", rot_y(nod), p0), atol=1e-12)


def test_lifted_mirrors_leave_every_beam_direct(design):
    bm = design.beam_model(mirrors_deployed=False)
    steps = design.lidar.steps
    p = bm.points(steps, np.ones(len(steps)))
    assert_allclose(bearing_of(p), design.lidar.bearing_from_step(steps), atol=1e-15)


def test_perturbation_changes_the_beam_model_but_not_the_assignment(spec):
    design = solve(spec)
    pert = {"L1": Perturbation(dalpha=-0.043, dbeta=0.05, dd=0.01)}
    a, b = design.beam_model(), design.beam_model(pert)
    assert np.array_equal(a.mirror_of_step, b.mirror_of_step)
    sel = design.mirror("L1").steps
    r = np.full(len(sel), 2.0)
    z = b.points(sel, r)[:, 2]
    # tilt 0.05 rad lifts the reflected beams out of plane by ~2*dbeta*(path after mirror)
    assert np.all(np.abs(z) > 0.05 * (2.0 - 0.2))
    assert_allclose(a.points(sel, r)[:, 2], 0, atol=1e-15)


def test_design_scales_with_d_and_the_head(spec, monkeypatch):
    # Similar triangles: scaling D, the standoff and the head/clearance by s scales every
    # length by s and leaves every angle unchanged.
    base = lidar_mod.LIDAR_MODELS["URG-04LX"]
    big = replace(base, name="URG-BIG", head_radius_m=base.head_radius_m * 2)
    monkeypatch.setitem(lidar_mod.LIDAR_MODELS, "URG-BIG", big)
    a = solve(spec)
    b = solve(spec.replace(lidar="URG-BIG", **{
        "layout.design_distance_m": 4.0, "placement.standoff_m": [spec.placement.standoff_m[0] * 2],
        "placement.clearance_m": spec.placement.clearance_m * 2,
        "mirror.glass_height_m": spec.mirror.glass_height_m * 2,
        "mirror.hinge_z_m": spec.mirror.hinge_z_m * 2}))
    for ma, mb in zip(a.mirrors, b.mirrors):
        assert_allclose(mb.beam_span_m, 2 * ma.beam_span_m, rtol=1e-9)
        assert_allclose(mb.phi_rad, ma.phi_rad, atol=1e-10)
        assert_allclose(mb.patch.normal_, ma.patch.normal_, atol=1e-10)


def test_optimal_beats_anchor_and_respects_clearance(spec):
    a = verify(solve(spec)).summary()
    o_design = solve(spec.replace(**{"placement.method": "optimal"}))
    o = verify(o_design).summary()
    for name in a:
        assert o[name]["rms_error_rad"] < 0.7 * a[name]["rms_error_rad"], name
    for m in o_design.mirrors:
        # reflected rays clear the optical head (the constraint the optimiser honours)
        assert m.oa_m >= o_design.lidar.head_radius_m - 1e-9


def test_k5_is_supported(spec):
    d = solve(spec.replace(**{"layout.windows": 5, "layout.mirrors_per_side": 4}))
    assert [m.name for m in d.mirrors] == ["L1", "L2", "L3", "L4", "R1", "R2", "R3", "R4"]
    assert verify(d).n_blocked == 0
    frac = d.lidar.step_from_bearing(d.target_bearing) * 5
    assert_allclose(frac, np.round(frac), atol=1e-9)  # fifths of a step


@pytest.mark.parametrize("changes, match", [
    ({"layout.windows": 5, "layout.mirrors_per_side": 2}, "blocked"),
    ({"layout.mirrors_per_side": 1}, "blocked"),
    ({"lidar": "UTM-30LX"}, "180 deg"),
    ({"placement.standoff_m": [0.005]}, "housing"),
])
def test_unbuildable_splits_are_refused_with_a_reason(spec, changes, match):
    with pytest.raises(InfeasibleDesignError, match=match):
        solve(spec.replace(**changes))


@pytest.mark.parametrize("changes, field", [
    ({"layout.windows": 4}, "layout.windows"),
    ({"layout.windows": 1}, "layout.windows"),
    ({"layout.design_distance_m": 0.0}, "layout.design_distance_m"),
    ({"layout.design_distance_m": 6.0}, "layout.design_distance_m"),
    ({"layout.mirrors_per_side": 3}, "layout.mirrors_per_side"),
    ({"placement.method": "best"}, "placement.method"),
])
def test_bad_parameters_name_the_field(spec, changes, field):
    with pytest.raises(ParameterError) as e:
        spec.replace(**changes)
    assert e.value.field == field and "allowed" in str(e.value)


# -- layering: the solved-design types below the solver, no import cycles ------------------
_CORE = ("geometry", "lidar", "spec", "beams", "design", "verify", "solver")


def _nodlidar_imports(name: str) -> tuple[set[str], list[str]]:
    """Top-level and in-function imports of nodlidar modules by ``nodlidar/<name>.py``,
    read from its syntax tree (module names relative to the package)."""
    import ast

    tree = ast.parse((ROOT / "nodlidar" / f"{name}.py").read_text())
    top, inner = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            target = node.module.split(".")[0]
            (top.add(target) if node in tree.body else inner.append(target))
    return top, inner


def test_core_modules_import_without_cycles_or_function_level_imports():
    """The import graph of the core read from source: acyclic (a topological order exists),
    and beams/design/verify/solver hide no nodlidar import in a function or under
    TYPE_CHECKING (spec's in-function imports check optional sections; not a cycle here)."""
    graph = {}
    for name in _CORE:
        top, inner = _nodlidar_imports(name)
        if name in ("beams", "design", "verify", "solver"):
            assert not inner, f"{name} imports {inner} inside a function or block"
            assert "TYPE_CHECKING" not in (ROOT / "nodlidar" / f"{name}.py").read_text(), name
        graph[name] = top & set(_CORE)
    order, left = [], dict(graph)
    while left:
        ready = [m for m, deps in left.items() if deps <= set(order)]
        assert ready, f"import cycle among {sorted(left)}"
        order += sorted(ready)
        for m in ready:
            del left[m]
    # the layering docs/architecture.md describes
    assert order.index("beams") < order.index("design") < order.index("verify") < order.index("solver")
    assert "solver" not in graph["design"] | graph["beams"] | graph["verify"]


@pytest.mark.parametrize("name", _CORE)
def test_each_core_module_imports_alone_in_a_fresh_interpreter(name):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", f"import nodlidar.{name}"], capture_output=True,
                       text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr


def test_solver_reexports_the_design_types():
    from nodlidar import design, solver

    assert solver.Design is design.Design and solver.MirrorSolution is design.MirrorSolution
