"""The body-frame velocity error (``NavFilter.body_velocity_error``) against exact references.

The truth is ``exp(dtheta) C (C^T v + dv_b)``; the Kalman state's velocity holds
``xi_v = C dv_b + dtheta x v``. Each test computes what the filter approximates with the
exact rotations and an exact integration of the body-frame dynamics.
"""

import numpy as np
import pytest

from filters.algebra import body_velocity_reset_jacobian
from filters.state import ATT, VEL
from filters.vehicle_model import LATERAL, VERTICAL, constraint_axes
from ngnav.conventions import gravity_n_mps2
from ngnav.rotation import (
    dcm_from_quat,
    quat_conjugate,
    quat_from_euler,
    quat_from_rotvec,
    quat_multiply,
    quat_to_rotvec,
    skew,
)
from tests.helpers import level_filter


def _rot(rotvec: np.ndarray) -> np.ndarray:
    return dcm_from_quat(quat_from_rotvec(np.asarray(rotvec, dtype=float)))


def _errors(q_true, v_true, q_nom, v_nom) -> tuple[np.ndarray, np.ndarray]:
    """``(dtheta, xi_v)`` of a truth about a nominal state (NED rad, NED m/s)."""
    d = quat_multiply(q_true, quat_conjugate(q_nom))
    dth = quat_to_rotvec(-d if d[0] < 0 else d)
    c_t, c = dcm_from_quat(q_true), dcm_from_quat(q_nom)
    dv_b = c_t.T @ v_true - c.T @ v_nom
    return dth, c @ dv_b + np.cross(dth, v_nom)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reset_jacobian_carries_the_error_left_by_a_correction(seed):
    """A body-style correction of about 1 deg and 0.1 m/s at 60 m/s, the truth 1 deg and
    0.1 m/s from it: the new velocity error is ``G_vv e_v + G_vtheta e_theta`` to second
    order, where the identity (the NED error's reset) misses by ``V e_theta dtheta``."""
    rng = np.random.default_rng(seed)
    q = quat_from_euler(*np.radians([5.0, 3.0, 80.0]))
    v = np.array([10.0, 58.0, -4.0])
    dth_hat = rng.normal(0.0, 0.02, 3)
    dxi_hat = rng.normal(0.0, 0.1, 3)
    e_th = rng.normal(0.0, 0.02, 3)
    e_v = rng.normal(0.0, 0.1, 3)
    # the truth whose errors about (q, v) are (dth_hat + e_th, dxi_hat + e_v)
    dth = dth_hat + e_th
    q_t = quat_multiply(quat_from_rotvec(dth), q)
    c, c_t = dcm_from_quat(q), dcm_from_quat(q_t)
    dv_b = c.T @ (dxi_hat + e_v - np.cross(dth, v))
    v_t = c_t @ (c.T @ v + dv_b)
    got = _errors(q_t, v_t, q, v)
    assert np.allclose(got[0], dth, atol=1e-12) and np.allclose(got[1], dxi_hat + e_v)
    # the correction injected as the filter does
    q_new = quat_multiply(quat_from_rotvec(dth_hat), q)
    v_new = _rot(dth_hat) @ (v + dxi_hat + np.cross(v, dth_hat))
    th_new, xi_new = _errors(q_t, v_t, q_new, v_new)
    # the attitude error's reset for a left (NED) error: I + [dth_hat]x / 2
    assert np.linalg.norm(th_new - (e_th + 0.5 * np.cross(dth_hat, e_th))) < 0.05 * np.linalg.norm(
        th_new - e_th
    )
    gvv, gvt = body_velocity_reset_jacobian(dth_hat, dxi_hat, v)
    predicted = gvv @ e_v + gvt @ e_th
    miss_identity = np.linalg.norm(xi_new - e_v)
    miss_jacobian = np.linalg.norm(xi_new - predicted)
    # first order in e with coefficients ~ V |dth_hat|: 1e-2 m/s; left: ~ V |dth|^2 e
    assert miss_identity > 5e-3
    assert miss_jacobian < 0.05 * miss_identity


