"""Every analytic Jacobian of NavFilter against central differences, and the gates' dof.

Each measurement model's H (GPS position and velocity with the antenna lever arm, the
rate products with the forecast's feedback, zero rate, static biases, sideslip and angle
of attack with and without the lift law, NED and body-frame velocity error) and the
block transition F are compared with central differences of the model's own prediction
(and of the nominal propagation), the nominal state perturbed through the filter's own
error injection (``NavFilter._inject``: ``q <- exp(dtheta) q``, NED small angles,
:mod:`filters.state`). A Jacobian that disagrees with the prediction it linearises
makes the filter fuse its measurements along wrong directions, which no end-to-end
error statistic pins down to a term. The reset's Jacobian (the covariance's side of the
injection) is compared the same way. The bias columns are taken with ``bias_effect``
the identity: a forecast compensation's ``T`` is an effect on the measured features
that the nominal prediction does not contain, so differences of it cannot pin ``T``.

Then the innovation gates: each update's NIS is built by hand from a known P, R and
innovation, set just below and just above ``chi2.ppf(gate_probability, dof)`` with the
model's own dof (3 for a GPS position or velocity and the zero rate, nq for the rate
products, 1 for each vehicle model and the heading check); a gate on any other dof
(2 in place of 3 once went unnoticed) accepts or rejects the wrong one.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np
import pytest
from filterpy.kalman import update as kf_update
from scipy.stats import chi2

from filters.ekf import FilterNoise, NavFilter
from filters.state import ATT, B_F, B_WDOT, POS, RATE, VEL, b_quad
from filters.vehicle_model import LATERAL, LIFT_JACOBIAN_LAG_BLOCKS, VERTICAL
from ngnav.compensation import QUAD_PAIRS
from ngnav.frontend import ArraySolver
from ngnav.layout import nine_accelerometer_cube
from ngnav.rotation import (
    dcm_from_quat,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
    quat_to_rotvec,
)
from tests.helpers import PAIRS

#: The nominal state the models are linearised at: 47 m/s climbing a little, banked,
#: pitched and turned, turning at 0.58 rad/s about a skew axis.
POS0 = np.array([120.0, -45.0, -80.0])
VEL0 = np.array([38.0, -27.0, -3.0])
Q0 = quat_from_euler(0.35, -0.12, 2.2)
W0 = np.array([0.30, -0.20, 0.45])
ANTENNA = np.array([0.3, -0.1, -0.15])
#: Binary64 unit roundoff.
EPS_MACH = np.finfo(float).eps

_SOLVER = ArraySolver(nine_accelerometer_cube(0.1), np.full(9, 1e-3))
_COV = _SOLVER.covariance()


def _filter(
    *,
    position_sigma_m: float = 0.0,
    aoa_sigma_rad: float = 0.0,
    lift_k_m: float = 0.0,
    lift_k_sigma_m: float = 0.0,
    liftoff_mps: float = 0.0,
    quad_feedback: np.ndarray | None = None,
    feature_quad_feedback: np.ndarray | None = None,
    body_velocity_error: bool = False,
    antenna: np.ndarray = ANTENNA,
) -> NavFilter:
    """A nine-cube filter at the nominal state, with nonzero bias and position estimates."""
    nf = NavFilter(
        FilterNoise(_COV, _COV, _COV * 1e-6, position_sigma_m),
        PAIRS,
        antenna,
        sensor_axes_b=nine_accelerometer_cube(0.1).axes_b,
        solve_matrix=_SOLVER.solve_matrix,
        aoa_prior_sigma_rad=aoa_sigma_rad,
        aoa_lift_k_m=lift_k_m,
        aoa_lift_k_sigma_m=lift_k_sigma_m,
        liftoff_speed_mps=liftoff_mps,
        quad_feedback=quad_feedback,
        feature_quad_feedback=feature_quad_feedback,
        body_velocity_error=body_velocity_error,
    )
    # attitude known to 0.01 rad: |v| tr(P_att) / 2 = 7e-3 m/s keeps the body-frame
    # velocity error in use (NavFilter.in_body_frame) where it is asked for
    nf.initialise(0.0, POS0, VEL0, Q0, W0, 1.0, 0.1, 0.01, 0.01, aoa_rad=-0.02)
    rng = np.random.default_rng(2024)
    nf.bias = rng.normal(0.0, 0.02, nf.bias.shape)
    nf.dr = rng.normal(0.0, 5e-4, nf.dr.shape)
    return nf


def _injected(nf: NavFilter, dx: np.ndarray) -> NavFilter:
    """A copy of ``nf`` whose nominal state has taken the error ``dx`` (its own reset).

    The covariance is put back: the models are functions of the nominal state at a
    fixed P (the second-order means they add read P, not the state).
    """
    out = copy.deepcopy(nf)
    out.x = np.array(dx, dtype=float)
    out._inject()
    out.P = nf.P.copy()
    return out


def _error(true: NavFilter, est: NavFilter) -> np.ndarray:
    """The error state (true - estimate) between two nominal states, filters/state.py's
    convention: NED position and velocity differences, the NED rotation vector of
    ``q_true * conj(q_est)``, and differences of rate, biases, positions, AOA states.
    (With the body-frame velocity error ``xi_v`` differs from the NED difference at
    second order only, which central differences cancel.)"""
    lay = est.layout
    e = np.zeros(lay.n)
    e[POS] = true.pos - est.pos
    e[VEL] = true.vel - est.vel
    e[ATT] = quat_to_rotvec(quat_multiply(true.q, quat_conjugate(est.q)))
    e[RATE] = true.w - est.w
    e[lay.bias] = true.bias - est.bias
    e[lay.dr] = true.dr - est.dr
    e[lay.aoa] = np.array([true.aoa_b - est.aoa_b, true.aoa_k - est.aoa_k])[: lay.n_aoa]
    return e


def _steps(nf: NavFilter) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference step ``h`` per error state (its own unit) and a bound ``M3`` on
    the third derivative of any model here along that state (per unit cubed).

    A step leaves a truncation error ``h^2 M3 / 6`` and a rounding error of about
    ``eps |y| / h`` (``|y|`` <= 150: metres and m/s). Every model is linear in position;
    rate products are quadratic (central differences are exact on them); the biases,
    sensor positions and ``K`` enter linearly or through the small angle of attack
    (``M3`` 1 is generous); the attitude and the angle-of-attack offset turn vectors of
    at most 50 m/s (``M3`` 50); the velocity enters the lift law through ``1 / V^2``
    (``24 K n_w / V^5``: 3e-5 here) and the lift-off blend (``60 / width^3`` times the
    law's 0.03 rad times 50 m/s: 0.07), ``M3`` 0.1. With these steps both errors stay
    below about 1e-8 per unit of H.
    """
    lay = nf.layout
    h, m3 = np.empty(lay.n), np.ones(lay.n)
    h[POS], m3[POS] = 1e-3, 0.0
    h[VEL], m3[VEL] = 1e-4, 0.1
    h[ATT], m3[ATT] = 1e-5, 50.0
    h[RATE] = 1e-5
    h[lay.bias] = 1e-5
    h[lay.dr] = 1e-6
    h[lay.aoa] = [1e-5, 1e-3][: lay.n_aoa]
    m3[lay.aoa] = [50.0, 1.0][: lay.n_aoa]
    return h, m3


