"""The filter's models against exact references: geometry, sideslip, integration, rate products."""

import numpy as np
import pytest
from filterpy.kalman import update as kf_update
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from filters.ekf import FilterNoise, NavFilter
from filters.noise import static_mean_walk_s
from filters.state import ATT, B_F, RATE, VEL
from filters.vehicle_model import (
    ATTITUDE_REMAINDER_UPDATES,
    LATERAL,
    LIFT_JACOBIAN_LAG_BLOCKS,
    SIDESLIP_REMAINDER_UPDATES,
    VERTICAL,
    constraint_axes,
    load_extrapolation_weights,
    prior_weighted_count,
    remainder_moments,
    remainder_variance,
)
from ngnav.conventions import gravity_n_mps2
from ngnav.frontend import ArraySolver
from ngnav.layout import ArrayLayout, kinematic_features, nine_accelerometer_cube
from ngnav.motion import min_jerk_step
from ngnav.mounting import MountingErrors
from ngnav.paper import outward_directions
from ngnav.rotation import (
    dcm_from_quat,
    euler_from_quat,
    quat_conjugate,
    quat_from_euler,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_to_rotvec,
    skew,
)
from tests.helpers import PAIRS, initialise_level
from tests.helpers import level_filter as _filter


def _lift_law_filter() -> NavFilter:
    """A level filter with the airframe's lift law: K = 18 m (known to 0.9 m), an
    offset known to 0.02 rad, the lift-off blend over 32-40 m/s."""
    layout = nine_accelerometer_cube(0.1)
    solver = ArraySolver(layout, np.full(9, 1e-3))
    cov = solver.covariance()
    nf = NavFilter(
        FilterNoise(cov, cov, cov * 1e-6),
        PAIRS,
        np.zeros(3),
        aoa_prior_sigma_rad=0.02,
        aoa_lift_k_m=18.0,
        liftoff_speed_mps=40.0,
        aoa_lift_k_sigma_m=0.9,
    )
    initialise_level(nf)
    return nf


vec3 = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=30, deadline=None)
@given(vec3, vec3, vec3, st.integers(0, 2**31 - 1))
def test_geometry_jacobian_is_exact(wdot, w, f, seed):
    """S G dr is the solved change from moving the sensors by dr (outputs are linear in dr)."""
    nf, layout, solver = _filter(0.0005)
    dr = np.random.default_rng(seed).normal(0.0, 0.001, (9, 3))
    moved = ArrayLayout(layout.positions_b_m + dr, layout.axes_b, lever_arm_m=0.1)
    da = (
        moved.outputs(wdot[None], f[None], w[None])[0]
        - layout.outputs(wdot[None], f[None], w[None])[0]
    )
    sg = nf.geometry_jacobian(wdot, w)
    np.testing.assert_allclose(sg @ dr.ravel(), solver.solve_matrix @ da, atol=1e-12)


def test_position_states_exist_only_with_a_position_sigma():
    assert _filter(0.0)[0].layout.n == 21
    nf = _filter(0.0005)[0]
    assert nf.layout.n == 48
    np.testing.assert_allclose(np.diag(nf.P)[nf.layout.dr], 0.0005**2)


@settings(max_examples=30, deadline=None)
@given(vec3.map(lambda v: v * 0.5), vec3.map(lambda v: v * 10.0))
def test_body_velocity_jacobians_match_finite_differences(rotvec, vel):
    """The lateral (sideslip) and vertical (angle-of-attack) body-velocity Jacobians
    against central differences of the injected error."""
    nf, _, _ = _filter()
    q = quat_from_rotvec(rotvec)
    assert nf.sideslip_model(q, vel)[0] == pytest.approx(dcm_from_quat(q)[:, 1] @ vel)
    for axis in (LATERAL, VERTICAL):
        h0, h = nf.body_velocity_model(q, vel, axis)
        assert h0 == pytest.approx(dcm_from_quat(q)[:, axis] @ vel)
        eps = 1e-6
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            # error convention: truth = exp(dtheta) * estimate, v_true = v + dv
            up = nf.body_velocity_model(quat_multiply(quat_from_rotvec(d), q), vel, axis)[0]
            dn = nf.body_velocity_model(quat_multiply(quat_from_rotvec(-d), q), vel, axis)[0]
            assert h[0, ATT][k] == pytest.approx((up - dn) / (2 * eps), abs=1e-6)
            up = nf.body_velocity_model(q, vel + d, axis)[0]
            dn = nf.body_velocity_model(q, vel - d, axis)[0]
            assert h[0, VEL][k] == pytest.approx((up - dn) / (2 * eps), abs=1e-6)


@settings(max_examples=30, deadline=None)
@given(vec3.map(lambda v: v * 0.5), vec3.map(lambda v: v * 10.0), st.floats(-0.3, 0.3))
def test_angle_of_attack_model_and_jacobian(rotvec, vel, aoa):
    """With the AOA state the vertical model is the velocity along the wind-normal
    axis ``[-sin a, 0, cos a]``; its Jacobian in attitude, velocity and angle of attack
    against central differences (the lateral model does not depend on it)."""
    nf, _, _ = _filter(aoa_sigma_rad=0.05)
    assert nf.layout.n == 22 and nf.layout.aoa == slice(21, 22)
    q = quat_from_rotvec(rotvec)
    h0, h = nf.body_velocity_model(q, vel, VERTICAL, aoa)
    v_b = dcm_from_quat(q).T @ vel
    assert h0 == pytest.approx(-np.sin(aoa) * v_b[0] + np.cos(aoa) * v_b[2], abs=1e-12)
    eps = 1e-6
    up = nf.body_velocity_model(q, vel, VERTICAL, aoa + eps)[0]
    dn = nf.body_velocity_model(q, vel, VERTICAL, aoa - eps)[0]
    assert h[0, nf.layout.aoa][0] == pytest.approx((up - dn) / (2 * eps), abs=1e-6)
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        up = nf.body_velocity_model(quat_multiply(quat_from_rotvec(d), q), vel, VERTICAL, aoa)[0]
        dn = nf.body_velocity_model(quat_multiply(quat_from_rotvec(-d), q), vel, VERTICAL, aoa)[0]
        assert h[0, ATT][k] == pytest.approx((up - dn) / (2 * eps), abs=1e-6)
    assert nf.body_velocity_model(q, vel, LATERAL, aoa)[1][0, nf.layout.aoa][0] == 0.0
    # a vehicle flying at its angle of attack meets the model exactly
    assert nf.body_velocity_model(q, dcm_from_quat(q) @ [np.cos(aoa), 0, np.sin(aoa)], 2, aoa)[
        0
    ] == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("speed_scale", [1.0, 0.72])  # flying; inside the lift-off blend
def test_lift_law_jacobian_matches_finite_differences(speed_scale):
    """With the airframe's lift law the angle of attack is ``w (alpha_b + K n_w / V^2)``,
    so the vertical model also depends on the velocity (through V), the force bias
    (through n_w), the offset and K: each Jacobian column against central differences
    of the whole chain (``set_load`` then the model; the angle inside ``n_w`` held). The
    load is steady, so the Jacobian's load (``LIFT_JACOBIAN_LAG_BLOCKS`` back) is this one."""
    nf = _lift_law_filter()
    assert nf.layout.n_aoa == 2
    q = quat_from_rotvec(np.array([0.4, -0.1, 1.2]))
    vel = np.array([30.0, -40.0, 3.0]) * speed_scale  # 50.1 m/s, or 36 m/s (w = 0.79)
    f_b = np.array([1.5, 0.3, -17.0])
    nf.q, nf.aoa_b = q, np.deg2rad(-1.2)

    def model(v, d_bf=None, d_b=0.0, d_k=0.0):
        nf.vel, nf._lift_u, nf._lift_w = v, 0.0, 1.0  # same angle inside n_w every time
        nf.set_load(f_b - (np.zeros(3) if d_bf is None else d_bf))  # f_true = f - d_bias
        nf.aoa_b += d_b
        nf.aoa_k += d_k
        y = nf.body_velocity_model(q, v, VERTICAL, nf.aoa)[0]
        nf.aoa_b -= d_b
        nf.aoa_k -= d_k
        return y

    model(vel)
    _, h = nf.body_velocity_model(q, vel, VERTICAL, nf.aoa)
    eps = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        fd = (model(vel + d) - model(vel - d)) / (2 * eps)
        assert h[0, VEL][k] == pytest.approx(fd, rel=1e-6, abs=1e-9)
        fd = (model(vel, d_bf=d) - model(vel, d_bf=-d)) / (2 * eps)
        assert h[0, B_F][k] == pytest.approx(fd, rel=1e-6, abs=1e-9)
    ia = nf.layout.aoa.start
    fd = (model(vel, d_b=eps) - model(vel, d_b=-eps)) / (2 * eps)
    assert h[0, ia] == pytest.approx(fd, rel=1e-6)
    fd = (model(vel, d_k=eps) - model(vel, d_k=-eps)) / (2 * eps)
    assert h[0, ia + 1] == pytest.approx(fd, rel=1e-6)
    assert abs(h[0, ia + 1]) > 0 and abs(h[0, B_F][2]) > 0  # the terms are exercised
    assert (nf._lift_dw > 0) == (speed_scale < 1.0)


