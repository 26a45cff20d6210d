import numpy as np

from ngnav.conventions import G0_MPS2
from ngnav.motion import min_jerk_step
from ngnav.rotation import (
    cross3,
    cross_rows,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_rotate_by_rotvec,
    quat_to_rotvec,
)
from ngnav.sim.turntable import fixed_axis_turn
from ngnav.strapdown import integrate_rate, rotation_angle_about


def test_quaternion_maps_body_to_ned():
    q = quat_from_rotvec(np.array([0, 0, np.pi / 2]))  # yaw 90 deg: body x points east
    np.testing.assert_allclose(quat_rotate(q, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-15)
    v = np.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(quat_to_rotvec(quat_from_rotvec(v)), v, atol=1e-15)


def test_integration_of_constant_rate_is_exact():
    t = np.arange(501) * 0.01
    w = np.tile([0.3, -0.5, 0.8], (501, 1))
    q = integrate_rate(w, t)
    expected = quat_from_rotvec(w[0] * t[-1])
    np.testing.assert_allclose(quat_normalize(q[-1]), quat_normalize(expected), atol=1e-12)


def test_turn_truth_is_self_consistent():
    tr = fixed_axis_turn(
        np.deg2rad(95.0),
        duration_s=3.0,
        rest_before_s=0.5,
        rest_after_s=0.5,
        rate_hz=1000.0,
        axis_b=np.array([1.0, 1.0, 0.0]),
        pivot_b_m=np.zeros(3),
    )
    np.testing.assert_allclose(tr.f_b_mps2[0], [0, 0, -G0_MPS2], atol=1e-12)
    # rate derivative: the analytic one matches the central difference of the analytic rate
    num = np.gradient(tr.omega_b_rps, tr.t_s, axis=0)
    assert np.max(np.abs(num[1:-1] - tr.omega_dot_b_rps2[1:-1])) < 2e-3
    # integrating the rate reproduces the attitude and the angle about the axis
    q = integrate_rate(tr.omega_b_rps, tr.t_s, tr.q_nb[0])
    d = quat_multiply(q[-1], tr.q_nb[-1] * [1, -1, -1, -1])
    assert np.linalg.norm(quat_to_rotvec(d)) < 1e-8
    ang = rotation_angle_about(q, np.array([1.0, 1.0, 0.0]))
    assert np.rad2deg(ang[-1]) == np.float64(np.rad2deg(ang[-1]))
    assert abs(np.rad2deg(ang[-1]) - 95.0) < 1e-6


def test_min_jerk_step_float_path_matches_arrays():
    """The filter's float path gives the array path's values, inside and outside [0, 1]."""
    taus = [-0.5, 0.0, 0.1, 0.37, 0.5, 0.93, 1.0, 1.7]
    arrays = min_jerk_step(np.array(taus))
    for k, tau in enumerate(taus):
        floats = min_jerk_step(tau)
        assert all(type(v) is float for v in floats)
        np.testing.assert_allclose(floats, [a[k] for a in arrays], rtol=1e-15, atol=1e-15)
    # the exact step: s(1/2) = 1/2, ds(1/2) = 30/16, constant outside
    assert min_jerk_step(0.5)[:2] == (0.5, 1.875)
    assert min_jerk_step(2.0) == (1.0, 0.0, 0.0)


def test_cross_rows_is_the_cross_product():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 21, 3))
    np.testing.assert_allclose(cross_rows(a, b), np.cross(a, b), rtol=0, atol=1e-15)
    # the single-vector form gives np.cross's value to the bit (the filter's speed work
    # keeps its estimates unchanged)
    for x, y in zip(a * 100.0, b, strict=True):
        assert np.array_equal(cross3(x, y), np.cross(x, y))


def test_quat_rotate_by_rotvec_is_the_normalised_product():
    rng = np.random.default_rng(4)
    for _ in range(20):
        q = quat_normalize(rng.normal(size=4))
        rv = rng.normal(size=3) * rng.choice([1e-6, 1e-2, 1.0])
        e = quat_from_rotvec(rv)
        np.testing.assert_allclose(
            quat_rotate_by_rotvec(q, rv, left=False),
            quat_normalize(quat_multiply(q, e)),
            atol=1e-15,
        )
        np.testing.assert_allclose(
            quat_rotate_by_rotvec(q, rv, left=True), quat_normalize(quat_multiply(e, q)), atol=1e-15
        )