def _fd_jacobian(
    nf: NavFilter, predict: Callable[[NavFilter], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of ``predict`` through the injection, and their error bound.

    Returns ``(J, tol)``, both (m, n): ``tol`` is ten times the sum of the truncation
    bound ``h^2 M3 / 6`` and the rounding bound ``4 eps max|y| / h`` (:func:`_steps`),
    so a correct Jacobian passes by an order of magnitude, while a dropped or flipped
    term fails unless it is below about 1e-7 of its unit.
    """
    h, m3 = _steps(nf)
    y0 = np.atleast_1d(predict(copy.deepcopy(nf)))
    cols, tols = [], []
    for j, hj in enumerate(h):
        d = np.zeros(nf.layout.n)
        d[j] = hj
        yp = np.atleast_1d(predict(_injected(nf, d)))
        ym = np.atleast_1d(predict(_injected(nf, -d)))
        cols.append((yp - ym) / (2.0 * hj))
        scale = np.maximum(np.abs(y0), np.maximum(np.abs(yp), np.abs(ym)))
        tols.append(10.0 * (hj * hj * m3[j] / 6.0 + 4.0 * EPS_MACH * scale / hj))
    return np.column_stack(cols), np.column_stack(tols)


def _check(h: np.ndarray, fd: np.ndarray, tol: np.ndarray, label: str) -> float:
    """Assert ``|H - FD| <= tol`` entrywise; return the max error relative to max |H|."""
    h = np.atleast_2d(h)
    err = np.abs(h - fd)
    bad = np.argwhere(err > tol)
    assert bad.size == 0, (
        f"{label}: H and central differences disagree at (row, state) "
        f"{[tuple(b) for b in bad[:8]]}: H {h[tuple(bad[0])]:.6g}, FD {fd[tuple(bad[0])]:.6g}"
    )
    rel = float(err.max() / np.abs(h).max())
    print(f"{label}: max |H - FD| / max |H| = {rel:.2e}")
    return rel


# --------------------------------------------------------------------------- GPS
@pytest.mark.parametrize("body_velocity_error", [False, True])
def test_gps_position_and_velocity_jacobians(body_velocity_error):
    """GPS antenna position ``p + C r`` and velocity ``v + C (w x r)`` (the lever arm
    0.35 m off the array): H_pos (position, attitude) and H_vel (velocity, attitude,
    rate) against central differences, in both velocity-error conventions."""
    nf = _filter(body_velocity_error=body_velocity_error)
    assert nf.in_body_frame() is body_velocity_error

    def pos_pred(f: NavFilter) -> np.ndarray:
        return f.pos + f.gps_model(f.q, f.w)[0]

    def vel_pred(f: NavFilter) -> np.ndarray:
        return f.vel + f.gps_model(f.q, f.w)[1]

    _, _, hp, hv = nf.gps_model(nf.q, nf.w)
    fd, tol = _fd_jacobian(nf, pos_pred)
    _check(hp, fd, tol, "GPS position")
    fd, tol = _fd_jacobian(nf, vel_pred)
    _check(hv, fd, tol, "GPS velocity")
    # the lever-arm columns are exercised: metres per radian, m/s per rad/s
    assert np.abs(hp[:, ATT]).max() > 0.1 and np.abs(hv[:, RATE]).max() > 0.1
    assert np.abs(hv[:, ATT]).max() > 0.05


# --------------------------------------------------------------------------- rate products
def _block_rates(nf: NavFilter, k: int = 8) -> np.ndarray:
    """A block of ``k`` rates (K, 3) ending at the nominal rate, turning through it."""
    s = np.linspace(-1.0, 0.0, k)[:, None]
    return nf.w + s * np.array([0.04, -0.03, 0.05])


def _rate_prediction(nf: NavFilter, w_block: np.ndarray, sg: np.ndarray | None) -> np.ndarray:
    """The rate update's own prediction of the block-mean quadratic terms: the innovation
    it stores for a zero measurement, negated (on a throw-away copy)."""
    f = copy.deepcopy(nf)
    f._block = None
    f.update_rate(np.zeros(f.layout.nq), w_block, w_block.shape[0], sg)
    return -f.last_rate_innovation


@pytest.mark.parametrize("with_positions", [False, True])
def test_rate_product_jacobian(with_positions):
    """Rate products' H (rate, quadratic biases and, with DR states, the sensor
    positions through ``S G``) against central differences of the update's prediction,
    the rate error shifting every sample of the block alike. The positions' effect is
    made at the true motion, ``S G(w) dr``: with the estimated ``dr`` nonzero a rate error
    moves it too (:meth:`NavFilter.geometry_rate_jacobian`, at the block's mean rate)."""
    nf = _filter(position_sigma_m=5e-4 if with_positions else 0.0)
    assert (nf.layout.n_dr > 0) is with_positions
    w_block = _block_rates(nf)
    wdot = np.array([1.5, -2.0, 0.7])
    sg = nf.geometry_jacobian(wdot, w_block.mean(axis=0)) if with_positions else None

    def pred(f: NavFilter) -> np.ndarray:
        w_true = w_block + (f.w - nf.w)
        sg_true = f.geometry_jacobian(wdot, w_true.mean(axis=0)) if with_positions else None
        return _rate_prediction(f, w_true, sg_true)

    _, h = nf.rate_model(w_block, sg)
    fd, tol = _fd_jacobian(nf, pred)
    _check(h, fd, tol, f"rate products{' with DR' if with_positions else ''}")
    if with_positions:
        assert np.abs(h[:, nf.layout.dr]).max() > 1e-3
        # the positions' share of the rate columns is far above the tolerance
        assert np.abs(nf.geometry_rate_jacobian(nf.w)[6:]).max() > 1e3 * tol.max()


def test_rate_product_jacobian_with_the_forecasts_feedback():
    """With ``quad_feedback`` the compensated terms also carry the forecast's return of
    the rate error, ``E_q (phi6(w_true) - phi6(w_hat))`` (phi6 the six rate products
    of ``ngnav.compensation.QUAD_PAIRS``, made from the filter's rate): the measurement
    is the update's prediction at the true state plus that return, and H must be its
    derivative in the true state, the feedback term included."""
    rng = np.random.default_rng(5)
    fb = rng.normal(0.0, 0.08, (3, 6))  # E_q: a few per cent, as S E for mm offsets
    nf = _filter(quad_feedback=fb)
    w_block = _block_rates(nf)
    pairs = np.array(QUAD_PAIRS)

    def phi6(w: np.ndarray) -> np.ndarray:
        return (w[:, pairs[:, 0]] * w[:, pairs[:, 1]]).mean(axis=0)

    def measured(f: NavFilter) -> np.ndarray:
        w_true = w_block + (f.w - nf.w)
        return _rate_prediction(f, w_true, None) + fb @ (phi6(w_true) - phi6(w_block))

    _, h = nf.rate_model(w_block)
    fd, tol = _fd_jacobian(nf, measured)
    _check(h, fd, tol, "rate products with quad_feedback")
    plain = _filter()
    _, h_plain = plain.rate_model(w_block)
    # the feedback's share of the rate columns is far above the tolerance
    assert np.abs(h - h_plain)[:, RATE].max() > 1e3 * tol.max()


# --------------------------------------------------------------------------- rest
def _assert_update_is_filterpys(
    before: NavFilter, after: NavFilter, y: np.ndarray, r: np.ndarray, h: np.ndarray
) -> None:
    """``after`` is ``before`` updated by filterpy's Kalman update with this innovation,
    noise and (finite-difference) Jacobian, then injected and reset."""
    x_ref, p_ref = kf_update(np.zeros(before.layout.n), before.P.copy(), y, r, h)
    ref = copy.deepcopy(before)
    ref.x, ref.P = x_ref, p_ref
    ref._inject()
    assert np.abs(x_ref).max() > 0  # the update moved the state
    for name in ("pos", "vel", "q", "w", "bias", "dr"):
        np.testing.assert_allclose(getattr(after, name), getattr(ref, name), rtol=0, atol=1e-13)
    scale = np.abs(before.P).max()
    np.testing.assert_allclose(after.P, ref.P, rtol=0, atol=1e-12 * scale)


def test_zero_rate_jacobian_and_update():
    """Zero rate at rest: the prediction is the body rate, so H reads the rate states
    alone; the update is filterpy's with that H, ``y = 0 - w`` and ``R = sigma^2 I``."""
    nf = _filter()
    fd, tol = _fd_jacobian(nf, lambda f: f.w.copy())
    _check(nf.rate_at_rest_model(), fd, tol, "zero rate")
    nf.w = np.array([2e-4, -1e-4, 3e-4])  # a rate inside the gate
    before = copy.deepcopy(nf)
    sigma = 1e-3
    _, ok = nf.update_zero_rate(sigma)
    assert ok
    _assert_update_is_filterpys(before, nf, -before.w, sigma**2 * np.eye(3), fd)


@pytest.mark.parametrize("walk_s", [0.0, 1.7])
def test_static_bias_jacobian_and_update(walk_s):
    """Static alignment: the mean solved angular acceleration and rate products measure
    ``M b`` (``M`` what the bias states leave in them; rows wdot and quad). The update
    must be filterpy's with the central differences of that prediction for H,
    ``y = z - M b`` and ``R = M cov M^T / n + M Q_walk M^T walk_s``."""
    nf = _filter()
    nq = nf.layout.nq
    k = 6 + nq
    idx = np.r_[0:3, 6 : 6 + nq]
    rng = np.random.default_rng(9)
    m = np.eye(k) + rng.normal(0.0, 0.05, (k, k))
    fd, _ = _fd_jacobian(nf, lambda f: (m @ f.bias)[idx])
    assert np.count_nonzero(np.abs(fd) > 1e-9) == idx.size * k  # the bias columns only
    z = m @ nf.bias + rng.normal(0.0, 1e-3, k)
    n = 500
    sample_cov = _COV * 1.3
    r = m[idx] @ sample_cov @ m[idx].T / n + m[idx] @ nf.noise.bias_rw_cov @ m[idx].T * walk_s
    before = copy.deepcopy(nf)
    nf.update_static_biases(z, n, m, sample_cov, walk_s)
    _assert_update_is_filterpys(before, nf, z[idx] - (m @ before.bias)[idx], r, fd)


# --------------------------------------------------------------------------- vehicle models
#: The lift law's load: the block's specific force, FRD, biases removed (a 1.8 g pull).
F_LOAD = np.array([1.5, 0.3, -17.0])

#: Angle-of-attack configurations: (aoa state sigma, K, K sigma, lift-off speed).
AOA_CASES = {
    "offset": (0.02, 0.0, 0.0, 0.0),  # the state is the angle of attack itself
    "law": (0.02, 18.0, 0.9, 0.0),  # lift law, K carried as a second state
    "law_fixed_k": (0.02, 18.0, 0.0, 0.0),  # lift law, K known
    "law_in_blend": (0.02, 18.0, 0.9, 55.0),  # 47 m/s inside the 44-55 m/s blend
}


def _aoa_filter(case: str, body_velocity_error: bool) -> tuple[NavFilter, np.ndarray]:
    """A filter with the AOA state of ``case`` on a steady load; and the raw force whose
    bias-removed value the load is (``f - b_f``, as the pipeline feeds ``set_load``)."""
    sigma, k, k_sigma, liftoff = AOA_CASES[case]
    nf = _filter(
        aoa_sigma_rad=sigma,
        lift_k_m=k,
        lift_k_sigma_m=k_sigma,
        liftoff_mps=liftoff,
        body_velocity_error=body_velocity_error,
    )
    f_raw = F_LOAD + nf.bias[3:6]
    for _ in range(4 * (LIFT_JACOBIAN_LAG_BLOCKS + 2)):
        nf.set_load(f_raw - nf.bias[3:6])  # steady: the lagged load is the current one
    return nf, f_raw


def _vertical_prediction(nf0: NavFilter, f_raw: np.ndarray) -> Callable[[NavFilter], float]:
    """The angle-of-attack model's prediction as a function of the injected state: the
    load re-read with the state's force bias and speed (the angle inside ``n_w``, the
    last block's, held at the nominal's, as ``set_load`` documents), then the velocity
    along the wind-normal axis at the state's own angle of attack."""

    def pred(f: NavFilter) -> float:
        if f.layout.n_aoa and f.aoa_lift_k_m > 0:
            ab, ak = f.aoa_b, f.aoa_k
            f.aoa_b, f.aoa_k, f._lift_u, f._lift_w = nf0.aoa_b, nf0.aoa_k, nf0._lift_u, nf0._lift_w
            f.set_load(f_raw - f.bias[3:6])
            f.aoa_b, f.aoa_k = ab, ak
        return f.body_velocity_model(f.q, f.vel, VERTICAL, f.aoa)[0]

    return pred


@pytest.mark.parametrize("body_velocity_error", [False, True])
def test_sideslip_jacobian(body_velocity_error):
    """Sideslip: the body-lateral velocity ``e_y . C^T v``; H (velocity, attitude, and
    nothing on the AOA states) against central differences, with the NED velocity error
    (second order in the state) and the body-frame one (exactly linear)."""
    for case in ("none", "law"):
        if case == "none":
            nf = _filter(body_velocity_error=body_velocity_error)
        else:
            nf, _ = _aoa_filter(case, body_velocity_error)
        assert nf.in_body_frame() is body_velocity_error
        _, h = nf.sideslip_model(nf.q, nf.vel)
        fd, tol = _fd_jacobian(nf, lambda f: f.sideslip_model(f.q, f.vel)[0])
        _check(h, fd, tol, f"sideslip ({case}, body={body_velocity_error})")
        assert np.abs(h[0, ATT]).max() > 10.0  # m/s per rad: exercised


@pytest.mark.parametrize("body_velocity_error", [False, True])
def test_vertical_model_jacobian_without_aoa_state(body_velocity_error):
    """Without the AOA state the vertical model is the body-z velocity ``e_z . C^T v``."""
    nf = _filter(body_velocity_error=body_velocity_error)
    assert nf.layout.n_aoa == 0 and nf.in_body_frame() is body_velocity_error
    _, h = nf.body_velocity_model(nf.q, nf.vel, VERTICAL, nf.aoa)
    fd, tol = _fd_jacobian(nf, lambda f: f.body_velocity_model(f.q, f.vel, VERTICAL, 0.0)[0])
    _check(h, fd, tol, f"vertical, no AOA state (body={body_velocity_error})")


@pytest.mark.parametrize("body_velocity_error", [False, True])
@pytest.mark.parametrize("case", list(AOA_CASES))
def test_angle_of_attack_jacobian(case, body_velocity_error):
    """Angle of attack: the velocity along ``[-sin a, 0, cos a]`` with ``a`` the state, or
    with the lift law ``w(V) (alpha_b + K n_w / V^2)``: H's velocity, attitude, force-bias,
    offset and ``K`` columns (``body_velocity_model`` with ``aoa_jacobian``) against
    central differences of the whole chain through the injection."""
    nf, f_raw = _aoa_filter(case, body_velocity_error)
    assert nf.in_body_frame() is body_velocity_error
    assert (nf._lift_dw > 0) is (case == "law_in_blend")
    _, h = nf.body_velocity_model(nf.q, nf.vel, VERTICAL, nf.aoa)
    fd, tol = _fd_jacobian(nf, _vertical_prediction(nf, f_raw))
    _check(h, fd, tol, f"angle of attack ({case}, body={body_velocity_error})")
    ia = nf.layout.aoa
    assert np.abs(h[0, ia][0]) > 1.0  # m/s per rad of the offset: exercised
    if nf.aoa_lift_k_m > 0:  # the law's terms are exercised
        assert np.abs(h[0, B_F]).max() > 1e-3  # the force bias through the load
        assert np.abs(nf.aoa_jacobian(nf.vel)[VEL]).max() > 1e-5  # the speed through 1 / V^2


# --------------------------------------------------------------------------- process model
K_BLOCK, DT = 10, 1e-3


def _block_samples() -> tuple[np.ndarray, np.ndarray]:
    """One block's angular accelerations and specific forces (K, 3), FRD: a 1.1 g pull
    with a roll acceleration, both changing a little over the block."""
    s = np.arange(1, K_BLOCK + 1)[:, None] / K_BLOCK
    wdot = np.array([0.5, -0.3, 0.8]) + s * np.array([0.2, 0.1, -0.1])
    f = np.array([1.0, 0.4, -10.5]) + s * np.array([0.2, -0.2, 0.1])
    return wdot, f


def _propagated(nf: NavFilter, sg: np.ndarray | None) -> NavFilter:
    out = copy.deepcopy(nf)
    wdot, f = _block_samples()
    out.propagate(wdot, f, DT, sg)
    return out


def _phi_applied(nf: NavFilter, sg: np.ndarray | None) -> np.ndarray:
    """The transition ``propagate`` applies to the covariance: ``P' = Phi P Phi^T + Q``,
    so from a prior ``a e_j e_j^T`` (tiny ``a``: the nominal's second-order terms, which
    read P, stay put) ``(P'(a) - P'(0)) / a`` is ``Phi[:, j] Phi[:, j]^T``, whose column j
    is ``Phi[:, j]`` (``Phi[j, j] = 1``: F has no diagonal)."""
    n = nf.layout.n
    a = 1e-12
    zero = copy.deepcopy(nf)
    zero.P = np.zeros((n, n))
    p0 = _propagated(zero, sg).P
    phi = np.empty((n, n))
    for j in range(n):
        one = copy.deepcopy(zero)
        one.P[j, j] = a
        phi[:, j] = (_propagated(one, sg).P[:, j] - p0[:, j]) / a
    return phi


@pytest.mark.parametrize("body_velocity_error", [False, True])
def test_transition_matches_finite_differences_of_the_propagation(body_velocity_error):
    """F over one block (10 samples of 1 ms) against central differences of the nominal
    propagation ``propagate`` of an injected error, with sensor-position and AOA states.

    Both the transition ``propagate`` applies to P and ``propagation_matrices`` at the
    documented block-start ``C`` and mean NED force are compared, block by block of
    the state layout. F is the error dynamics linearised at the block start and
    integrated to third order, so unlike an H it differs from the exact derivative of
    the block's nonlinear propagation by the block's own motion, to first order: the
    body turns by ``|w| t`` (5.8e-3 rad) and the force changes by ``|df| / |f|``
    (2.6e-2) over the block, and the trapezoids' error in the position goes as
    ``1 / K^2`` (1e-2). Each block may differ by the sum of those (4.2e-2; measured:
    at most 7.9e-3) times its largest entry, plus ten times the differences' rounding
    (``4 eps |y| / h``). A flipped sign or a dropped term is a difference of 1 in some
    block: each order of the series has blocks only it fills (position-attitude the
    second, position-rate and velocity-``b_wdot`` the third).
    """
    nf = _filter(position_sigma_m=5e-4, aoa_sigma_rad=0.02, body_velocity_error=body_velocity_error)
    assert nf.in_body_frame() is body_velocity_error
    lay = nf.layout
    wdot, f = _block_samples()
    nf.set_last_sample(
        wdot[0] - np.array([0.02, 0.01, -0.01]), f[0] - np.array([0.02, -0.02, 0.01])
    )
    sg = nf.geometry_jacobian(wdot.mean(axis=0), nf.w)
    end = _propagated(nf, sg)
    h, _ = _steps(nf)
    fd = np.empty((lay.n, lay.n))
    for j in range(lay.n):
        d = np.zeros(lay.n)
        d[j] = h[j]
        up = _error(_propagated(_injected(nf, d), sg), end)
        dn = _error(_propagated(_injected(nf, -d), sg), end)
        fd[:, j] = (up - dn) / (2.0 * h[j])
    # documented F: C at the block start, the block's mean specific force in NED
    c0 = dcm_from_quat(nf.q)
    rot = np.array([quat_to_rotvec(quat_multiply(quat_conjugate(nf.q), end.q))])  # body turn
    f_n = c0 @ (f - nf.bias[3:6] - sg[3:6] @ nf.dr).mean(axis=0)
    phi_doc, _ = nf.propagation_matrices(K_BLOCK, DT, c0, f_n, sg)
    phi_used = _phi_applied(nf, sg)
    turn = float(np.linalg.norm(rot))
    change = float(np.linalg.norm(f[-1] - f[0]) / np.linalg.norm(f.mean(axis=0)))
    rtol = turn + change + 1.0 / K_BLOCK**2
    assert 0.0 < turn < 0.01 and rtol < 0.05
    blocks = [POS, VEL, ATT, RATE, B_WDOT, B_F, b_quad(lay.nq), lay.dr, lay.aoa]
    worst = 0.0
    for phi, label in ((phi_used, "applied"), (phi_doc, "propagation_matrices")):
        for rows in blocks[:4]:
            for cols in blocks:
                ref = phi[rows, cols]
                err = np.abs(fd[rows, cols] - ref).max()
                fd_round = 4.0 * EPS_MACH * 200.0 / h[cols].min()
                bound = rtol * np.abs(ref).max() + 10.0 * fd_round
                assert err <= bound, (label, rows, cols, err, bound, np.abs(ref).max())
                if np.abs(ref).max() > 0:
                    worst = max(worst, err / np.abs(ref).max())
    print(f"transition (body={body_velocity_error}): worst block error / block max {worst:.2e}")
    # rows below the navigation states: identity (walks and constants)
    np.testing.assert_allclose(fd[12:, :], np.eye(lay.n)[12:, :], rtol=0, atol=1e-9)
    np.testing.assert_allclose(phi_used[12:, :], np.eye(lay.n)[12:, :], rtol=0, atol=1e-9)


@pytest.mark.parametrize("term", ["positions", "forecast"])
def test_transition_carries_what_the_features_make_from_the_rate(term):
    """A rate error reaches the block's angular acceleration and force through what is
    made from the estimated rate: the positions' effect the nominal removes,
    ``S G(w_hat) dr_hat``, and the forecast's products ``A S E_q q6(w_hat)`` the
    compensation removes. Central differences of a block whose features are made at an
    estimate off in its rate, against F's rate columns at a spin of 6 rad/s (measured:
    1e-4 and 5 % of the term apart; the block turns 0.06 rad, which F's block-start
    linearisation leaves out)."""
    fb = np.random.default_rng(7).normal(0.0, 0.08, (6, 6)) if term == "forecast" else None
    nf = _filter(position_sigma_m=5e-4 if term == "positions" else 0.0, feature_quad_feedback=fb)
    nf.w = np.array([6.0, 0.3, -0.2])
    wdot, f = _block_samples()
    nf.set_last_sample(wdot[0], f[0])
    pairs = np.array(QUAD_PAIRS)

    def sg_at(w: np.ndarray) -> np.ndarray | None:
        return nf.geometry_jacobian(wdot.mean(axis=0), w) if nf.layout.n_dr else None

    def propagated(est: NavFilter) -> NavFilter:
        out = copy.deepcopy(est)
        made = np.zeros(6)
        if fb is not None:  # the compensation's products from the estimate's rate
            q6 = lambda w: w[pairs[:, 0]] * w[pairs[:, 1]]  # noqa: E731
            made = fb @ (q6(nf.w) - q6(est.w))
        out.propagate(wdot + made[0:3], f + made[3:6], DT, sg_at(est.w))
        return out

    end = propagated(nf)
    h = 1e-5
    fd = np.empty((12, 3))
    for j in range(3):
        d = np.zeros(nf.layout.n)
        d[RATE.start + j] = h
        # the estimate off by -d: the error (true - estimate) is +d
        fd[:, j] = (
            _error(end, propagated(_injected(nf, -d))) - _error(end, propagated(_injected(nf, d)))
        )[:12] / (2 * h)
    c0 = dcm_from_quat(nf.q)
    f_n = c0 @ (f - nf.bias[3:6]).mean(axis=0)
    phi, _ = nf.propagation_matrices(K_BLOCK, DT, c0, f_n, sg_at(nf.w))
    plain = copy.deepcopy(nf)
    plain._quad_into_features = None
    if nf.layout.n_dr:
        plain.dr = np.zeros_like(nf.dr)
    phi_plain, _ = plain.propagation_matrices(K_BLOCK, DT, c0, f_n, sg_at(nf.w))
    term = np.abs(phi - phi_plain)[RATE, RATE].max()
    assert term > 1e-4  # 0.06 rad of turn: the rate columns agree to 10 % of the term
    assert np.abs(fd[RATE] - phi[RATE, RATE]).max() < 0.1 * term
    assert np.abs(fd[RATE] - phi_plain[RATE, RATE]).max() > 0.9 * term


def _error_body(true: NavFilter, est: NavFilter) -> np.ndarray:
    """:func:`_error` with the body-frame velocity error's ``VEL``: the truth is
    ``exp(dtheta) C (C^T v + dv_b)`` and the state holds ``xi_v = C dv_b + dtheta x v``."""
    e = _error(true, est)
    c_t, c_e = dcm_from_quat(true.q), dcm_from_quat(est.q)
    dv_b = c_t.T @ true.vel - c_e.T @ est.vel
    e[VEL] = c_e @ dv_b + np.cross(e[ATT], est.vel)
    return e


@pytest.mark.parametrize("body_velocity_error", [False, True])
def test_injection_reset_jacobian_matches_finite_differences(body_velocity_error):
    """The reset's Jacobian ``G`` (``P <- G P G^T`` in ``_inject``) against central
    differences of the error it leaves: a truth ``inject(old, e)`` seen from the new
    nominal ``inject(old, dx)``, as a function of ``e`` at 0. ``G`` is the first-order
    reset (``I + [dtheta]x / 2`` on the attitude, with the body-frame error
    ``body_velocity_reset_jacobian``'s velocity rows), so it differs from the exact
    derivative at second order in the correction: each block by about ``|dtheta|``
    (0.01 rad) of its part beyond the identity (measured: 2e-3 with the NED velocity
    error, 9.9e-3 with the body-frame one), bounded here at three times that; a flipped
    sign or a dropped term (all first order) is a difference of 1 to 2. The heading
    column of the attitude rows is held at ``e_z`` by design (observability-constrained,
    ``NavFilter._inject``) and left out here."""
    nf = _filter(body_velocity_error=body_velocity_error)
    n = nf.layout.n
    dx = np.zeros(n)
    dx[POS], dx[VEL] = [0.5, -0.3, 0.2], [0.06, -0.04, 0.03]
    dx[ATT], dx[RATE] = [0.006, -0.007, 0.004], [1e-3, -2e-3, 5e-4]
    new = _injected(nf, dx)
    error = _error_body if body_velocity_error else _error
    # G as _inject applies it: from a prior eps e_j e_j^T, column j of P' / eps (G_jj = 1)
    g = np.empty((n, n))
    for j in range(n):
        one = copy.deepcopy(nf)
        one.P = np.zeros((n, n))
        one.P[j, j] = 1e-12
        assert one.in_body_frame() is body_velocity_error
        one.x = dx.copy()
        one._inject()
        g[:, j] = one.P[:, j] / 1e-12
    h, _ = _steps(nf)
    fd = np.empty((n, n))
    for j in range(n):
        d = np.zeros(n)
        d[j] = h[j]
        fd[:, j] = (error(_injected(nf, d), new) - error(_injected(nf, -d), new)) / (2 * h[j])
    keep = np.ones((n, n), dtype=bool)
    keep[ATT.start : ATT.start + 2, ATT.start + 2] = False  # the held heading column
    np.testing.assert_allclose(g[ATT.start : ATT.stop, ATT.start + 2], [0.0, 0.0, 1.0])
    dth = float(np.linalg.norm(dx[ATT]))
    worst = 0.0
    for rows in (POS, VEL, ATT, RATE):
        for cols in (POS, VEL, ATT, RATE):
            k = keep[rows, cols]
            beyond = np.abs(g[rows, cols] - np.eye(n)[rows, cols])[k].max()
            err = np.abs(fd[rows, cols] - g[rows, cols])[k].max()
            rounding = 10.0 * 4.0 * EPS_MACH * 200.0 / h[cols].min()
            assert err <= 3.0 * dth * beyond + rounding, (rows, cols, err, beyond)
            if beyond > 0:
                worst = max(worst, err / beyond)
    # the body-frame reset turns the velocity with the attitude: exercised
    assert bool(np.abs(g[VEL, ATT]).max() > 0.1) is body_velocity_error
    print(f"reset (body={body_velocity_error}): worst error / G's part beyond I {worst:.2e}")


# --------------------------------------------------------------------------- gates
GATE_P = 0.9999
#: How far (relative) each NIS is put below or above its threshold: far beyond the
#: NIS's rounding (1e-15) and far inside the 10-25 % between neighbouring dofs'
#: quantiles (chi2.ppf(0.9999, 2, 3, 4) = 18.4, 21.1, 23.5), so only the right dof
#: accepts the one and rejects the other.
NIS_MARGIN = 1e-6
POS_SIGMA = np.array([1.2, 0.8, 2.5])
VEL_SIGMA = np.array([0.10, 0.15, 0.20])


def _gate_filter(quad_pairs: np.ndarray = PAIRS) -> NavFilter:
    """Level, heading north, at rest, with a diagonal navigation prior and the antenna at
    the array (so every GPS Jacobian is the identity on its block): S = P + R by hand."""
    nq = quad_pairs.shape[0]
    idx = np.r_[0:6, 6 : 6 + nq]
    cov = _COV[np.ix_(idx, idx)]
    nf = NavFilter(
        FilterNoise(cov, cov, cov * 1e-6), quad_pairs, np.zeros(3), gate_probability=GATE_P
    )
    q = np.array([1.0, 0.0, 0.0, 0.0])
    nf.initialise(0.0, POS0, np.zeros(3), q, np.zeros(3), POS_SIGMA, VEL_SIGMA, 0.01, 0.01)
    return nf


def _innovation(s_diag: np.ndarray, nis: float, direction: np.ndarray) -> np.ndarray:
    """An innovation along ``direction`` whose NIS with the diagonal S is ``nis``."""
    u = np.asarray(direction, dtype=float)
    return u * np.sqrt(nis / float(np.sum(u * u / s_diag)))


def _target(dof: int, side: int) -> float:
    return float(chi2.ppf(GATE_P, dof)) * (1.0 + side * NIS_MARGIN)


@pytest.mark.parametrize("reset", [False, True])
@pytest.mark.parametrize("side", [-1, 1])
def test_gps_position_gate_is_the_3_dof_quantile(side, reset):
    """A fix whose position NIS (``y^T (P + R)^-1 y``, 3 dof) is just below the 3-dof
    quantile is used, just above it rejected: as an ordinary fix and as the first fix
    after an outage (which resets onto the fix when it passes)."""
    nf = _gate_filter()
    r_sigma = np.array([1.5, 1.5, 3.0])
    s = POS_SIGMA**2 + r_sigma**2
    want = _target(3, side)
    y = _innovation(s, want, [0.6, -0.48, 0.64])
    res = nf.update_gps(nf.pos + y, nf.vel.copy(), r_sigma, 0.1, 0.0, reset=reset)
    assert res.nis_pos == pytest.approx(want, rel=1e-12)
    assert res.pos_accepted is (side < 0)
    assert nf.counters.gps_rejected_pos == int(side > 0)
    if reset:
        assert nf.counters.gps_gap_resets == int(side < 0)


@pytest.mark.parametrize("side", [-1, 1])
def test_gps_velocity_gate_is_the_3_dof_quantile(side):
    """A GPS velocity whose NIS (3 dof) is just below the 3-dof quantile is used, just
    above it rejected; the fix's position (exact) is used either way."""
    nf = _gate_filter()
    s = VEL_SIGMA**2 + 0.1**2
    want = _target(3, side)
    y = _innovation(s, want, [-0.3, 0.8, 0.52])
    res = nf.update_gps(nf.pos.copy(), y, np.array([1.5, 1.5, 3.0]), 0.1, 0.0)
    assert res.pos_accepted and res.nis_pos == pytest.approx(0.0, abs=1e-20)
    assert res.nis_vel == pytest.approx(want, rel=1e-12)
    assert res.vel_accepted is (side < 0)


@pytest.mark.parametrize("side", [-1, 1])
def test_zero_rate_gate_is_the_3_dof_quantile(side):
    """Zero rate: NIS ``w^T (P_rate + sigma^2 I)^-1 w``, 3 dof."""
    nf = _gate_filter()
    sigma = 0.004
    s = np.full(3, 0.01**2 + sigma**2)
    want = _target(3, side)
    nf.w = _innovation(s, want, [0.2, -0.5, 0.84])
    nis, ok = nf.update_zero_rate(sigma)
    assert nis == pytest.approx(want, rel=1e-12)
    assert ok is (side < 0)


@pytest.mark.parametrize("nq", [3, 2])
@pytest.mark.parametrize("side", [-1, 1])
def test_rate_gate_is_the_nq_dof_quantile(side, nq):
    """The rate products (nq of them: 3 on the nine-cube, 2 in a layout solving two), with
    correlated rate errors: the prediction ``w_i w_j + P_ij`` (the products' mean), NIS
    over ``S = J P_rate J^T + P_bias_q + S_qq / K + diag(P_ii P_jj + P_ij^2)`` (J the
    products' derivative at the rates shrunk by their variances, the last term the
    products' own spread), gated on nq dof."""
    pairs = PAIRS[:nq]
    nf = _gate_filter(pairs)
    p_rate = 1e-4 * np.array([[1.0, 0.3, -0.2], [0.3, 1.5, 0.1], [-0.2, 0.1, 0.8]])
    nf.P[RATE, RATE] = p_rate
    k = 6
    w = np.array([0.3, -0.2, 0.45])
    w_block = np.tile(w, (k, 1))
    ws = np.sign(w) * np.sqrt(w * w - np.diag(p_rate))
    jac = np.zeros((nq, 3))
    for r, (i, j) in enumerate(pairs):
        jac[r, i] += ws[j]
        jac[r, j] += ws[i]
    i, j = pairs[:, 0], pairs[:, 1]
    bq = nf.layout.bias.start + 6
    s = (
        jac @ p_rate @ jac.T
        + nf.P[bq : bq + nq, bq : bq + nq]
        + nf.noise.feature_cov[6:, 6:] / k
        + np.diag(p_rate[i, i] * p_rate[j, j] + p_rate[i, j] ** 2)
    )
    want = _target(nq, side)
    u = np.array([0.5, -0.7, 0.3])[:nq]
    y = u * np.sqrt(want / float(u @ np.linalg.solve(s, u)))
    pred = w[i] * w[j] + p_rate[i, j]
    nis = nf.update_rate(pred + y, w_block, k)
    assert nis == pytest.approx(want, rel=1e-9)
    assert nf.counters.rate_updates == int(side < 0)
    assert nf.counters.rate_rejected == int(side > 0)


@pytest.mark.parametrize("axis", [LATERAL, VERTICAL])
@pytest.mark.parametrize("side", [-1, 1])
def test_vehicle_model_gates_are_the_1_dof_quantile(side, axis):
    """Sideslip and angle of attack (no AOA state): with the attitude known exactly their
    second-order remainder vanishes, so R is the sigma's velocity alone (the horizontal
    speed's for the sideslip, the speed's for the angle of attack; the sideslip's
    vehicle also climbs, which the horizontal speed leaves out) and the NIS is
    ``v_axis^2 / (P_v,axis + R)``: 1 dof."""
    nf = _gate_filter()
    nf.P[ATT, :] = 0.0
    nf.P[:, ATT] = 0.0
    sigma = np.deg2rad(0.1)
    t2 = np.tan(sigma) ** 2
    speed = 30.0
    want = _target(1, side)
    p = VEL_SIGMA[axis] ** 2
    # v_axis^2 = want (p + (speed^2 + v_axis^2) tan^2): solved for v_axis
    v_axis = np.sqrt(want * (p + speed * speed * t2) / (1.0 - want * t2))
    vel = np.array([speed, 0.0, -4.0 if axis == LATERAL else 0.0])
    vel[axis] = v_axis
    nf.vel = vel
    if axis == LATERAL:
        nis = nf.update_sideslip(sigma, 5.0)
        used = nf.counters.sideslip_used
    else:
        nis = nf.update_angle_of_attack(sigma, 5.0)
        used = nf.counters.aoa_used
    assert nis == pytest.approx(want, rel=1e-9)
    assert used == int(side < 0)


@pytest.mark.parametrize("side", [-1, 1])
def test_heading_check_gate_is_the_1_dof_quantile(side):
    """The heading against the GPS course: ``d^2 / (P_yaw + sigma^2)``, 1 dof."""
    nf = _gate_filter()
    sigma = np.deg2rad(2.0)
    d = np.sqrt(_target(1, side) * (nf.P[8, 8] + sigma**2))
    nf.q = quat_from_euler(0.0, 0.0, 0.3)
    assert nf.check_heading_against_course(0.3 - d, sigma) is (side > 0)


def test_euler_variances_against_a_monte_carlo_of_the_attitude_error():
    """Roll, pitch and yaw variances from the NED attitude covariance, checked by
    perturbing the attitude with draws of the NED error and reading the Euler angles."""
    from filters.evaluate import euler_variances
    from ngnav.rotation import euler_from_quat, quat_from_euler, quat_from_rotvec, quat_multiply

    rng = np.random.default_rng(7)
    q = quat_from_euler(0.3, -0.2, np.deg2rad(100.0))  # flying east-ish, banked, nose down
    a = rng.normal(size=(3, 3)) * 1e-3
    p = a @ a.T + np.eye(3) * 1e-7
    got = euler_variances(q[None, :], p[None, :, :])[0]
    dth = rng.multivariate_normal(np.zeros(3), p, size=20000)
    qs = quat_multiply(quat_from_rotvec(dth), np.broadcast_to(q, (dth.shape[0], 4)))
    want = (euler_from_quat(qs) - euler_from_quat(q)).var(axis=0)
    # 20000 draws: a sample variance is within 3 % (its relative sigma is sqrt(2 / n), 1 %)
    np.testing.assert_allclose(got, want, rtol=0.03)
    # flying east the roll is mostly the east error: the north variance alone is far off
    assert abs(got[0] - p[0, 0]) > 0.2 * got[0]