def test_lift_law_jacobian_carries_the_sensor_positions_through_the_load():
    """With sensor-position (``DR``) states the load the lift law reads has lost
    ``S G dr_hat`` as the propagation's force has, so an error in ``dr`` moves the angle
    of attack as a force bias does: the Jacobian's ``DR`` columns (from ``set_load``'s
    ``sg_f``) against central differences of the whole chain, and zero without ``sg_f``."""
    layout = nine_accelerometer_cube(0.1)
    solver = ArraySolver(layout, np.full(9, 1e-3))
    cov = solver.covariance()
    nf = NavFilter(
        FilterNoise(cov, cov, cov * 1e-6, 0.0005),
        PAIRS,
        np.zeros(3),
        sensor_axes_b=layout.axes_b,
        solve_matrix=solver.solve_matrix,
        aoa_prior_sigma_rad=0.02,
        aoa_lift_k_m=18.0,
        aoa_lift_k_sigma_m=0.9,
    )
    initialise_level(nf)
    assert nf.layout.n_dr == 27 and nf.layout.n_aoa == 2
    q = quat_from_rotvec(np.array([0.3, -0.2, 0.9]))
    vel = np.array([40.0, -25.0, 2.0])
    f_b = np.array([1.0, -0.4, -19.0])
    sg_f = nf.geometry_jacobian(np.array([2.0, -6.0, 1.5]), np.array([1.2, -0.8, 0.5]))[3:6]
    nf.q, nf.vel = q, vel

    def model(d_dr):
        nf._lift_u, nf._lift_w = 0.0, 1.0  # the same angle inside n_w every time
        nf.set_load(f_b - sg_f @ d_dr, sg_f=sg_f)  # f_true = f - S G d_dr
        return nf.body_velocity_model(q, vel, VERTICAL, nf.aoa)[0]

    model(np.zeros(27))
    _, h = nf.body_velocity_model(q, vel, VERTICAL, nf.aoa)
    dr = nf.layout.dr
    eps = 1e-7
    fd = np.empty(27)
    for k in range(27):
        d = np.zeros(27)
        d[k] = eps
        fd[k] = (model(d) - model(-d)) / (2 * eps)
    np.testing.assert_allclose(h[0, dr], fd, rtol=1e-5, atol=1e-9)
    assert np.max(np.abs(h[0, dr])) > 1e-3  # exercised: m/s per m of sensor position
    nf._lift_u, nf._lift_w = 0.0, 1.0
    nf.set_load(f_b)
    _, h = nf.body_velocity_model(q, vel, VERTICAL, nf.aoa)
    assert not np.any(h[0, dr])


def test_lift_law_jacobian_takes_an_older_load_than_the_prediction():
    """The angle is predicted with the newest load; the Jacobian's ``K`` column (and
    the velocity term through ``u``) with the load ``LIFT_JACOBIAN_LAG_BLOCKS`` blocks
    back, so that the two carry independent noise."""
    nf = _lift_law_filter()
    nf.vel = np.array([60.0, 0.0, 0.0])
    loads = [9.0, 12.0, 15.0, 18.0]
    for n_w in loads:
        nf.set_load(np.array([0.0, 0.0, -n_w]) / np.cos(nf.aoa))  # n_w along the lift axis
    u = np.array(loads) / 60.0**2
    ia = nf.layout.aoa.start
    assert nf.aoa == pytest.approx(nf.aoa_b + nf.aoa_k * u[-1], rel=1e-12)
    j = nf.aoa_jacobian(nf.vel)
    assert j[ia + 1] == pytest.approx(u[-1 - LIFT_JACOBIAN_LAG_BLOCKS], rel=1e-12)
    wk = nf.aoa_k / 60.0**2
    assert j[VEL][0] == pytest.approx(-2.0 * wk * u[-1 - LIFT_JACOBIAN_LAG_BLOCKS] * 60.0)


def test_angle_of_attack_model_counts_the_loads_noise():
    """The angle predicted from a noisy load carries ``w K du``: the vertical model's R
    gains ``(dv/dalpha)^2 (w K)^2 a^T C a / V^4`` (``a`` the lift axis, ``C`` the load's
    covariance) and the angle's sigma ``(w K)^2 a^T C a / V^4``; without ``load_cov``
    neither does."""
    speed = 60.0
    out = {}
    for told in (False, True):
        nf = _lift_law_filter()
        nf.vel = np.array([speed, 0.0, 0.0])
        nf.body_velocity_log = []
        cov = np.diag([0.01, 0.02, 0.04])
        nf.set_load(np.array([0.0, 0.0, -12.0]), load_cov=cov if told else None)
        a = nf._lift_axis.copy()
        aca = float(a @ cov @ a)
        wk2 = (nf._lift_w * nf.aoa_k) ** 2  # before the update moves K
        sigma_before = nf.aoa_sigma
        nf.update_angle_of_attack(np.deg2rad(3e-5), 1.0)
        rec = nf.body_velocity_log[-1]
        out[told] = (rec.r_m2ps2, rec.dv_daoa_mps, sigma_before, aca, wk2)
    (r0, dv_da, s0, _, _), (r1, _, s1, aca, wk2) = out[False], out[True]
    assert r1 - r0 == pytest.approx(dv_da**2 * wk2 * aca / speed**4, rel=1e-9)
    assert s1**2 - s0**2 == pytest.approx(wk2 * aca / speed**4, rel=1e-9)
    assert r1 > r0


def test_set_load_survives_a_diverged_speed():
    """A filter whose velocity has run away (the array alone, no GPS) still takes its
    load: the covariance check, not an OverflowError in the law, reports the
    divergence."""
    nf = _lift_law_filter()
    nf.vel = np.array([1e120, 0.0, 0.0])
    nf.set_load(np.array([0.0, 0.0, -9.81]), load_cov=np.eye(3))
    assert nf._lift_u_var == 0.0 and abs(nf._lift_u) < 1e-200


