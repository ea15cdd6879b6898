"""Reproduction of the paper's Section III numbers, and the documented residuals.

The paper leaves OA (and its discretisation) unstated. Under the assumptions written in
design/urg04lx-paper.toml and docs/paper-reproduction.md, OA = 20.497 mm reproduces
phi(L1) = 80.0397 deg exactly (that is how OA was chosen); the other three numbers are then
predictions, and their residuals are pinned here so any change to them is deliberate.
"""

from pathlib import Path

import numpy as np
from numpy.testing import assert_allclose

from nodlidar.closed_form import eq4_8_point
from nodlidar.designio import paper_comparison
from nodlidar.solver import solve
from nodlidar.spec import load_design

PAPER = Path(__file__).resolve().parents[1] / "design" / "urg04lx-paper.toml"


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
