"""The paper's Section VI scenario in simulation: mirrors deployed vs lifted.

Truth: the simulator's mover (0.13 m/s, heading 89.4 deg; nodlidar.paper) and its per-beam
object ids. The paper's bounds: final v within 0.01 m/s, heading within 2 deg.
"""

from __future__ import annotations

import numpy as np
import pytest

from nodlidar.paper import TRACKING_HEADING_DEG, TRACKING_SPEED_M_S
from nodlidar.tracking.study import run_study, study_table


@pytest.fixture(scope="module")
def design():
    from nodlidar.solver import solve
    from nodlidar.spec import load_design

    return solve(load_design("design/urg04lx-paper.toml"))


@pytest.fixture(scope="module")
def renyi_study(design):
    return run_study(design, n_scans=38, seed=0, entropies=("renyi",))


def test_final_estimates_within_paper_bounds(renyi_study):
    for c in renyi_study.configs:
        e = c.estimates["renyi"]
        # the paper's success bounds (Section VI; the acceptance criteria)
        assert abs(e["v"][-1] - TRACKING_SPEED_M_S) <= 0.01, c.label
        err = (e["heading_deg"][-1] - TRACKING_HEADING_DEG + 180) % 360 - 180
        assert abs(err) <= 2.0, c.label


def test_convergence_mirrors_no_later_than_without(renyi_study):
    conv = {c.label: c.convergence["renyi"]["both"] for c in renyi_study.configs}
    print("convergence scan (renyi):", conv)
    assert conv["mirrors"] is not None and conv["no mirrors"] is not None
    assert conv["mirrors"] <= conv["no mirrors"]


def test_traces_and_density(renyi_study):
    m, n = renyi_study.configs
    assert m.mirrors_deployed and not n.mirrors_deployed
    # the same scans see the object in both runs (same nod ramp and object)
    assert m.scans_seen == n.scans_seen
    # without mirrors only the direct middle window sees the object: one trace per scan;
    # with mirrors two reflected windows overlap it too (paper: 28 vs 13 traces)
    assert n.traces_per_scan == [1] * n.scans_seen
    assert m.traces_total >= 2 * n.traces_total
    assert m.points_total >= 2 * n.points_total


def test_segmentation_precision_recall(renyi_study):
    for c in renyi_study.configs:
        print(c.label, "precision", c.precision, "recall", c.recall)
        # precision: static surfaces are not carved within 3 sigma + 1.5 voxels of their
        # returns, so no static cluster should pass; one would cost >= 5 points of ~2400.
        assert c.precision >= 0.98
        # recall: the 6 cm ground band of the 1 m cylinder is removed by construction (~6 %
        # of its points) and slices seen only at the sweep ends lack opposite-time evidence
        assert c.recall >= 0.85


def test_table_rows(renyi_study):
    rows = study_table(renyi_study)
    assert [r["config"] for r in rows] == ["mirrors", "no mirrors"]
    assert all(np.isfinite(r["err_v_m_s"]) for r in rows)


def test_robot_driving_with_known_pose(design):
    """The paper's sensor rides a robot with reliable localisation: with the robot driving
    at 0.1 m/s towards the scene (its pose known, every scan placed in the world by it), the
    static room must stay static and the object's motion is still the truth."""
    res = run_study(design, n_scans=38, seed=0, entropies=("renyi",),
                    robot_velocity_m_s=(0.1, 0.0))
    assert res.robot_velocity_m_s == (0.1, 0.0)
    for c in res.configs:
        e = c.estimates["renyi"]
        # measured: precision 1.000, recall 0.91, final errors <= 0.0007 m/s and 0.3 deg
        assert c.precision >= 0.98 and c.recall >= 0.85, c.label
        assert abs(e["v"][-1] - TRACKING_SPEED_M_S) <= 0.01, c.label
        err = (e["heading_deg"][-1] - TRACKING_HEADING_DEG + 180) % 360 - 180
        assert abs(err) <= 2.0, c.label
        assert c.convergence["renyi"]["both"] is not None


@pytest.mark.slow
def test_voxel_entropy_study_reported(design):
    """The paper's eq. 12 (voxel entropy): final estimates within the bounds; its convergence is
    reported, not asserted against the mirrors (it is piecewise constant and noisy)."""
    res = run_study(design, n_scans=38, seed=0, entropies=("voxel",))
    for c in res.configs:
        e = c.estimates["voxel"]
        print(c.label, "voxel convergence", c.convergence["voxel"], "final", e["v"][-1],
              e["heading_deg"][-1])
        assert abs(e["v"][-1] - TRACKING_SPEED_M_S) <= 0.01
        assert abs(e["heading_deg"][-1] - TRACKING_HEADING_DEG) <= 2.0


@pytest.mark.slow
def test_convergence_over_noise_seeds(design):
    """Seed 0 alone is one noise draw. Over 8 seeds (Rényi) the mirrors converge earlier in
    most runs but not all (seed 7: 9 with mirrors vs 7 without, measured), so the claim
    checked is about the median, and the per-seed numbers are printed."""
    from nodlidar.tracking.study import seed_sweep

    rows = seed_sweep(design, range(8), 38, ("renyi",))
    for r in rows:
        print(r)
    m = [r["conv_mirrors"] for r in rows]
    n = [r["conv_no_mirrors"] for r in rows]
    assert None not in m and None not in n
    assert np.median(m) <= np.median(n)