def test_velocity_curvature_matches_sampled_errors():
    """The NED velocity's second-order part ``c = v_true - v - xi_v`` of errors drawn from
    P: its mean and covariance against 200 000 samples, the truth built with exact
    rotations. Within 5 standard errors per element."""
    nf, _, _ = level_filter()
    nf.body_velocity_error = True
    nf.q = quat_from_euler(*np.radians([20.0, 5.0, 80.0]))
    nf.vel = np.array([10.0, 58.0, -4.0])
    rng = np.random.default_rng(7)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T / 6.0
    scale = np.r_[np.full(3, 0.02), np.full(3, 0.1)]  # rad, m/s
    cov = cov * np.outer(scale, scale)
    idx = np.r_[ATT, VEL]
    nf.P[np.ix_(idx, idx)] = cov
    mean, cc = nf.velocity_curvature()
    x = rng.multivariate_normal(np.zeros(6), cov, size=200_000)
    c = dcm_from_quat(nf.q)
    v = nf.vel
    samples = np.empty((x.shape[0], 3))
    for k, (dth, xi) in enumerate(zip(x[:, :3], x[:, 3:], strict=True)):
        dv_b = c.T @ (xi - np.cross(dth, v))
        v_t = _rot(dth) @ c @ (c.T @ v + dv_b)
        samples[k] = v_t - v - xi
    n = samples.shape[0]
    se_mean = samples.std(axis=0) / np.sqrt(n)
    assert np.all(np.abs(samples.mean(axis=0) - mean) < 5.0 * se_mean)
    emp = np.cov(samples.T)
    # the sample covariance's standard error, sqrt((s_ii s_jj + s_ij^2) / n) for a
    # Gaussian: the curvature is a quadratic form, so use the fourth moments instead
    d = samples - samples.mean(axis=0)
    se_cov = np.sqrt(np.einsum("ni,nj,ni,nj->ij", d, d, d, d) / n - emp**2) / np.sqrt(n)
    assert np.all(np.abs(emp - cc) < 5.0 * se_cov + 1e-12)
    # and the NED error's filter has none
    nf.body_velocity_error = False
    assert not np.any(nf.velocity_curvature()[1])


def _propagate_body(c0, v_b0, w_b, f_b, g_n, t_s, steps=400):
    """Exact-to-RK4 body-frame dynamics with constant rate and force: (C, v_b) at t_s."""
    h = t_s / steps

    # the attitude under a constant body rate is exact: C(t) = C0 exp([w]x t)
    def acc(t, v_b):
        c = c0 @ _rot(w_b * t)
        return f_b - np.cross(w_b, v_b) + c.T @ g_n

    v = v_b0.copy()
    for k in range(steps):
        t = k * h
        k1 = acc(t, v)
        k2 = acc(t + h / 2, v + h / 2 * k1)
        k3 = acc(t + h / 2, v + h / 2 * k2)
        k4 = acc(t + h, v + h * k3)
        v = v + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return c0 @ _rot(w_b * t_s), v


