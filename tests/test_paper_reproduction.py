"""Reproduction of the paper's Section III numbers, and the documented residuals.

Two readings (docs/paper-reproduction.md):

* EXACT (design/urg04lx-paper.toml, the default): explicit per-mirror step ranges, anchor targets
  on the third-step grid, OA = 2.0 / 7.0 cm, mirrors not chained. All four printed numbers
  come out within 0.003 cm and 0.007 deg; checked here against a hand construction that
  does not use the solver (law of reflection from the anchor target and OA).
* CHAINED (design/urg04lx-paper-chained.toml): equal contiguous split, L2 chained to L1, OA
  fitted to phi(L1); the other three numbers are predictions with ~9 % longer mirrors,
  pinned here so any change to them is deliberate.
"""

from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.optimize import brentq, fsolve

from nodlidar.closed_form import eq4_8_point
from nodlidar.designio import paper_comparison
from nodlidar.errors import InfeasibleDesignError
from nodlidar.solver import solve
from nodlidar.spec import load_design
from nodlidar.verify import verify

DESIGNS = Path(__file__).resolve().parents[1] / "design"
PAPER = DESIGNS / "urg04lx-paper-chained.toml"  # the chained reading
PAPER_EXACT = DESIGNS / "urg04lx-paper.toml"    # the reading that gives all four numbers

# Section III as printed: QZ [cm] and phi [deg]
PRINTED = {"L1": (5.4692, 80.0397), "L2": (14.6019, 60.8307)}


def _hand_mirror(lidar, first, last, anchor, target_rad, oa, D):
    """A mirror built by hand in 2-D from its anchor beam, target and OA.

    Independent of the solver's triangle construction (law of sines in ZOM): the anchor
    point Z = r u(anchor) is found by root-finding the perpendicular distance from O to
    the line Z -> M (M = D u(target)) equal to OA; the normal bisects Z -> O and Z -> M
    (law of reflection). Returns QZ [m] (first to last beam's hit points), phi [deg] and
    (Z, n).
    """
    def u(t):
        return np.array([np.cos(t), np.sin(t)])

    def cross(a, b):
        return a[0] * b[1] - a[1] * b[0]

    uz, M = u(lidar.bearing_from_step(anchor)), D * u(target_rad)
    f = lambda r: abs(cross(r * uz, M - r * uz)) / np.linalg.norm(M - r * uz) - oa  # noqa: E731
    rs = np.linspace(1e-3, 1.0, 2000)
    v = np.array([f(r) for r in rs])
    i = np.nonzero(np.sign(v[:-1]) != np.sign(v[1:]))[0][0]  # nearest root: the real mirror
    Z = brentq(f, rs[i], rs[i + 1], xtol=1e-15) * uz
    n = -uz + (M - Z) / np.linalg.norm(M - Z)
    n /= np.linalg.norm(n)
    phi = 90.0 - np.degrees(np.arccos(abs(uz @ n)))
    hits = [(Z @ n) / (u(lidar.bearing_from_step(s)) @ n) * u(lidar.bearing_from_step(s))
            for s in (first, last)]
    return float(np.linalg.norm(hits[1] - hits[0])), float(phi), (Z, n)


@pytest.fixture(scope="module")
def exact():
    return solve(load_design(PAPER_EXACT))


