"""The round model (nodlidar.tracking.round_motion): a moving circle fitted to a window's
points, checked on the analytic fan of tests/cylinder_fan.py (independent of the
simulator): unbiased and start-independent on a cylinder cut by the view's edge, its
covariance the size of its scatter, a centre per mirror window, and no circle where the
points are a flat face or a corner."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from cylinder_fan import cylinder_scans
from numpy.testing import assert_allclose

from nodlidar.tracking.round_motion import fit_moving_circle

EDGE = np.radians(40.0)
#: a person (r 0.18 m) 1.2 m out on the view's +40 deg edge, 0.12 m outside it, walking
#: into the view square to the edge at 0.4 m/s: every slice is cut by the edge (the
#: situation of the diagonal pair's left person entering the mirrors' view)
C0 = 1.2 * np.array([np.cos(EDGE), np.sin(EDGE)]) + 0.12 * np.array([-np.sin(EDGE), np.cos(EDGE)])
V = 0.4 * np.array([np.sin(EDGE), -np.cos(EDGE)])


def _window(seed, n=6, noise_m=0.01, v=V, c0=C0):
    P, T = [], []
    for _beams, d, rng_m, t in cylinder_scans(v, c0, 0.18, n, noise_m, seed, 40.0):
        P.append(d * rng_m[:, None])
        T.append(t)
    return np.concatenate(P), np.concatenate(T)


def test_a_cylinder_cut_by_the_views_edge_reads_its_velocity_unbiased_from_any_start():
    # The entropy refinement reads this window's speed across the cut weakly (its minimum
    # follows its start: docs/tracking.md). The circle's centre moves with the object
    # whatever part of it is seen. Over 40 noise draws (1 cm): the mean error within 3
    # standard errors of zero (no bias); the fit's own sd no smaller than the scatter and
    # at most twice it (40 draws estimate an sd to ~11 %; measured 1.1x and 1.7x: a beam's
    # noise reaches the circle's normal at |cos incidence|, so the residuals are not
    # equally noisy and the equal-noise covariance is conservative); and starts 20 % slow
    # and 20 % fast give the same answer (to 1e-4 m/s: Gauss-Newton stops at a smaller step).
    errs, sds = [], []
    for seed in range(40):
        P, T = _window(seed)
        slow = fit_moving_circle(P, T, T.max(), 0.8 * V, 0.01)
        fast = fit_moving_circle(P, T, T.max(), 1.2 * V, 0.01)
        assert slow is not None and fast is not None
        assert_allclose(slow.velocity, fast.velocity, atol=1e-4)
        errs.append(slow.velocity - V)
        sds.append(np.sqrt(np.diag(slow.cov)))
        assert_allclose(slow.radius_m, 0.18, atol=0.02)
        assert slow.rms_norm < 1.2  # noise along the beam reaches the normal at |cos| <= 1
        assert slow.serial < 0.15  # independent noise leaves neighbours uncorrelated
    errs, sds = np.array(errs), np.array(sds)
    se = errs.std(axis=0) / np.sqrt(len(errs))
    assert np.all(np.abs(errs.mean(axis=0)) < 3 * se), (errs.mean(axis=0), se)
    ratio = sds.mean(axis=0) / errs.std(axis=0)
    assert np.all((ratio > 0.85) & (ratio < 2.0)), ratio


def test_a_centre_per_window_absorbs_a_windows_shift():
    # A mirror's calibration error shifts its points rigidly. The object is seen through
    # window 0 for the first three scans and window 1 (points 3 cm off in x) after: one
    # centre reads the shift as 0.03 m / ~0.3 s of motion; a centre per window does not.
    P, T = _window(0, noise_m=0.002)
    lab = (T >= 0.3).astype(int)
    P = P + np.where(lab[:, None] == 1, [0.03, 0.0], 0.0)
    one = fit_moving_circle(P, T, T.max(), V, 0.002)
    per = fit_moving_circle(P, T, T.max(), V, 0.002, labels=lab)
    assert one is not None and per is not None
    assert np.hypot(*(one.velocity - V)) > 0.05
    assert_allclose(per.velocity, V, atol=0.01)  # 0.2 cm noise, 6 scans: sd ~3 mm/s


@pytest.mark.parametrize("shape", ["face", "corner"])
def test_a_box_is_no_circle(shape):
    # A box's face seen square on fits a circle metres wide (refused above max_radius_m);
    # its corner fits one poorly: residuals larger than the range noise, and neighbours'
    # residuals alike (the shape the circle leaves, not noise).
    rng = np.random.default_rng(0)
    s = np.linspace(-0.2, 0.2, 60)
    if shape == "face":
        pts = np.column_stack([np.full_like(s, 2.0), s])
    else:
        pts = np.concatenate([np.column_stack([2.0 + np.abs(s[s < 0]), s[s < 0]]),
                              np.column_stack([2.0 + s[s >= 0], s[s >= 0]])])
    P = np.concatenate([pts + [0.03 * k, 0.0] for k in range(5)])
    P = P + 0.01 * rng.standard_normal(P.shape)
    T = np.repeat(0.1 * np.arange(5), len(pts))
    fit = fit_moving_circle(P, T, T.max(), [0.3, 0.0], 0.01, max_radius_m=2.0)
    if shape == "face":
        assert fit is None or fit.radius_m > 2.0
    else:
        assert fit is not None and fit.rms_norm > 1.5 and fit.serial > 0.5


def test_too_few_points_are_no_fit():
    P, T = _window(0)
    assert fit_moving_circle(P[:4], T[:4], T.max(), V, 0.01) is None


def test_the_compiled_normal_equations_are_the_numpy_jacobians():
    # nodlidar.tracking._kernel.circle_normal_equations sums in point order, numpy's matrix
    # product does not: the same to 1e-9 relative (rounding only), two windows, residuals
    # beyond the Huber threshold included.
    from nodlidar.tracking._kernel import circle_normal_equations

    rng = np.random.default_rng(3)
    P, T = _window(0)
    dt = T - T.max()
    sig = 0.01 + 0.01 * rng.random(len(P))
    k = (T >= 0.3).astype(np.int64)
    c = np.array([[1.0, 0.9], [1.02, 0.85]])
    v, R, huber = np.array([0.3, -0.2]), 0.2, 2.0
    Ak, gk = np.zeros((2, 5, 5)), np.zeros((2, 5))
    circle_normal_equations(P, dt, sig, k, c, v, R, huber, Ak, gk)
    d = P - c[k] - dt[:, None] * v
    dist = np.hypot(d[:, 0], d[:, 1])
    u = d / dist[:, None]
    r = (dist - R) / sig
    assert np.any(np.abs(r) > huber)
    w = np.where(np.abs(r) <= huber, 1.0, huber / np.abs(r))
    J = np.column_stack([-u, -u * dt[:, None], -np.ones(len(P))]) / sig[:, None]
    for kk in (0, 1):
        s = k == kk
        assert_allclose(Ak[kk], (J[s] * w[s, None]).T @ J[s], rtol=1e-9, atol=1e-9)
        assert_allclose(gk[kk], J[s].T @ (w[s] * r[s]), rtol=1e-9, atol=1e-9)


def test_the_compiled_start_and_residual_passes_are_numpys():
    # The algebraic start's sums and the residuals' RMS and serial correlation, each one
    # compiled pass, against numpy written out: the start circle to 1e-9 m (its normal
    # equations are summed about the first point, numpy's least squares is not), the
    # statistics to 1e-12 relative (rounding only).
    from nodlidar.tracking._kernel import circle_residual_stats
    from nodlidar.tracking.round_motion import _kasa

    rng = np.random.default_rng(5)
    P, T = _window(1)
    dt = T - T.max()
    v = np.array([0.25, -0.3])
    q = P - dt[:, None] * v
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    sol = np.linalg.lstsq(A, (q ** 2).sum(axis=1), rcond=None)[0]
    centre, radius = _kasa(P, dt, v)
    assert_allclose(centre, sol[:2], atol=1e-9)
    assert_allclose(radius, np.sqrt(sol[2] + sol[:2] @ sol[:2]), atol=1e-9)

    sig = 0.01 + 0.01 * rng.random(len(P))
    k = (T >= 0.3).astype(np.int64)
    scan = np.round(T / 0.1).astype(np.int64)
    c = np.array([[1.0, 0.9], [1.02, 0.85]])
    rr, rs, m = circle_residual_stats(P, dt, sig, k, c, v, 0.2, scan)
    d = P - c[k] - dt[:, None] * v
    r = (np.hypot(d[:, 0], d[:, 1]) - 0.2) / sig
    same = (np.diff(scan) == 0) & (np.diff(k) == 0)
    assert m == np.count_nonzero(same) and 0 < m < len(P) - 1
    assert_allclose(rr, r @ r, rtol=1e-12)
    assert_allclose(rs, np.sum(r[:-1][same] * r[1:][same]), rtol=1e-12)


def test_a_warm_start_reaches_the_cold_starts_minimum_in_fewer_steps(monkeypatch):
    # The tracker starts each scan's fit from the last scan's (TrackerConfig.round_warm):
    # the window gained a scan and its centres moved on at the last velocity. The minimum
    # is the same (to 1e-5 m/s: both stop at a step below 1e-4), reached in fewer steps
    # than from the algebraic circle at the entropy's velocity (20 % slow here: across the
    # cut it is weakly determined).
    import nodlidar.tracking._kernel as kernel

    calls = []
    normal = kernel.circle_normal_equations
    monkeypatch.setattr(kernel, "circle_normal_equations",
                        lambda *a: calls.append(1) or normal(*a))
    P, T = _window(2, n=7)
    last = T < 0.6  # the first six scans: the last scan's window
    lab = (T >= 0.3).astype(int)
    before = fit_moving_circle(P[last], T[last], T[last].max(), V, 0.01, labels=lab[last])
    assert before is not None
    calls.clear()
    cold = fit_moving_circle(P, T, T.max(), 0.8 * V, 0.01, labels=lab)
    n_cold = len(calls)
    calls.clear()
    warm = fit_moving_circle(P, T, T.max(), 0.8 * V, 0.01, labels=lab, start=before)
    n_warm = len(calls)
    assert cold is not None and warm is not None
    assert_allclose(warm.velocity, cold.velocity, atol=1e-5)
    assert_allclose(warm.radius_m, cold.radius_m, atol=1e-5)
    assert_allclose(warm.centres, cold.centres, atol=1e-5)
    assert n_warm < n_cold, (n_warm, n_cold)
    # a label the start has no centre for: the algebraic start, the same minimum
    other = fit_moving_circle(P, T, T.max(), 0.8 * V, 0.01, labels=lab + 5, start=before)
    assert other is not None
    assert_allclose(other.velocity, cold.velocity, atol=1e-5)
    # a start the fit fails from (here: no finite centre) loses nothing: the fit is made
    # again from the algebraic start, exactly the cold fit
    broken = dataclasses.replace(before, centres=np.full_like(before.centres, np.nan))
    again = fit_moving_circle(P, T, T.max(), 0.8 * V, 0.01, labels=lab, start=broken)
    assert again is not None
    assert_allclose(again.velocity, cold.velocity, rtol=0, atol=0)


@pytest.mark.parametrize("field, value, allowed", [
    ("round_model", "ellipse", "off, cut or always"),
    ("round_radius_m", (0.5, 0.05), "0 < low < high"),
    ("round_max_serial", 2.0, "-1..1"),
    ("round_max_sd_m_s", 0.0, "> 0 m/s"),
])
def test_round_model_settings_are_checked(field, value, allowed):
    from nodlidar.errors import ParameterError
    from nodlidar.tracking.tracker import TrackerConfig

    with pytest.raises(ParameterError, match=f"{field} = .*{allowed}"):
        TrackerConfig(**{field: value})