@pytest.mark.parametrize("axis", [LATERAL, VERTICAL])
def test_body_remainder_is_the_dynamics_second_order(axis):
    """Truth and nominal flown through 0.2 s of the body-frame dynamics (60 m/s, 0.5 rad/s,
    1.5 g), the truth off by 1 deg, 2 deg/s and 0.1 m/s at the start. The even part of
    the constraint's error in the error's size, ``(D(e) + D(-e)) / 2``, is the second
    order the linear propagation leaves out; ``body_velocity_remainder_matrix`` gives it
    from the errors at the update (the odd part, the linear propagation's). The model
    expands the interval to its square (its cube for gravity), so it is good to about
    ``|w| T`` = 0.1 of itself."""
    nf, _, _ = level_filter()
    nf.body_velocity_error = True
    g = gravity_n_mps2()
    c0 = dcm_from_quat(quat_from_euler(*np.radians([30.0, 8.0, 80.0])))
    v_b0 = np.array([60.0, 0.5, 3.0])
    w_b = np.array([0.3, 0.2, 0.35])
    f_b = np.array([1.0, 4.0, -14.0])
    t_s = 0.2
    x0 = np.r_[np.radians([0.7, -1.0, 0.5]), np.radians([2.0, -1.5, 1.8]), [0.1, -0.05, 0.08]]
    n_b, _ = constraint_axes(axis, 0.0)

    def run(eps):
        dth0, dw, dvb0 = eps * x0[0:3], eps * x0[3:6], eps * x0[6:9]
        c_n, v_n = _propagate_body(c0, v_b0, w_b, f_b, g, t_s)
        c_t, v_t = _propagate_body(_rot(dth0) @ c0, v_b0 + dvb0, w_b + dw, f_b, g, t_s)
        d = c_t @ c_n.T
        dth = _skew_log(d)
        dv_b = v_t - v_n
        v_ned = c_n @ v_n
        xi = c_n @ dv_b + np.cross(dth, v_ned)
        return float(n_b @ dv_b), np.r_[dth, xi, dw], c_n, v_n

    eps = 1.0
    d_p, x_p, c_n, v_n = run(eps)
    d_m, x_m, _, _ = run(-eps)
    q_exact = 0.5 * (d_p + d_m)
    x_lin = 0.5 * (x_p - x_m)  # the linear propagation's errors at the update
    nf.q = _quat_from_dcm(c_n)
    nf.vel = c_n @ v_n
    nf.w = w_b.copy()
    m = nf.body_velocity_remainder_matrix(n_b, t_s)
    q_model = 0.5 * float(x_lin @ m @ x_lin)
    assert abs(q_exact) > 1e-4  # the term the NED error's count stood for
    assert q_model == pytest.approx(q_exact, rel=0.1)


