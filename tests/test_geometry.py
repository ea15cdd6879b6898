"""The geometry core against closed forms: law of reflection, rotations, perturbations."""

import numpy as np
from numpy.testing import assert_allclose

from nodlidar.geometry import (
    MirrorPatch,
    Perturbation,
    matrix_from_axis_angle,
    reflect,
    rot_x,
    rot_y,
    rot_z,
    unit,
)

rng = np.random.default_rng(7)


def test_reflection_obeys_the_law_of_reflection():
    d = unit(rng.normal(size=(1000, 3)))
    n = unit(rng.normal(size=(1000, 3)))
    r = reflect(d, n)
    # |r| = 1, angle of incidence = angle of reflection, r in the plane of d and n
    assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-12)
    assert_allclose(np.sum(r * n, 1), -np.sum(d * n, 1), atol=1e-12)
    assert_allclose(np.einsum("ij,ij->i", np.cross(d, n), r), 0, atol=1e-12)
    assert_allclose(reflect(r, n), d, atol=1e-12)  # involution


def test_rotations_agree_with_axis_angle():
    for a in (-1.0, 0.3, 2.0):
        assert_allclose(rot_z(a), matrix_from_axis_angle([0, 0, 1], a), atol=1e-15)
        assert_allclose(rot_y(a), matrix_from_axis_angle([0, 1, 0], a), atol=1e-15)
        assert_allclose(rot_x(a), matrix_from_axis_angle([1, 0, 0], a), atol=1e-15)
    # REP 103: positive pitch tips +x down; positive roll lifts +y
    assert rot_y(0.1)[2, 0] < 0
    assert rot_x(0.1)[2, 1] > 0
    # vectorised form equals the scalar form
    a = rng.uniform(-3, 3, 5)
    for rot in (rot_x, rot_y, rot_z):
        assert_allclose(rot(a), np.stack([rot(x) for x in a]))


def _patch(theta=0.3, d=0.06, hinge_z=-0.025):
    n_out = np.array([np.cos(theta), np.sin(theta), 0.0])
    normal = -n_out  # towards the lidar
    along = np.cross([0, 0, 1.0], normal)
    return MirrorPatch("M", tuple(d * n_out), tuple(normal), tuple(along), -0.03, 0.03, -0.015,
                       0.015, hinge_z)


def test_dd_moves_the_plane_along_its_normal():
    p = _patch()
    q = p.perturbed(Perturbation(dd=0.004))
    assert_allclose(q.standoff, p.standoff + 0.004, atol=1e-15)
    assert_allclose(q.normal_, p.normal_, atol=1e-15)


def test_dalpha_turns_the_normal_about_the_vertical_through_o():
    p = _patch(theta=0.3)
    q = p.perturbed(Perturbation(dalpha=0.05))
    assert_allclose(q.normal_azimuth, p.normal_azimuth + 0.05, atol=1e-14)
    assert_allclose(q.standoff, p.standoff, atol=1e-15)


def test_dbeta_tilts_a_normal_incidence_beam_by_two_dbeta():
    # Beam along the outward normal hits the mirror at normal incidence; a tilt of dbeta
    # about the (horizontal) hinge axis sends it back 2*dbeta out of the scan plane.
    for dbeta in (-0.05, 0.01, 0.035):
        p = _patch(theta=0.3).perturbed(Perturbation(dbeta=dbeta))
        d = np.array([[np.cos(0.3), np.sin(0.3), 0.0]])
        r = reflect(d, p.normal_)[0]
        assert_allclose(np.arcsin(abs(r[2])), 2 * abs(dbeta), atol=1e-12)


def test_dbeta_shifts_the_scan_plane_line_by_h_tan_dbeta():
    # The paper's eq. 4 term h*tan(dbeta): the mirror's trace in the scan plane moves by
    # hinge_z * tan(dbeta) along the normal (sign by the right-hand rule about 'along').
    h, dbeta = -0.025, 0.02
    p = _patch(hinge_z=h)
    q = p.perturbed(Perturbation(dbeta=dbeta))
    ray = np.array([[np.cos(0.3), np.sin(0.3), 0.0]])
    t = q.intersect(np.zeros((1, 3)), ray, finite=False)[0][0]
    assert_allclose(abs(t - p.standoff), abs(h * np.tan(dbeta)), rtol=1e-9)


def test_finite_patch_misses_outside_its_rectangle():
    p = _patch()
    o = np.zeros((3, 3))
    c = p.point(np.array([0.0, 0.029, 0.031]))  # inside, inside, outside along s
    t, s, z = p.intersect(o, unit(c))
    assert np.isfinite(t[:2]).all() and np.isinf(t[2])
    assert_allclose(t[:2], np.linalg.norm(c[:2], axis=1), atol=1e-14)


def test_hinge_rotation_composes_and_lifts_out_of_plane():
    p = _patch()
    q = p.rotated_about_hinge(0.4).rotated_about_hinge(-0.4)
    assert_allclose(q.corners(), p.corners(), atol=1e-14)
    lifted = p.rotated_about_hinge(-np.pi / 2)  # hinge below: top swings away from O
    assert lifted.corners()[:, 2].max() < 0  # the whole glass is below the scan plane