def _noisy_load_run(seed: int, n_updates: int, sigma_f_mps2: float) -> tuple[float, float]:
    """One airframe's lift law learnt from ``n_updates`` angle-of-attack updates, five
    noisy block loads before each (level, 60 m/s, attitude and velocity known; the load
    switching between 1 and 1.5 g every 20 updates so that offset and ``K`` separate;
    above the lift-off blend). The filter is told the load's noise (``set_load``'s
    ``load_cov``), which is then the update's only noise beyond the numerical floor.
    Returns the two states' errors over their sigmas."""
    rng = np.random.default_rng([20261124, seed])
    nf = _lift_law_filter()
    speed, a_prior, a_sigma = 60.0, np.deg2rad(-1.5), 0.02
    q = np.array([1.0, 0.0, 0.0, 0.0])
    nf.initialise(
        0.0, np.zeros(3), np.array([speed, 0, 0]), q, np.zeros(3), 1e-6, 1e-9,
        np.full(3, 1e-9), 1e-9, aoa_rad=a_prior,
    )  # fmt: skip
    a0 = a_prior + rng.normal(0.0, a_sigma)
    k_true = nf.aoa_lift_k_m + rng.normal(0.0, nf.aoa_lift_k_sigma_m)
    load_cov = np.eye(3) * sigma_f_mps2**2  # what the filter is told of each block's load
    for i in range(n_updates):
        n_w = 9.81 * (1.0 if (i // 20) % 2 == 0 else 1.5)
        alpha = a0 + k_true * n_w / speed**2
        lift_axis = np.array([np.sin(alpha), 0.0, -np.cos(alpha)])
        nf.q, nf.vel = q.copy(), speed * np.array([np.cos(alpha), 0.0, np.sin(alpha)])
        for _ in range(5):
            f = n_w * lift_axis + rng.normal(0.0, sigma_f_mps2, 3)
            nf.set_load(f - nf.bias[3:6], load_cov=load_cov)
        nf.update_angle_of_attack(np.deg2rad(3e-5), 1.0)  # the scenarios' numerical floor
    ia = nf.layout.aoa.start
    return (
        (nf.aoa_b - a0) / np.sqrt(nf.P[ia, ia]),
        (nf.aoa_k - k_true) / np.sqrt(nf.P[ia + 1, ia + 1]),
    )


def test_lift_law_states_stay_centred_under_a_noisy_load():
    """Errors in variables: with the Jacobian's load sharing the predicted angle's noise
    the update pushed the offset up and ``K`` down (this Monte Carlo with
    ``LIFT_JACOBIAN_LAG_BLOCKS`` set to 0, measured: mean z +2.71 / -2.76, rms 2.91 / 2.95,
    standard error 0.07). With independent noise (measured: mean z -0.005 / 0.012, rms
    1.008 / 1.007) the mean z of each state is within 4 standard errors of 0, and its sum
    of z^2 inside the two-sided 0.998 chi-square interval: the load's noise, which the
    filter is told, is then all the update's noise, and the states' sigmas are right."""
    runs = 200
    z = np.array([_noisy_load_run(s, 200, 0.5) for s in range(runs)])
    se = z.std(axis=0, ddof=1) / np.sqrt(runs)
    assert np.all(np.abs(z.mean(axis=0)) < 4.0 * se), (z.mean(axis=0), se)
    z2 = np.sum(z**2, axis=0)
    assert np.all((z2 > chi2.ppf(0.001, runs)) & (z2 < chi2.ppf(0.999, runs))), z2 / runs


@pytest.mark.parametrize(
    ("axis", "aoa_state"), [(LATERAL, False), (VERTICAL, False), (VERTICAL, True)]
)
def test_body_velocity_second_order_terms_match_monte_carlo(axis, aoa_state):
    """Mean and variance of what the linear sideslip (lateral) and angle-of-attack
    (vertical) models leave out, against sampling.

    Errors drawn from the filter's own covariance (correlated attitude and velocity,
    coast-sized) are injected exactly (``q_true = exp(dtheta) q``); the true lateral
    velocity minus its linear prediction must have the mean and variance that
    ``sideslip_second_order`` gives, within the sampling error of 200 000 draws.
    With the ``AOA`` state (a 1.5 deg angle of attack known to 1 deg, correlated with
    the rest) its error turns the constraint axis too.
    """
    nf, _, _ = _filter(aoa_sigma_rad=0.02 if aoa_state else 0.0)
    rng = np.random.default_rng(7)
    nf.q = quat_from_rotvec(np.array([0.3, -0.1, 2.0]))
    nf.vel = np.array([14.0, -15.0, 1.0])
    nf.aoa_b = np.deg2rad(1.5) if aoa_state else 0.0  # no lift law: the state is the angle
    idx = np.r_[6:9, 3:6, nf.layout.aoa.start] if aoa_state else np.r_[6:9, 3:6]
    d = idx.size
    a = rng.normal(size=(d, d))
    px = a @ a.T
    scale = np.r_[[0.03] * 3, [1.5] * 3, [0.0175] * (d - 6)]
    px *= np.outer(scale, scale) / d
    p = np.eye(nf.layout.n) * 1e-6
    p[np.ix_(idx, idx)] = px
    nf.P = p
    y0, h = nf.body_velocity_model(nf.q, nf.vel, axis, nf.aoa)
    mean, var, var_att, mean_att = nf.body_velocity_second_order(axis)
    if axis == LATERAL:
        assert (mean, var, var_att, mean_att) == nf.sideslip_second_order()
    n = 200_000
    x = rng.multivariate_normal(np.zeros(d), px, n)
    dq = np.array([quat_from_rotvec(e) for e in x[:, 0:3]])
    c_true = np.array([dcm_from_quat(quat_multiply(e, nf.q)) for e in dq])
    al = nf.aoa + (x[:, 6] if aoa_state else 0.0)
    n_b = np.zeros((n, 3))
    if axis == LATERAL:
        n_b[:, 1] = 1.0
    else:
        n_b[:, 0], n_b[:, 2] = -np.sin(al), np.cos(al)
    y_true = np.einsum("ki,kji,kj->k", n_b, c_true, nf.vel + x[:, 3:6])
    resid = y_true - (y0 + x[:, 3:6] @ h[0, VEL] + x[:, 0:3] @ h[0, ATT])
    if aoa_state:
        resid -= x[:, 6] * h[0, nf.layout.aoa][0]
    sd = np.sqrt(var)
    assert abs(resid.mean() - mean) < 4.0 * sd / np.sqrt(n)
    # the sample variance: a 2 % band (sampling about 0.5 %, third-order terms of the
    # exponential below that at these sizes; measured 0.4 %)
    assert resid.var() == pytest.approx(var, rel=0.02)
    # the attitude-product part alone, dtheta^T A dtheta / 2 with a = C n_b at the estimate
    c = dcm_from_quat(nf.q)
    a_n = c @ (n_b[0] if axis == LATERAL else [-np.sin(nf.aoa), 0.0, np.cos(nf.aoa)])
    a_m = 0.5 * (np.outer(a_n, nf.vel) + np.outer(nf.vel, a_n)) - (a_n @ nf.vel) * np.eye(3)
    q_att = 0.5 * np.einsum("ki,ij,kj->k", x[:, 0:3], a_m, x[:, 0:3])
    assert q_att.var() == pytest.approx(var_att, rel=0.02)
    assert abs(q_att.mean() - mean_att) < 4.0 * np.sqrt(var_att / n)
    assert 0.0 < var_att < var
    assert var > 1e-3  # coast-sized errors make the term matter (R is 1.2e-3 at 20 m/s for 0.1 deg)


def _lift_law_at(speed_mps: float, aligned: bool) -> tuple[NavFilter, float, callable]:
    """The lift-law filter at ``speed_mps`` under a steady load, and the exact vertical
    model at an error ``x = (dtheta, dv, d alpha_b, dK)`` written out here: the true
    state's velocity along its own wind-normal axis, at the angle ``w(V) (alpha_b + K
    n_w / V^2)`` of its own speed, offset and ``K`` (``n_w`` held, the force bias
    exact). ``aligned`` flies the body at its angle of attack (the model's value 0)."""
    nf = _lift_law_filter()
    q = quat_from_rotvec(np.array([0.1, -0.05, 0.9]))
    f_b = np.array([1.0, 0.2, -15.0])
    nf.q, nf.aoa_b = q, np.deg2rad(-1.0)
    direction = np.array([0.6, -0.8, 0.05]) / np.linalg.norm([0.6, -0.8, 0.05])
    for _ in range(8):  # a steady load: the Jacobian's lagged load is this one
        if aligned:
            direction = dcm_from_quat(q) @ [np.cos(nf.aoa), 0.0, np.sin(nf.aoa)]
        nf.vel = speed_mps * direction
        nf.set_load(f_b)
    n_w = float(nf._lift_axis @ f_b)
    vel, k_m, alpha_b = nf.vel.copy(), nf.aoa_k, nf.aoa_b

    def model(x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        v_t = vel + x[:, 3:6]
        speed_t = np.linalg.norm(v_t, axis=1)
        w_t = min_jerk_step((speed_t - 32.0) / 8.0)[0]
        alpha_t = w_t * (alpha_b + x[:, 6] + (k_m + x[:, 7]) * n_w / speed_t**2)
        n_b = np.column_stack([-np.sin(alpha_t), np.zeros(len(x)), np.cos(alpha_t)])
        dq = np.array([quat_from_rotvec(e) for e in x[:, 0:3]])
        c_t = np.array([dcm_from_quat(quat_multiply(e, q)) for e in dq])
        return np.einsum("ki,kji,kj->k", n_b, c_t, v_t)

    return nf, n_w, model


@settings(max_examples=25, deadline=None)
@given(
    st.sampled_from([33.0, 36.0, 39.0, 50.0]),  # in the lift-off blend (32-40 m/s); flying
    st.lists(st.floats(-1.0, 1.0), min_size=8, max_size=8).map(np.array),
)
def test_lift_law_second_order_terms_are_the_models_curvature(speed_mps, d):
    """The remainder's quadratic form is the exact model's second derivative.

    For a rank-one covariance ``P = d d^T`` over ``(dtheta, dv, d alpha_b, dK)`` the
    remainder's mean is ``d^T M d / 2``, so twice it must be the second directional
    derivative of the exact model along ``d`` (central differences). The blend's own
    curvature ``w''`` is left to ``blend_remainder_var`` by design and taken out of the
    reference. A remainder without the speed's products with the law's states (the
    lift-off blend's slope times the offset's error, ``1 / V^2`` times ``K``'s) or
    without the speed's own curvature fails by far more than the tolerance."""
    nf, _, model = _lift_law_at(speed_mps, aligned=False)
    d = d * np.r_[[0.01] * 3, [1.0] * 3, 0.02, 1.0]
    if not np.any(d):
        return
    ia = nf.layout.aoa
    idx = np.r_[6:9, 3:6, ia.start, ia.start + 1]
    p = np.zeros((nf.layout.n, nf.layout.n))
    p[np.ix_(idx, idx)] = np.outer(d, d)
    nf.P = p
    got = 2.0 * nf.body_velocity_second_order(VERTICAL).mean

    def second_difference(eps: float) -> float:
        return float((model(eps * d) - 2.0 * model(0.0 * d) + model(-eps * d))[0]) / eps**2

    # Richardson's extrapolation of the central difference: where the terms cancel to a
    # thousandth of their size, its O(eps^2) error alone reached 0.2 % at eps = 1e-3
    want = (4.0 * second_difference(1e-3) - second_difference(2e-3)) / 3.0
    # the blend's w'' part: dv/dalpha * w''(V) * law * dV^2
    _, t_b = constraint_axes(VERTICAL, nf.aoa)
    dv_da = -float((dcm_from_quat(nf.q) @ t_b) @ nf.vel)
    speed = float(np.linalg.norm(nf.vel))
    dds = min_jerk_step((speed - 32.0) / 8.0)[2] / 64.0
    want -= dv_da * dds * nf._unblended_aoa() * float(nf.vel @ d[3:6] / speed) ** 2
    assert got == pytest.approx(want, rel=1e-4, abs=1e-8)


@pytest.mark.parametrize(
    ("speed_mps", "speed_sigma_mps", "k_sigma_m"),
    [(36.0, 0.1, 0.9), (50.0, 0.3, 2.0)],  # the blend's middle (w'' = 0); flying
)
def test_lift_law_second_order_terms_match_monte_carlo(speed_mps, speed_sigma_mps, k_sigma_m):
    """The same against sampling, with the body flying at its angle of attack: errors
    drawn from a covariance (the speed 0.1-0.3 m/s, the law's states as uncertain as a
    prior), the exact model minus the linear prediction must have the remainder's mean
    and variance (plus, in the blend, ``blend_remainder_var``'s part) within 2 % and
    the sampling error of 200 000 draws. The terms beyond the second order stay below
    that at these sizes: the largest, ``V da^3 / 6`` from the axis's sine, is 0.4 % of
    the variance with ``K`` 2 m uncertain (2.2 % at 5 m, measured). The speed's product
    with the law's states is a fifth of the variance or more: without it a remainder
    fails."""
    nf, n_w, model = _lift_law_at(speed_mps, aligned=True)
    rng = np.random.default_rng(23)
    ia = nf.layout.aoa
    idx = np.r_[6:9, 3:6, ia.start, ia.start + 1]
    px = np.diag(np.r_[[1e-4**2] * 3, [speed_sigma_mps**2] * 3, 0.02**2, k_sigma_m**2])
    p = np.eye(nf.layout.n) * 1e-12
    p[np.ix_(idx, idx)] = px
    nf.P = p
    vel = nf.vel
    y0, h = nf.body_velocity_model(nf.q, vel, VERTICAL, nf.aoa)
    assert abs(y0) < 1e-12
    rem = nf.body_velocity_second_order(VERTICAL)
    _, t_b = constraint_axes(VERTICAL, nf.aoa)
    dv_da = -float((dcm_from_quat(nf.q) @ t_b) @ vel)
    blend = dv_da**2 * nf._unblended_aoa() ** 2 * nf.blend_remainder_var()
    x = rng.multivariate_normal(np.zeros(idx.size), px, 200_000)
    resid = model(x) - (y0 + x[:, 3:6] @ h[0, VEL] + x[:, 0:3] @ h[0, ATT] + x[:, 6:8] @ h[0, ia])
    # the product, written out: dv/dalpha dV (w' d alpha_b + (w' u - 2 w u / V) dK)
    speed = float(np.linalg.norm(vel))
    u = n_w / speed**2
    d_v = x[:, 3:6] @ vel / speed
    dw, w = nf._lift_dw, nf._lift_w
    mixed = dv_da * d_v * (dw * x[:, 6] + (dw - 2.0 * w / speed) * u * x[:, 7])
    assert mixed.var() > 0.2 * resid.var()
    var = rem.var + blend
    assert resid.var() == pytest.approx(var, rel=0.02)
    assert abs(resid.mean() - rem.mean) < 4.0 * np.sqrt(var / x.shape[0])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([6, 7]))
def test_remainder_moments_are_those_of_a_gaussian_quadratic_form(seed, d):
    """``q = x^T M x / 2`` with ``x ~ N(0, P)`` is ``sum_i lambda_i z_i^2 / 2`` over the
    eigenvalues of ``L^T M L`` (``P = L L^T``): mean ``sum lambda / 2``, variance
    ``sum lambda^2 / 2``; the attitude part is the same on the first three rows."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(d, d))
    m = a + a.T
    b = rng.normal(size=(d, d))
    p = b @ b.T + 0.1 * np.eye(d)
    rem = remainder_moments(m, p)

    def exact(mm: np.ndarray, pp: np.ndarray) -> tuple[float, float]:
        el = np.linalg.cholesky(pp)
        lam = np.linalg.eigvalsh(el.T @ mm @ el)
        return 0.5 * float(lam.sum()), 0.5 * float(lam @ lam)

    mean, var = exact(m, p)
    mean_att, var_att = exact(m[:3, :3], p[:3, :3])
    assert rem.mean == pytest.approx(mean, rel=1e-9, abs=1e-12)
    assert rem.var == pytest.approx(var, rel=1e-9)
    assert rem.mean_att == pytest.approx(mean_att, rel=1e-9, abs=1e-12)
    assert rem.var_att == pytest.approx(var_att, rel=1e-9)


@pytest.mark.parametrize("axis", [LATERAL, VERTICAL])
def test_body_velocity_update_counts_the_correlated_remainder(axis):
    """R is the sigma's body velocity squared (horizontal speed for the sideslip, 3-D
    speed for the angle of attack) plus the remainder's variance counted
    ``SIDESLIP_REMAINDER_UPDATES`` times and its attitude-product part
    ``ATTITUDE_REMAINDER_UPDATES`` times; the remainder's mean shifts the prediction.

    The reference is one filterpy update built here from the documented formula, at a
    coast-sized covariance where the remainder dominates R.
    """
    nf, _, _ = _filter()
    rng = np.random.default_rng(11)
    nf.q = quat_from_rotvec(np.array([0.2, 0.05, 1.0]))
    nf.vel = 20.0 * dcm_from_quat(nf.q)[:, 0]  # along the body x axis: no sideslip
    v0 = nf.vel.copy()
    idx = np.r_[6:9, 3:6]
    a = rng.normal(size=(6, 6))
    scale = np.r_[[0.05] * 3, [1.0] * 3]  # 3 deg tilts: the attitude products matter too
    p = np.eye(nf.layout.n) * 1e-6
    p[np.ix_(idx, idx)] = (a @ a.T) * np.outer(scale, scale) / 6.0
    nf.P = p
    sigma = np.deg2rad(0.003)
    v_lat, h = nf.body_velocity_model(nf.q, nf.vel, axis)
    mean2, var2, var_att, _ = nf.body_velocity_second_order(axis)
    speed = np.hypot(v0[0], v0[1]) if axis == LATERAL else np.linalg.norm(v0)
    r0 = (speed * np.tan(sigma)) ** 2
    assert var2 > 10 * r0  # the remainder dominates, so the factor matters
    extra = ATTITUDE_REMAINDER_UPDATES - SIDESLIP_REMAINDER_UPDATES
    # the attitude part's own count changes R by more than 10 %
    assert extra * var_att > 0.1 * SIDESLIP_REMAINDER_UPDATES * var2
    r = np.array([[r0 + SIDESLIP_REMAINDER_UPDATES * var2 + extra * var_att]])
    x_ref, p_ref = kf_update(np.zeros(nf.layout.n), p.copy(), np.array([-(v_lat + mean2)]), r, h)
    if axis == LATERAL:
        nis = nf.update_sideslip(sigma, 5.0)
    else:
        nis = nf.update_angle_of_attack(sigma, 5.0)
    s = float((h @ p @ h.T)[0, 0] + r[0, 0])
    assert nis == pytest.approx(float(np.squeeze(v_lat + mean2)) ** 2 / s, rel=1e-9)
    # the attitude reset after injection (first order, G = I + [dtheta]x / 2 on ATT, the
    # left error's: tests/test_body_velocity_error.py checks it against exact rotations),
    # its heading column held at e_z (the observability-constrained reset)
    g = np.eye(nf.layout.n)
    g[ATT, ATT] += 0.5 * skew(x_ref[ATT])
    g[6:8, 8] = 0.0
    np.testing.assert_allclose(nf.P, g @ p_ref @ g.T, rtol=0, atol=1e-12)
    used = (nf.counters.sideslip_used, nf.counters.aoa_used)
    assert used == ((1, 0) if axis == LATERAL else (0, 1))
    np.testing.assert_allclose(nf.vel, v0 + x_ref[VEL], atol=1e-12)


def test_trapezoid_is_exact_for_constant_angular_acceleration():
    """From rest about a fixed axis: w = a t and angle = a t^2 / 2, exactly, in any block size."""
    nf, _, _ = _filter()
    a = np.array([0.3, -0.2, 0.5])
    dt = 1e-3
    nf.set_last_sample(a, np.array([0.0, 0.0, -9.80665]))
    t = 0.0
    for k in (10, 7, 10, 3, 10):
        nf.propagate(np.tile(a, (k, 1)), np.tile([0.0, 0.0, -9.80665], (k, 1)), dt)
        t += k * dt
    np.testing.assert_allclose(nf.w, a * t, rtol=1e-12)
    q_exact = quat_normalize(quat_from_rotvec(0.5 * a * t * t))
    np.testing.assert_allclose(nf.q, q_exact, atol=1e-12)


def test_trapezoid_is_exact_for_constant_specific_force():
    """Without rotation a constant force gives v = a t and p = a t^2 / 2 exactly, in any block
    size, with ``a = (I + (P_att - tr(P_att) I) / 2) C f + g`` (the attitude error's mean)."""
    nf, _, _ = _filter()
    f_b = np.array([1.2, -0.4, -9.0])
    dt = 1e-3
    c = dcm_from_quat(nf.q)
    pa = nf.P[ATT, ATT]
    a = (np.eye(3) + 0.5 * (pa - np.trace(pa) * np.eye(3))) @ c @ f_b + gravity_n_mps2()
    nf.set_last_sample(np.zeros(3), f_b)
    nf.vel = np.array([12.0, -3.0, 0.5])
    pos0, vel0 = nf.pos.copy(), nf.vel.copy()
    t = 0.0
    for k in (10, 7, 10, 3, 10):
        nf.P[ATT, ATT] = pa  # keep the mean's correction fixed over the run
        nf.propagate(np.zeros((k, 3)), np.tile(f_b, (k, 1)), dt)
        t += k * dt
    np.testing.assert_allclose(nf.vel, vel0 + a * t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(nf.pos, pos0 + vel0 * t + 0.5 * a * t * t, rtol=0, atol=1e-12)


def test_rate_product_jacobian_shrinks_rates_inside_their_uncertainty():
    """A rate smaller than its own sigma carries no product information; a large one keeps it."""
    nf, _, _ = _filter()
    w_block = np.tile([0.002, 1.5, -0.8], (10, 1))
    var = np.array([0.01**2, 0.01**2, 0.01**2])
    _, h = nf.rate_model(w_block, rate_var=var)
    _, h_plain = nf.rate_model(w_block)
    # rows: (y z), (x z), (x y); column RATE x gets w_z and w_y in rows 1 and 2
    np.testing.assert_allclose(h[1:, RATE][:, 0], h_plain[1:, RATE][:, 0], rtol=1e-4)
    # |w_x| = 0.002 < sigma 0.01: its coefficient (rows 1, 2 -> columns z, y) is zero
    assert h[1, RATE][2] == 0.0 and h[2, RATE][1] == 0.0
    assert h_plain[1, RATE][2] == pytest.approx(0.002)


@pytest.mark.parametrize(
    ("yaw_deg", "course_deg", "reset"),
    [
        (180.0, 0.0, True),  # flying backwards: zero sideslip, but the wrong way round
        (20.0, 0.0, True),  # tens of degrees off: every sideslip gate fails
        (0.5, 0.0, False),  # inside the gate: the heading keeps its own estimate
        (179.5, -179.5, False),  # the same 1 deg across the +-180 deg cut
    ],
)
def test_heading_goes_onto_a_course_it_contradicts(yaw_deg, course_deg, reset):
    nf, _, _ = _filter()
    roll, pitch = np.deg2rad(3.0), np.deg2rad(-2.0)
    nf.q = quat_from_euler(roll, pitch, np.deg2rad(yaw_deg))
    nf.P[8, 8] = np.deg2rad(1.0) ** 2
    sigma = np.deg2rad(0.8)
    assert nf.check_heading_against_course(np.deg2rad(course_deg), sigma) is reset
    r, p, y = euler_from_quat(nf.q)
    assert (r, p) == pytest.approx((roll, pitch), abs=1e-12)  # the tilt is kept
    if reset:
        assert y == pytest.approx(np.deg2rad(course_deg), abs=1e-12)
        assert nf.P[8, 8] == pytest.approx(sigma**2)
        assert not np.any(nf.P[8, :8]) and not np.any(nf.P[8, 9:])
        assert nf.counters.heading_resets == 1
    else:
        assert y == pytest.approx(np.deg2rad(yaw_deg), abs=1e-12)
        assert nf.counters.heading_resets == 0


@pytest.mark.parametrize(
    ("yaw_deg", "backwards"), [(180.0, True), (95.0, True), (85.0, False), (0.0, False)]
)
def test_a_heading_more_than_90_deg_off_the_velocity_flies_backwards(yaw_deg, backwards):
    nf, _, _ = _filter()
    nf.vel = np.array([20.0, 0.0, -1.0])  # north, climbing
    nf.q = quat_from_euler(np.deg2rad(3.0), np.deg2rad(-2.0), np.deg2rad(yaw_deg))
    assert nf.flies_backwards() is backwards


def test_a_take_off_that_settles_flying_backwards_is_put_on_its_course():
    """``uav-survey`` at the paper's grade, run 4: its heading drifts 125 deg on the runway
    and the take-off's fixes relearn the tilt into a heading 180 deg off (which both vehicle
    models accept: the velocity has no lateral and no wind-normal part), told as 0.3 deg.
    The first fix that finds the state flying backwards puts the heading on the course;
    before, the flip stood at 17 s (179.9 deg) with a NEES of 6e5."""
    from filters.bench import _first_seconds
    from filters.evaluate import run_errors
    from filters.pipeline import run_filter
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    sim = simulate_flight(load_flight("uav-survey", ["sensor.preset=ic3022"]), 4)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, 30.0)
    res = run_filter(samples, fixes, sim.config)
    assert res.counts["heading resets to the GPS course"] >= 1 and not res.track_losses
    est = res.estimates
    after = (est.t_s > 16.0) & (est.t_s < 30.0)  # airborne, the tilt relearned
    yaw_err = np.rad2deg(run_errors(est, sim.truth).att_ned_rad[after, 2])
    assert np.max(np.abs(yaw_err)) < 5.0


def test_a_fix_that_finds_the_tilt_unknown_starts_the_filter_again():
    """``uav-survey`` at the paper's grade, run 0: its 30 s coast ends with a tilt 1-sigma
    above 100 deg. The first fix finds it beyond ``LOST_TILT_SIGMA_DEG`` and the filter
    starts again from the next two fixes (tilt from the GPS acceleration, heading from the
    course); fused on instead, its velocity 1-sigma went from 16 m/s to 10^6 m/s over 35 s
    of accepted fixes."""
    from filters.evaluate import run_errors
    from filters.pipeline import run_filter
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    sim = simulate_flight(load_flight("uav-survey", ["sensor.preset=ic3022"]), 0)
    res = run_filter(sim.samples, sim.fixes, sim.config, truth=sim.truth)
    (loss,) = res.track_losses
    assert 329.9 < loss.lost_at_s < 331.0 and "tilt 1-sigma" in loss.reason
    assert loss.restarted_s - loss.lost_at_s < 1.0
    est = res.estimates
    after = (est.t_s > 335.0) & (est.t_s < 400.0)
    assert np.all(est.valid[after])
    assert np.max(np.sqrt(est.cov_nav[after, 3, 3])) < 1.0
    err = run_errors(est, sim.truth)
    assert np.max(np.linalg.norm(err.pos_ned_m[after], axis=1)) < 5.0


def test_reopen_attitude_adds_tilt_and_rate_variance_only():
    nf, _, _ = _filter()
    rng = np.random.default_rng(3)
    a = rng.normal(size=(nf.layout.n, nf.layout.n))
    nf.P = a @ a.T * 1e-4 + np.eye(nf.layout.n) * 1e-6
    before = nf.P.copy()
    nf.reopen_attitude(0.2, 0.03)
    added = nf.P - before
    expect = np.zeros_like(added)
    expect[6, 6] = expect[7, 7] = 0.2**2
    expect[RATE, RATE] = np.eye(3) * 0.03**2
    assert np.allclose(added, expect, rtol=0, atol=1e-15)
    assert nf.counters.attitude_reopens == 1
    assert nf.consecutive_velocity_rejects == 0


def test_transition_is_the_exponential_of_the_error_dynamics():
    """Phi over a block is exp(F t) to third order, F the documented error dynamics.

    F (filters/state.py): d pos = d vel; d vel = -[f_n]x d theta - C d b_f - C S_f G d r;
    d theta = C d w; d w = -d b_w - S_w G d r; the biases, DR and AOA states have none.
    Phi must be the third-order series of that F (dense powers here) and differ from
    scipy's matrix exponential by its fourth-order term (F t)^4 / 24 alone (the fifth
    power vanishes for this F).
    """
    from scipy.linalg import expm

    from filters.state import B_WDOT, POS

    nf, _, _ = _filter(0.0005, aoa_sigma_rad=0.01)
    rng = np.random.default_rng(3)
    c = dcm_from_quat(quat_normalize(rng.normal(size=4)))
    f_n = np.array([1.5, -2.0, -9.0])
    sg = nf.geometry_jacobian(rng.normal(size=3), rng.normal(size=3))
    k, dt = 20, 0.001
    phi, q = nf.propagation_matrices(k, dt, c, f_n, sg)
    n = nf.layout.n
    f = np.zeros((n, n))
    f[POS, VEL] = np.eye(3)
    f[VEL, ATT] = -skew(f_n)
    f[VEL, B_F] = -c
    f[VEL, nf.layout.dr] = -c @ sg[3:6]
    f[ATT, RATE] = c
    f[RATE, B_WDOT] = -np.eye(3)
    f[RATE, nf.layout.dr] = -sg[0:3]
    ft = f * (k * dt)
    ft2 = ft @ ft
    series = np.eye(n) + ft + ft2 / 2 + ft2 @ ft / 6
    np.testing.assert_allclose(phi, series, rtol=0, atol=1e-14)
    fourth = ft2 @ ft2 / 24
    assert np.abs(fourth).max() > 1e-6  # the check below can see a missing term
    np.testing.assert_allclose(expm(ft) - phi, fourth, rtol=0, atol=1e-13)
    np.testing.assert_allclose(q, q.T, rtol=0, atol=1e-12 * np.abs(q).max())


@pytest.mark.parametrize(
    ("speed_mps", "speed_sigma_mps"),
    [(32.0, 0.4), (32.4, 0.2), (36.0, 0.5), (40.0, 0.3), (50.0, 0.3)],
)
def test_blend_remainder_matches_sampled_speed_errors(speed_mps, speed_sigma_mps):
    """What the lift-off blend does beyond its linear term, against sampling.

    The blend is the minimum-jerk step over 32-40 m/s (lift-off speed 40 m/s). For a
    speed error drawn from the filter's velocity covariance (along the velocity), the
    variance of ``w(V + dV) - w(V) - w'(V) dV`` from 400 000 draws must match
    ``blend_remainder_var`` within 4 of its standard errors: at the blend's start
    (where ``w'`` is 0 and the linear sigma is nothing), inside it, at its end, and 0
    in flight (50 m/s, flat over +-6 sigma).
    """
    nf = _lift_law_filter()
    u = np.array([0.6, -0.8, 0.0])
    nf.vel = speed_mps * u
    p = nf.P.copy()
    p[VEL, VEL] = np.diag([speed_sigma_mps**2, speed_sigma_mps**2, 0.01])
    nf.P = p
    got = nf.blend_remainder_var()
    if speed_mps >= 40.0 + 6 * speed_sigma_mps:
        assert got == 0.0
        return
    d_v = np.random.default_rng(11).normal(0.0, speed_sigma_mps, 400_000)
    x0 = (speed_mps - 32.0) / 8.0
    s0, ds0, _ = min_jerk_step(x0)
    r = min_jerk_step(x0 + d_v / 8.0)[0] - s0 - ds0 * d_v / 8.0
    want = r.var()
    se = np.sqrt(((r - r.mean()) ** 2).var() / r.size)
    assert want > 0 and got > 0
    assert abs(got - want) < 4 * se + 1e-3 * want


def test_correlated_update_is_the_noise_augmented_states_update():
    """update_correlated (filterpy's KalmanFilter.update_correlated) equals, for random SPD
    inputs, two exact references built another way: filterpy's plain (Joseph) update on the
    state augmented with the noise (``[[P, M], [M^T, R]]``, ``H_a = [H, I]``, zero R), and
    the Gaussian conditional of ``dx`` on ``z`` from the joint covariance of ``[dx; v]``."""
    from filters.updates import update_correlated

    rng = np.random.default_rng(11)
    for _ in range(5):
        n, nz = 6, 3
        a = rng.normal(size=(n + nz, n + nz))
        joint = a @ a.T + 0.1 * np.eye(n + nz)  # covariance of [dx; v], M its corner
        p, m, r = joint[:n, :n], joint[:n, n:], joint[n:, n:]
        h = rng.normal(size=(nz, n))
        x, z = rng.normal(size=n), rng.normal(size=nz)
        x2, p2 = update_correlated(x, p, z, r, h, m)
        h_a = np.hstack([h, np.eye(nz)])
        xa, pa = kf_update(np.r_[x, np.zeros(nz)], joint, z, np.zeros((nz, nz)), h_a)
        np.testing.assert_allclose(x2, xa[:n], rtol=0, atol=1e-10)
        np.testing.assert_allclose(p2, pa[:n, :n], rtol=0, atol=1e-10)
        c_xz = joint[:n] @ h_a.T  # cov(dx, z) = P H^T + M
        s = h_a @ joint @ h_a.T
        np.testing.assert_allclose(x2, x + c_xz @ np.linalg.solve(s, z - h @ x), atol=1e-10)
        np.testing.assert_allclose(p2, p - c_xz @ np.linalg.solve(s, c_xz.T), atol=1e-10)
        # and it differs from the update that ignores M (the test can tell them apart)
        _, p0 = kf_update(x, p, z, r, h)
        assert np.abs(p0 - p2).max() > 1e-3


def test_the_reset_is_the_dense_jacobians_product():
    """``apply_reset_jacobian`` (the compiled row and column loops) equals ``G P G^T`` with
    ``G`` written out dense: the attitude rows ``ga`` and, body-style, the velocity rows
    ``[gvv, gvt]`` on the velocity and attitude columns; symmetric."""
    from filters.algebra import (
        apply_reset_jacobian,
        attitude_reset_jacobian,
        body_velocity_reset_jacobian,
    )

    rng = np.random.default_rng(5)
    n = 50
    for body in (False, True):
        a = rng.normal(size=(n, n))
        p = a @ a.T + np.eye(n)
        dth, dv, v = rng.normal(0, 0.05, 3), rng.normal(0, 0.5, 3), rng.normal(0, 30.0, 3)
        ga = attitude_reset_jacobian(dth)
        g = np.eye(n)
        g[ATT, ATT] = ga
        if body:
            gvv, gvt = body_velocity_reset_jacobian(dth, dv, v)
            g[VEL, VEL] = gvv
            g[VEL, ATT] = gvt
            got = apply_reset_jacobian(p, ga, gvv, gvt)
        else:
            got = apply_reset_jacobian(p, ga)
        want = g @ p @ g.T
        np.testing.assert_allclose(got, 0.5 * (want + want.T), rtol=1e-12, atol=1e-12)
        assert np.array_equal(got, got.T)


def test_the_angle_of_attacks_linear_variance_is_j_p_j():
    """``kernels.aoa_linear_var`` is ``j P j`` for ``kernels.aoa_jacobian``'s ``j``."""
    from filters import kernels

    rng = np.random.default_rng(6)
    n, aoa0, bias0, dr0 = 53, 51, 12, 24
    a = rng.normal(size=(n, n))
    p = a @ a.T
    args = (
        n, aoa0, 2, 0.8, 0.3, np.array([60.0, 3.0, -2.0]), 0.05, 0.04, 0.2,
        np.array([0.1, 0.0, -0.99]), rng.normal(size=(3, 12)), bias0, rng.normal(size=(3, 27)),
        dr0,
    )  # fmt: skip
    j = kernels.aoa_jacobian(*args)
    assert np.count_nonzero(j) > 10  # the law, velocity, bias and position columns
    assert kernels.aoa_linear_var(p, *args) == pytest.approx(j @ p @ j, rel=1e-12)


def test_rate_noise_cross_is_the_propagations_covariance_with_the_quad_noise():
    """Monte Carlo (fixed seed): the errors one propagated block leaves (true - estimate, with
    feature noise drawn from the solver's covariance) against the mean of the same samples'
    quadratic-term noise, the rate measurement's noise, give NavFilter.rate_noise_cross."""
    solver = ArraySolver(nine_accelerometer_cube(0.1), np.full(9, 1e-3))
    cov = solver.covariance()
    nf = NavFilter(
        FilterNoise(cov, cov, cov * 1e-6, quad_cross_cov=cov[0:6, 6:]),
        PAIRS,
        np.zeros(3),
    )
    k, dt = 20, 1e-3
    q0 = quat_from_euler(0.3, -0.2, 1.0)
    w0 = np.array([0.3, -0.2, 0.4])
    nf.initialise(0.0, np.zeros(3), np.array([20.0, 1.0, -1.0]), q0, w0, 1.0, 0.1, 0.01, 0.01)
    wd = np.tile([0.5, -0.3, 0.2], (k, 1))
    f = np.tile([1.0, 0.5, -9.8], (k, 1))
    start = (nf.pos.copy(), nf.vel.copy(), nf.q.copy(), nf.w.copy(), nf.t_s, nf.P.copy())

    def run(dwd: np.ndarray, df: np.ndarray) -> np.ndarray:
        nf.pos, nf.vel, nf.q, nf.w, nf.t_s, nf.P = (
            v.copy() if hasattr(v, "copy") else v for v in start
        )
        nf.set_last_sample(wd[0], f[0])
        nf.propagate(wd + dwd, f + df, dt)
        return np.concatenate([nf.pos, nf.vel, nf.q, nf.w])

    truth = run(np.zeros((k, 3)), np.zeros((k, 3)))
    rng = np.random.default_rng(5)
    chol = np.linalg.cholesky(cov)
    n_trials = 4000
    prod = np.empty((n_trials, 12, 3))
    for t in range(n_trials):
        noise = rng.standard_normal((k, 9)) @ chol.T
        est = run(noise[:, 0:3], noise[:, 3:6])
        d_att = quat_to_rotvec(quat_multiply(truth[6:10], quat_conjugate(est[6:10])))
        err = np.concatenate([truth[0:6] - est[0:6], d_att, truth[10:13] - est[10:13]])
        prod[t] = np.outer(err, noise[:, 6:].mean(axis=0))
    got = prod.mean(axis=0)
    se = prod.std(axis=0) / np.sqrt(n_trials)
    want = nf.rate_noise_cross(k, dt, dcm_from_quat(q0))[:12]
    assert np.all(np.abs(got - want) < 4.0 * se + 1e-15)
    # the check has power: the rate and velocity rows are many standard errors from zero
    assert np.abs(want[RATE]).max() > 10 * se[RATE].max()
    assert np.abs(want[VEL]).max() > 10 * se[VEL].max()
    # held samples carry no noise: with every sample held there is no cross-covariance
    assert nf.rate_noise_cross(k, dt, np.eye(3), np.ones(k, dtype=bool)) is None


def test_rate_jacobian_carries_the_forecast_compensations_return_of_the_rate_error():
    """A forecast compensation subtracts ``S E phi`` with ``phi``'s rate products taken
    from the filter's own rate, so a rate error returns in the compensated products.
    Against the real channel model (a 6 mm outward offset, the known error the
    compensation removes, and the nominal solve): with ``quad_feedback`` the Jacobian
    predicts the compensated products' change to second order in the rate error;
    the products' Jacobian alone misses it by ``E_qq``'s 7 %."""
    nominal = nine_accelerometer_cube(0.1)
    errors = MountingErrors(0.006 * outward_directions(nominal), np.zeros((9, 2)))
    real = errors.real_layout(nominal)
    solver = ArraySolver(nominal, np.full(9, 1e-3))
    se = solver.solve_matrix @ errors.error_matrix(nominal)
    cov = solver.covariance()
    noise = FilterNoise(cov, cov, cov * 1e-6)
    with_fb = NavFilter(noise, PAIRS, np.zeros(3), quad_feedback=se[6:, 6:12])
    plain = NavFilter(noise, PAIRS, np.zeros(3))
    wdot, f = np.array([3.0, -2.0, 1.0]), np.array([1.0, 0.5, -19.6])
    w_true = np.array([0.8, -1.5, 2.0])
    dw = np.array([2e-4, -1e-4, 1.5e-4])
    w_est = w_true - dw
    raw = solver.solve_matrix @ real.outputs(wdot, f, w_true)
    z = (raw - se @ kinematic_features(wdot, f, w_est))[6:]
    block = np.tile(w_est, (4, 1))
    pred, h = with_fb.rate_model(block)
    pred_plain, h_plain = plain.rate_model(block)
    np.testing.assert_array_equal(pred, pred_plain)
    y = z - pred
    lin = h[:, RATE] @ dw
    assert np.max(np.abs(y - lin)) < 1e-3 * np.max(np.abs(y))
    miss = np.max(np.abs(y - h_plain[:, RATE] @ dw)) / np.max(np.abs(y))
    assert 0.05 < miss < 0.1, miss
    with pytest.raises(ValueError, match="quad_feedback"):
        NavFilter(noise, PAIRS, np.zeros(3), quad_feedback=np.zeros((3, 3)))


def test_prior_weighted_count_limits():
    """``1 + (c - 1) R / (s + R)``: the whole count where the prior along the constraint
    is nothing (the update keeps all of it: w = 1), half-way where the prior equals R,
    and 1 plus ``(c - 1) R / s`` to first order where the prior is far larger; never
    below 1 nor above the count, falling as the prior grows; a count of 1 stays 1."""
    c, r = 7.0, 2.5e-9
    assert prior_weighted_count(c, r, 0.0) == c
    assert prior_weighted_count(c, r, r) == pytest.approx(1.0 + (c - 1.0) / 2.0, rel=1e-15)
    assert prior_weighted_count(c, r, 2500.0 * r) == pytest.approx(1.0 + 6.0 / 2501.0, rel=1e-12)
    s = np.logspace(-3, 6, 50) * r
    got = np.array([prior_weighted_count(c, r, x) for x in s])
    assert np.all(np.diff(got) < 0.0) and np.all((got > 1.0) & (got < c))
    assert prior_weighted_count(1.0, r, 3.0 * r) == 1.0
    assert prior_weighted_count(c, 0.0, 0.0) == c  # no information either way: the count


@pytest.mark.parametrize("axis", [LATERAL, VERTICAL])
@pytest.mark.parametrize("prior_scale", [1.0, 1e-7])
def test_count_by_prior_weight_update(axis, prior_scale):
    """``count_by_prior_weight``: outside the hand-over and coasts the sideslip update's R
    counts the remainder ``prior_weighted_count`` times, with the configured counts' R and
    the prior ``h P h^T`` along the constraint; the angle-of-attack update keeps the
    configured counts (the same R and posterior, to the bit).

    With a GPS-held prior along the constraint (thousands of times R) the posterior
    variance along it is the remainder counted once plus the sigma's (the count's R
    less the count), where the configured count leaves it several times that; with a
    prior far below R (``prior_scale`` 1e-7 along the constraint, the rest kept)
    the update is the configured one within 1 %. Either way the update is filterpy's
    with that R (Joseph form)."""
    sigma = np.deg2rad(3e-5)
    out = {}
    for on in (False, True):
        nf, _, _ = _filter()
        nf.count_by_prior_weight = on
        nf.attitude_remainder_updates = 7.0
        nf.body_velocity_log = []
        rng = np.random.default_rng(5)
        nf.q = quat_from_rotvec(np.array([0.2, 0.05, 1.0]))
        c = dcm_from_quat(nf.q)
        idx = np.r_[6:9, 3:6]
        a = rng.normal(size=(6, 6))
        scale = np.r_[[0.005] * 3, [0.05] * 3]
        p = np.eye(nf.layout.n) * 1e-12
        p[np.ix_(idx, idx)] = (a @ a.T) * np.outer(scale, scale) / 6.0
        nf.vel = 60.0 * c[:, 0]
        nf.t_last_position_fix = nf.t_s  # GPS-held: not a coast
        _, h = nf.body_velocity_model(nf.q, nf.vel, axis)
        # the prior along the constraint scaled, the rest (and so the remainder) about kept
        ph = p @ h[0]
        p = p - (1.0 - prior_scale) * np.outer(ph, ph) / float(h[0] @ ph)
        nf.P = p.copy()
        rem = nf.body_velocity_second_order(axis)
        if axis == LATERAL:
            nf.update_sideslip(sigma, 5.0)
        else:
            nf.update_angle_of_attack(sigma, 5.0)
        r_used = nf.body_velocity_log[0].r_m2ps2
        _, p_ref = kf_update(np.zeros(nf.layout.n), p.copy(), np.zeros(1), np.array([[r_used]]), h)
        # the nominal moved (a nonzero innovation), so compare where the reset leaves P
        # as it was: the velocity block and the constraint's direction through it
        out[on] = (float(h[0] @ p @ h[0]), r_used, rem, nf, p_ref, h[0])
    s_prior, r_off, rem, nf_off, _, h = out[False]
    _, r_on, _, nf_on, p_ref_on, _ = out[True]
    r_sigma = r_off - remainder_variance(rem, SIDESLIP_REMAINDER_UPDATES, 7.0)
    counted_once = r_sigma + rem.var
    assert r_off > 3.0 * counted_once  # the count dominates R
    np.testing.assert_allclose(nf_on.P[VEL, VEL], p_ref_on[VEL, VEL], rtol=1e-9, atol=0.0)
    if axis == VERTICAL:
        assert r_on == r_off
        np.testing.assert_array_equal(nf_on.P, nf_off.P)
        return
    want = remainder_variance(
        rem,
        prior_weighted_count(SIDESLIP_REMAINDER_UPDATES, r_off, s_prior),
        prior_weighted_count(7.0, r_off, s_prior),
    )
    assert r_on == pytest.approx(r_sigma + want, rel=1e-12)
    if prior_scale == 1.0:
        assert s_prior > 1000.0 * r_off
        assert r_on == pytest.approx(counted_once, rel=1e-2)
    else:
        assert s_prior < 0.01 * r_off
        assert r_on == pytest.approx(r_off, rel=1e-2)


#: A free vehicle on tactical's flight: the fixed-wing's airframe keys cleared with the kind.
FREE_VEHICLE = [
    "vehicle.kind=free",
    "vehicle.lift_k_m=0",
    "vehicle.lift_k_sigma_m=0",
    "vehicle.body_velocity_error=false",
]


def test_vehicle_kind_decides_the_models_and_a_fixed_wing_updates_at_5_hz():
    """``vehicle.kind``: a free vehicle gets no vehicle-model update and no angle-of-attack
    state; a fixed-wing gets the sideslip and angle-of-attack updates at 5 Hz, both axes
    at every update time, through the hand-over's hold and after it."""
    from filters.pipeline import run_filter
    from ngnav.settings import VehicleSettings
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    assert VehicleSettings().kind == "free"
    with pytest.raises(ValueError, match=r"vehicle\.lift_k_m describes a fixed-wing"):
        VehicleSettings(lift_k_m=2.0)
    short = [
        "run.rate_hz=200",
        "flight.legs=[{ duration_s = 12.0, ramp_s = 1.0, bank_deg = 30.0 }]",
    ]
    scn = load_flight("tactical", short)
    assert scn.vehicle.fixed_wing
    sim = simulate_flight(scn, 0)
    log: list = []
    res = run_filter(sim.samples, sim.fixes, sim.config, body_velocity_log=log)
    assert res.estimates.aoa_rad is not None
    t = np.array([rec.t_s for rec in log])
    axes = np.array([rec.axis for rec in log])
    np.testing.assert_array_equal(t[axes == LATERAL], t[axes == VERTICAL])
    gaps = np.diff(t[axes == LATERAL])
    assert gaps.size >= 50
    np.testing.assert_allclose(gaps, 0.2, atol=0.006)

    free = load_flight("tactical", short + FREE_VEHICLE)
    assert not free.vehicle.fixed_wing
    sim = simulate_flight(free, 0)
    log = []
    res = run_filter(sim.samples, sim.fixes, sim.config, body_velocity_log=log)
    assert log == [] and res.estimates.aoa_rad is None
    assert res.counts["sideslip updates"] == 0 and res.counts["angle-of-attack updates"] == 0


def _static_alignment_nees(
    use_sample_cov: bool, draws: int = 400, walk: bool = False, read_walk: bool = False
) -> float:
    """Mean NEES (9 dof) of the bias states after :meth:`NavFilter.update_static_biases`,
    over ``draws`` biases drawn from the prior and static means drawn with the raw
    solve's noise through the static effect ``M``, while the filter's ``feature_cov``
    is a loop-mapped ``T cov T^T`` (as :func:`filters.pipeline.filter_noise` builds it).

    With ``walk`` the biases walk over the mean's samples (spectral density chosen so
    that the walk's spread from its mean equals the white noise of the mean) and the
    states are the last sample's; ``read_walk`` passes the walk's weight."""
    layout = nine_accelerometer_cube(0.1)
    solver = ArraySolver(layout, np.full(9, 1e-3))
    raw = solver.covariance()
    k = raw.shape[0]
    rng = np.random.default_rng(11)
    # a compensation with a 20 % angular-acceleration gain makes the loop's map visible
    e6 = np.zeros((k, 6))
    e6[0:3, 0:3] = 0.2 * np.eye(3)
    e6[0:3, 3:6] = 0.05 * rng.normal(size=(3, 3))
    e6[3:6, 3:6] = 0.01 * np.eye(3)
    e6[6:, 0:6] = 0.02 * rng.normal(size=(k - 6, 6))
    t = np.eye(k)
    t[0:6, 0:6] = np.linalg.inv(np.eye(6) + e6[0:6])
    mapped = t @ raw @ t.T
    mapped[6:, 6:] = raw[6:, 6:]
    # the static mean's effect: the force bias taken out with the biased force
    m = np.eye(k)
    m[:, 3:6] -= e6[:, 3:6] @ np.linalg.inv(np.eye(3) + e6[3:6, 3:6])
    prior = raw * 4.0
    n = 500
    dt = 1e-3
    walk_s = static_mean_walk_s(dt, n)
    rw = raw / n / walk_s if walk else prior * 1e-9
    total = 0.0
    for _ in range(draws):
        nf = NavFilter(FilterNoise(mapped, prior, rw), PAIRS, np.zeros(3))
        initialise_level(nf)
        b = rng.multivariate_normal(np.zeros(k), prior)
        b_mean = b
        if walk:
            steps = rng.multivariate_normal(np.zeros(k), rw * dt, n - 1)
            path = b + np.vstack([np.zeros(k), np.cumsum(steps, axis=0)])
            b, b_mean = path[-1], path.mean(axis=0)
        mean = m @ (b_mean + rng.multivariate_normal(np.zeros(k), raw / n))
        nf.update_static_biases(
            mean, n, m, raw if use_sample_cov else None, walk_s if read_walk else 0.0
        )
        e = b - nf.bias
        pb = nf.P[nf.layout.bias, nf.layout.bias]
        total += float(e @ np.linalg.solve(pb, e))
    return total / draws


def test_static_alignment_reads_its_mean_with_the_raw_solves_noise():
    """The static mean has no forecast loop: with the raw solve's per-sample covariance
    through ``M`` the bias states' NEES is chi-square(9) over 400 draws (99.9 % bounds);
    read with the loop-mapped ``feature_cov`` (its angular acceleration 1.2^-2 of the raw
    variance here) they are over-sure and fail the upper bound."""
    draws = 400
    lo, hi = (float(chi2.ppf(q, 9 * draws) / draws) for q in (0.0005, 0.9995))
    assert lo <= _static_alignment_nees(True, draws) <= hi
    assert _static_alignment_nees(False, draws) > hi


def test_static_mean_walk_weight_is_the_walks_spread_from_its_mean():
    """``b_last - mean(b)`` of a discrete walk: ``sum_j (j / n) w_j``, exactly."""
    n, dt = 7, 0.01
    want = dt * sum((j / n) ** 2 for j in range(1, n))
    assert static_mean_walk_s(dt, n) == pytest.approx(want, rel=1e-12)
    assert static_mean_walk_s(dt, 1) == 0.0
    assert static_mean_walk_s(1e-3, 5001) == pytest.approx(5.0 / 3.0, rel=1e-3)
    with pytest.raises(ValueError, match="n_samples"):
        static_mean_walk_s(dt, 0)


def test_static_alignment_reads_the_biases_walk_over_its_mean():
    """The states are the biases at the mean's last sample: with the walk's spread as
    large as the mean's noise, reading it (``walk_s``) gives chi-square(9) over 400 draws
    (99.9 % bounds), leaving it out is over-sure and fails the upper bound."""
    draws = 400
    lo, hi = (float(chi2.ppf(q, 9 * draws) / draws) for q in (0.0005, 0.9995))
    assert lo <= _static_alignment_nees(True, draws, walk=True, read_walk=True) <= hi
    assert _static_alignment_nees(True, draws, walk=True) > hi


@settings(max_examples=200, deadline=None)
@given(
    k_now=st.integers(1, 40),
    k_prev=st.integers(1, 40),
    slope=st.floats(-50.0, 50.0),
    offset=st.floats(-30.0, 30.0),
    dt=st.floats(1e-4, 1e-2),
)
def test_the_loads_weights_take_two_block_means_to_the_block_end(k_now, k_prev, slope, offset, dt):
    """A load linear in time, sampled at ``dt`` over two consecutive blocks: the weighted
    block means equal its value at the last sample (the filter's time), for any block
    lengths; the weights sum to 1, and for equal blocks stay short of the long-block limit
    1.5 / -0.5."""
    t_e = 3.0
    t_now = t_e - dt * np.arange(k_now)  # the current block's samples, ending at t_e
    t_prev = t_e - dt * (k_now + np.arange(k_prev))  # the block before it
    load = lambda t: offset + slope * t  # noqa: E731
    w_now, w_prev = load_extrapolation_weights(k_now, k_prev)
    got = w_now * load(t_now).mean() + w_prev * load(t_prev).mean()
    assert got == pytest.approx(load(t_e), abs=1e-9 * (1.0 + abs(slope) + abs(offset)))
    assert w_now + w_prev == pytest.approx(1.0)
    assert -1.0 < w_prev <= 0.0
    if k_now == k_prev:  # equal blocks: short of the long-block limit's 0.5
        assert w_prev > -0.5


def test_the_loads_weights_reject_empty_blocks():
    with pytest.raises(ValueError, match="block sizes"):
        load_extrapolation_weights(0, 10)