def test_exact_reading_reproduces_the_four_printed_numbers(exact):
    lid = exact.lidar
    U = lid.angular_resolution / 3  # pi/1536
    OP = lid.bearing_from_step(271)  # the first direct beam beside the left mirrors' fan
    hand = {"L1": _hand_mirror(lid, 616, 725, 725, OP + U, 0.020, 2.0),
            "L2": _hand_mirror(lid, 498, 611, 611, OP - U, 0.070, 2.0)}
    for name, (qz_cm, phi_deg) in PRINTED.items():
        m = exact.mirror(name)
        span, phi, (Z, n) = hand[name]
        # solver vs hand construction: two computations of the same plane geometry, so
        # they agree to round-off (1e-12 m / 1e-9 deg leaves room for the root finders)
        assert_allclose(m.beam_span_m, span, atol=1e-12)
        assert_allclose(np.degrees(m.phi_rad), phi, atol=1e-9)
        assert_allclose(m.patch.origin_[:2], Z, atol=1e-12)
        assert_allclose(abs(m.patch.normal_[:2] @ n), 1.0, atol=1e-12)
        # against the printed numbers: the bound (0.003 cm, 0.01 deg); the paper
        # prints 4 decimals, the residual is the off-grid target (next test)
        assert abs(span * 100 - qz_cm) < 0.003, (name, span * 100, qz_cm)
        assert abs(phi - phi_deg) < 0.01, (name, phi, phi_deg)
    # the json numbers the issue quotes, to their last printed digit
    rows = {r["quantity"]: r["ours"] for r in paper_comparison(exact)}
    assert_allclose([rows["L1_length_m"] * 100, rows["L1_phi_deg"], rows["L2_length_m"] * 100,
                     rows["L2_phi_deg"]], [5.4663, 80.0326, 14.5991, 60.8271], atol=5e-5)


def test_exact_fit_needs_targets_off_the_third_step_grid(exact):
    # The residual explained: letting each anchor target (and OA) float, the printed QZ and
    # phi are met exactly with the targets 0.014 (L1) and 0.007 (L2) deg clockwise of the
    # pi/1536 grid and OA within 0.02 mm of the round values: the paper's targets were not
    # exactly on the grid (or its numbers carry that much rounding).
    lid = exact.lidar
    U = lid.angular_resolution / 3
    OP = lid.bearing_from_step(271)
    cases = {"L1": (616, 725, OP + U, 0.020), "L2": (498, 611, OP - U, 0.070)}
    off = {}
    for name, (first, last, grid, oa) in cases.items():
        qz, phi = PRINTED[name]

        def g(x, first=first, last=last, grid=grid, qz=qz, phi=phi):
            s, p, _ = _hand_mirror(lid, first, last, last, grid + np.radians(x[0]), x[1], 2.0)
            return [s * 100 - qz, p - phi]

        x, info, ier, _ = fsolve(g, [0.0, oa], full_output=True, xtol=1e-12)
        assert_allclose(g(x), 0, atol=1e-9)  # a true solution
        off[name] = x[0]
        assert abs(x[1] - oa) < 2e-5, (name, x[1])
    assert_allclose([off["L1"], off["L2"]], [-0.0143, -0.0066], atol=5e-4)


def test_exact_reading_blocks_only_the_declared_beams(exact):
    v = verify(exact)
    bad = v.steps[v.bad]
    # L2's tip shadows L1's first reflections (R2 likewise R1's), exactly the declared ones
    assert set(bad) == set(range(616, 626)) | set(range(143, 153))
    assert_allclose(exact.shadowed_steps, sorted(bad))  # what the runtime must drop
    assert not v.unexpected_blocked().any()
    # 612..615 and 153..156 reach no glass and stay direct
    for s in (*range(612, 616), *range(153, 157)):
        assert v.hit[s - exact.lidar.step_min] == -1 and v.blocker[s - exact.lidar.step_min] == -1
    # without the declaration the same file is refused, naming the beams and the blocker
    spec = load_design(PAPER_EXACT).replace(**{"placement.shadowed_steps": []})
    with pytest.raises(InfeasibleDesignError, match="L1 steps 616..625 blocked by L2"):
        solve(spec)


def test_exact_right_side_mirrors_the_left(exact):
    # s <-> 768 - s is the reflection y -> -y; R1 is built on the construction ray of the
    # missing step 43, so its plane is L1's mirrored and only its beam count differs.
    flip = np.array([1.0, -1.0, 1.0])
    for a, b in (("L1", "R1"), ("L2", "R2")):
        la, rb = exact.mirror(a), exact.mirror(b)
        assert_allclose(rb.patch.origin_, la.patch.origin_ * flip, atol=1e-12)
        assert_allclose(rb.patch.normal_, la.patch.normal_ * flip, atol=1e-12)
    assert len(exact.mirror("R1").steps) == 109 and len(exact.mirror("L1").steps) == 110
    assert exact.mirror("R1").anchor_step == 43
    v = verify(exact)
    # the anchors that are real beams land exactly on target
    for name in ("L1", "L2", "R2"):
        i = exact.mirror(name).anchor_step - exact.lidar.step_min
        assert abs(v.error[i]) < 1e-12