# -- the one rotation vocabulary -----------------------------------------------------------
def test_rotate_about_axis_matches_the_matrix_per_row():
    """Rodrigues per row vs the 3x3 matrix built one row at a time (exact to rounding)."""
    from nodlidar.geometry import matrix_from_axis_angle, rotate_about_axis, unit

    rng = np.random.default_rng(7)
    v = rng.normal(size=(40, 3))
    k = unit(rng.normal(size=(40, 3)))
    a = rng.uniform(-np.pi, np.pi, 40)
    want = np.array([matrix_from_axis_angle(k[i], a[i]) @ v[i] for i in range(40)])
    assert_allclose(rotate_about_axis(v, k, a), want, atol=1e-14)
    # one axis and one angle for all rows; norm and the axis component are kept
    out = rotate_about_axis(v, k[0], 0.7)
    assert_allclose(np.linalg.norm(out, axis=1), np.linalg.norm(v, axis=1), rtol=1e-14)
    assert_allclose(out @ k[0], v @ k[0], atol=1e-14)


def test_pitch_about_pivot_is_rot_y_about_the_pivot():
    """The nod as written out vs rot_y matrices; the pivot is a fixed point; +pitch tips +x down."""
    from nodlidar.geometry import pitch_about_pivot, rot_y

    rng = np.random.default_rng(3)
    p = rng.normal(size=(30, 3))
    a = rng.uniform(-0.5, 0.5, 30)
    pivot = np.array([0.02, -0.01, 0.05])
    want = pivot + np.einsum("nij,nj->ni", rot_y(a), p - pivot)
    assert_allclose(pitch_about_pivot(p, a, pivot), want, atol=1e-15)
    assert_allclose(pitch_about_pivot(pivot[None], 0.3, pivot), pivot[None], atol=1e-15)
    assert pitch_about_pivot(np.array([1.0, 0, 0]), 0.1)[2] < 0


def test_directions_from_bearings():
    """Unit vectors whose atan2 is the bearing and whose asin(z) is the elevation."""
    from nodlidar.geometry import bearing_of, directions_from_bearings

    b = np.linspace(-2, 2, 9)
    e = np.linspace(-0.3, 0.3, 9)
    d = directions_from_bearings(b, e)
    assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-15)
    assert_allclose(bearing_of(d), b, atol=1e-15)
    assert_allclose(np.arcsin(d[:, 2]), e, atol=1e-15)
    assert_allclose(directions_from_bearings(b)[:, 2], 0.0)


def test_perturb_frames_batched_equals_the_closed_form_per_sample():
    """The batched mounting-error model against the same three motions written as 3x3
    matrices one sample at a time (tilt about the hinge line, offset, yaw about O), and
    MirrorPatch.perturbed is that model for one sample. Same formula, different evaluation
    order: agreement to a few ulp of the ~0.1 m coordinates (1e-15 m)."""
    from nodlidar.geometry import perturb_frames

    p = _patch(theta=0.7, hinge_z=-0.02)
    rng = np.random.default_rng(11)
    e = rng.normal(size=(25, 3)) * [0.05, 0.08, 0.003]
    o, n, a, u = perturb_frames(p.origin_, p.normal_, p.along_, p.up_, p.hinge_z,
                                e[:, 0], e[:, 1], e[:, 2])
    assert o.shape == n.shape == a.shape == u.shape == (25, 3)
    pivot = p.origin_ + p.hinge_z * p.up_
    for k, (da, db, dd) in enumerate(e):
        T = matrix_from_axis_angle(p.along_, db)
        o_k = pivot + T @ (p.origin_ - pivot)
        n_k = T @ p.normal_
        o_k = o_k - dd * n_k   # the normal faces the lidar: outward is -normal here
        Z = rot_z(da)
        assert_allclose(o[k], Z @ o_k, atol=1e-15)
        assert_allclose(n[k], Z @ n_k, atol=1e-15)
        assert_allclose(a[k], Z @ p.along_, atol=1e-15)
        assert_allclose(u[k], Z @ T @ p.up_, atol=1e-15)
        q = p.perturbed(Perturbation(da, db, dd))
        assert_allclose(q.origin_, o[k], atol=1e-15)
        assert_allclose(q.normal_, n[k], atol=1e-15)
        assert_allclose(q.up_, u[k], atol=1e-15)
    # the standoff grows by dd exactly when only dd is applied (the model's meaning of dd)
    o1, n1, _, _ = perturb_frames(p.origin_, p.normal_, p.along_, p.up_, p.hinge_z, 0, 0, e[:, 2])
    assert_allclose(np.abs(np.sum(o1 * n1, 1)), p.standoff + e[:, 2], atol=1e-15)


def test_incidence_angle_against_the_angle_between_vectors():
    """arccos|d.n| vs atan2(|d x n|, |d.n|) (the well-conditioned form), either normal sign."""
    from nodlidar.geometry import incidence_angle

    rng = np.random.default_rng(5)
    d = unit(rng.normal(size=(50, 3)))
    n = unit(rng.normal(size=3))
    want = np.arctan2(np.linalg.norm(np.cross(d, n), axis=1), np.abs(d @ n))
    # arccos loses digits near 0 (normal incidence): 1e-7 rad covers sqrt(eps)
    assert_allclose(incidence_angle(d, n), want, atol=1e-7)
    assert_allclose(incidence_angle(d, -n), incidence_angle(d, n), atol=0)
    assert_allclose(incidence_angle(n, n), 0.0, atol=1e-7)
    assert np.all((incidence_angle(d, n) >= 0) & (incidence_angle(d, n) <= np.pi / 2))