def _skew_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (small angles)."""
    ang = np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    ax = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return ax * (0.5 if ang < 1e-12 else ang / (2.0 * np.sin(ang)))


def _quat_from_dcm(r: np.ndarray) -> np.ndarray:
    return quat_from_rotvec(_skew_log(r))


def test_setting_reaches_the_filter_and_keeps_its_covariance_positive():
    """``vehicle.body_velocity_error`` from a scenario override reaches the filter a run
    builds; a 3 s hand-over and turn on it keeps P positive definite (the pipeline's
    checks) and reads the same first GPS fix."""
    from filters.pipeline import run_filter
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    scn = load_flight(
        "tactical",
        [
            "run.rate_hz=200",
            "flight.legs=[{ duration_s = 3.0, ramp_s = 1.0, bank_deg = 30.0 }]",
            "vehicle.body_velocity_error=true",
        ],
    )
    assert scn.vehicle.body_velocity_error is True
    sim = simulate_flight(scn, 0)
    res = run_filter(sim.samples, sim.fixes, sim.config)
    cov = res.estimates.cov_nav
    assert np.all(np.linalg.eigvalsh(cov)[:, 0] > 0)
    assert res.estimates.t_s[-1] > 2.9


def test_body_frame_only_while_the_attitude_is_known():
    """``in_body_frame``: the body-frame error while the attitude's uncertainty curves
    the NED velocity by at most ``BODY_FRAME_MAX_CURVATURE_MPS`` (``|v| tr(P_att) / 2``),
    the NED error above it and whenever the setting is off; the curvature read-out is
    zero in the NED error."""
    from filters.algebra import BODY_FRAME_MAX_CURVATURE_MPS

    nf, _, _ = level_filter()
    nf.vel = np.array([0.0, 60.0, 0.0])
    limit_var = 2.0 * BODY_FRAME_MAX_CURVATURE_MPS / 60.0  # tr(P_att) at the limit, rad^2
    nf.P[ATT, ATT] = np.eye(3) * (0.9 * limit_var / 3.0)
    assert not nf.in_body_frame()  # the setting is off
    nf.body_velocity_error = True
    assert nf.in_body_frame()
    assert np.any(nf.velocity_curvature()[1])
    nf.P[ATT, ATT] = np.eye(3) * (1.1 * limit_var / 3.0)
    assert not nf.in_body_frame()
    mean, cov = nf.velocity_curvature()
    assert not np.any(mean) and not np.any(cov)


@pytest.mark.parametrize("body", [False, True])
def test_injection_resets_the_attitude_covariance_as_exact_rotations_do(body):
    """After a correction ``dth_hat`` the truth's attitude error about the new nominal is
    ``log(exp(e) exp(-dth_hat))`` with ``e ~ N(dth_hat, P)``: the filter's injected
    covariance against 200 000 such errors built with exact rotations. The reset of a
    left error is ``I + [dth_hat]x / 2``; the opposite sign's covariance misses the
    sampled one by far more than the filter's may. The filter holds the reset's heading
    column at ``e_z`` (observability-constrained, ``NavFilter._inject``), so the heading
    here is known well enough (0.1 mrad) that its column does not matter; the test
    below checks that column."""
    nf, _, _ = level_filter()
    nf.body_velocity_error = body
    nf.q = quat_from_euler(*np.radians([20.0, 5.0, 80.0]))
    nf.vel = np.array([1.0, 2.0, 0.0])  # slow, so that the body path stays on
    sig = np.array([0.05, 0.01, 1e-4])  # rad, anisotropic: an isotropic P hides the sign
    p_att = np.diag(sig**2)
    nf.P[ATT, :] = 0.0
    nf.P[:, ATT] = 0.0
    nf.P[ATT, ATT] = p_att
    dth_hat = np.array([0.1, -0.08, 0.12])
    nf.x = np.zeros_like(nf.x)
    nf.x[ATT] = dth_hat
    q_old = nf.q.copy()
    nf._inject()  # the private step every update ends with, driven directly
    rng = np.random.default_rng(11)
    e = rng.multivariate_normal(dth_hat, p_att, size=200_000)
    q_new = nf.q
    new = np.empty_like(e)
    for k, ek in enumerate(e):
        q_t = quat_multiply(quat_from_rotvec(ek), q_old)
        d = quat_multiply(q_t, quat_conjugate(q_new))
        new[k] = quat_to_rotvec(-d if d[0] < 0 else d)
    emp = np.cov(new.T)
    wrong_g = np.eye(3) - skew(0.5 * dth_hat)
    miss = np.linalg.norm(nf.P[ATT, ATT] - emp)
    miss_wrong = np.linalg.norm(wrong_g @ p_att @ wrong_g.T - emp)
    assert np.abs(new.mean(axis=0)).max() < 5e-3  # the injection removed the mean
    assert miss < 0.1 * miss_wrong


def test_injection_leaves_a_turn_about_the_vertical_alone():
    """A turn of the whole solution about the vertical (the left error's ``e_z``) is
    unobservable at rest. Whatever the correction, the reset keeps a heading-only
    covariance heading-only: the exact reset's column, ``e_z + dth_hat x e_z / 2``, put
    part of it into the tilt's rows at every tilt correction, and at rest the fixes read
    that as heading information (``static``: the sigma fell from 5.0 to 3.6 deg while
    the error stayed 5.8 deg rms)."""
    nf, _, _ = level_filter()
    rng = np.random.default_rng(4)
    for _ in range(20):
        nf.P[ATT, :] = 0.0
        nf.P[:, ATT] = 0.0
        nf.P[ATT, ATT] = np.diag([0.0, 0.0, 0.087**2])
        nf.x = np.zeros_like(nf.x)
        nf.x[ATT] = rng.normal(size=3) * 1e-3
        nf._inject()
        assert np.abs(nf.P[6:8, :]).max() == 0.0
        assert nf.P[8, 8] == pytest.approx(0.087**2, rel=1e-12)