def test_paper_numbers_and_residuals():
    design = solve(load_design(PAPER))
    rows = {r["quantity"]: r for r in paper_comparison(design)}
    # fitted: exact to the printed precision (4 decimals of a degree)
    assert_allclose(rows["L1_phi_deg"]["ours"], 80.0397, atol=5e-5)
    # predictions: documented residuals (docs/paper-reproduction.md), to 0.01 % / 0.001 deg
    assert_allclose(rows["L2_phi_deg"]["ours"], 60.7727, atol=1e-3)        # paper 60.8307
    assert_allclose(rows["L1_length_m"]["ours"], 0.059430, rtol=1e-4)      # paper 0.054692
    assert_allclose(rows["L2_length_m"]["ours"], 0.160103, rtol=1e-4)      # paper 0.146019


def test_chaining_equals_placing_l2_by_its_own_oa():
    # Round trip between the two ways to place L2: chained to L1's end, or unchained with
    # the OA that the chained solution has. Both must give the same mirror.
    spec = load_design(PAPER)
    chained = solve(spec)
    oas = [chained.mirror("L1").oa_m, chained.mirror("L2").oa_m]
    # (the R side gets the L side's OAs too and may overlap; only L is compared)
    free = solve(spec.replace(**{"placement.chain": False, "placement.standoff_m": oas}),
                 check=False)
    for name in ("L1", "L2"):
        assert_allclose(free.mirror(name).patch.origin_, chained.mirror(name).patch.origin_,
                        atol=1e-12)
        assert_allclose(free.mirror(name).patch.normal_, chained.mirror(name).patch.normal_,
                        atol=1e-12)


def test_literal_eqs_4_to_8_are_far_from_the_exact_model():
    # Documented finding: as printed, eqs 4-8 misplace reflected points at 2 m by tens of
    # centimetres even with zero perturbation (median over L1's beams, natural frame reading
    # with x/y swapped as eq. 7 writes them).
    design = solve(load_design(PAPER))
    m = design.mirror("L1")
    th = design.lidar.bearing_from_step(m.steps)
    r = np.full(len(th), 2.0)
    exact = design.beam_model().points(m.steps, r)
    p = eq4_8_point(r, th, m.patch.normal_azimuth, m.standoff_m, -design.spec.mirror.hinge_z_m)
    err = np.linalg.norm(p[:, [1, 0]] * [1, -1] - exact[:, :2], axis=1)
    assert np.median(err) > 0.3


def test_explicit_plans_reproduce_the_automatic_split():
    # Round trip between the two ways to state a design: the chained reading's automatic
    # split (windows, mirrors_per_side, one OA, chain) written out as explicit
    # [[placement.mirrors]] (with chain = true for the inner mirrors) gives the same mirrors.
    spec = load_design(PAPER)
    auto = solve(spec)
    oa = spec.placement.standoff_m[0]
    plans = []
    for m in auto.mirrors:
        plans.append({"name": m.name, "steps": [m.first_step, m.last_step],
                      "anchor_step": m.anchor_step, "target_step": m.target_step,
                      "target_offset": m.offset_index, "chain": m.index > 1,
                      "standoff_m": oa if m.index == 1 else 0.0})
    explicit = solve(spec.replace(**{"placement.mirrors": plans}))
    for a in auto.mirrors:
        b = explicit.mirror(a.name)
        assert_allclose(b.patch.origin_, a.patch.origin_, atol=1e-12)
        assert_allclose(b.patch.normal_, a.patch.normal_, atol=1e-12)
        assert_allclose(b.target_bearing, a.target_bearing, atol=1e-15)
    assert np.array_equal(explicit.direct_steps, auto.direct_steps)
