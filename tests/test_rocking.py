"""A still body's rocking (``ngnav.sim.rocking``): white rate, exact derivatives, exact turn."""

import numpy as np
import pytest
from scipy.stats import chi2

from ngnav.rotation import quat_conjugate, quat_multiply, quat_to_rotvec
from ngnav.sim.flight import FlightPlan, Profile, Transition, fly
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.rocking import rocking_angles, turn_body
from ngnav.sim.simulate import simulate_flight


def _interpolant(samples: np.ndarray, rate_hz: float, t_s: np.ndarray) -> np.ndarray:
    """The trigonometric interpolant of periodic ``samples`` (n, 3) at times ``t_s``, summed
    term by term (not by the inverse FFT the module uses)."""
    n = samples.shape[0]
    c = np.fft.rfft(samples, axis=0) / n
    k = np.arange(c.shape[0])
    weight = np.where((k == 0) | ((n % 2 == 0) & (k == n // 2)), 1.0, 2.0)
    phase = np.exp(2j * np.pi * np.outer(t_s, k) * rate_hz / n)
    return np.real(phase @ (weight[:, None] * c))


def test_the_rocking_rate_is_white_with_its_sigma():
    n, sigma = 20000, 3e-6
    _, rate, _ = rocking_angles(n, 1000.0, sigma, np.random.default_rng(3))
    # variance per axis: chi-square with n - 2 dof (mean and Nyquist terms removed)
    dof = n - 2
    lo, hi = chi2.ppf([0.0005, 0.9995], dof) / dof
    assert np.all((lo < rate.var(0) / sigma**2) & (rate.var(0) / sigma**2 < hi))
    # no correlation from one sample to the next (or a block of ten later): |r| < 4/sqrt(n)
    for lag in (1, 2, 10):
        r = np.sum(rate[lag:] * rate[:-lag], 0) / np.sum(rate * rate, 0)
        assert np.all(np.abs(r) < 4.0 / np.sqrt(n))


@pytest.mark.parametrize("n", [64, 65])
def test_the_angle_and_the_derivative_are_the_rate_s_exact_integral_and_derivative(n):
    rate_hz = 1000.0
    theta, rate, rdot = rocking_angles(n, rate_hz, 1e-3, np.random.default_rng(5))
    t = (np.arange(n) + 0.37) / rate_hz  # between the samples
    h = 1e-4 / rate_hz  # truncation ~ (2 pi 500 h)^2 / 6 ~ 2e-8 of the derivative
    for f, df in ((theta, rate), (rate, rdot)):
        fd = (_interpolant(f, rate_hz, t + h) - _interpolant(f, rate_hz, t - h)) / (2 * h)
        want = _interpolant(df, rate_hz, t)
        assert np.abs(fd - want).max() < 1e-6 * np.abs(want).max()


def test_a_turned_turning_body_keeps_its_kinematics():
    # a turning flight turned by a slow, smooth theta: the attitude's rate is the rate, the
    # rate's derivative is the derivative, to the first-order terms (|theta| |theta_dot|)
    plan = FlightPlan(
        duration_s=4.0,
        bank=Profile(0.0, (Transition(0.5, 1.0, np.deg2rad(30)),)),
        pitch=Profile(0.0),
        speed=Profile(30.0),
    )
    tr = fly(plan, 1000.0)
    a, f = 1e-4, 2.0  # rad, Hz
    phase = 2 * np.pi * f * tr.t_s[:, None] * np.array([1.0, 1.3, 0.7])
    theta = a * np.sin(phase)
    rate = a * 2 * np.pi * f * np.array([1.0, 1.3, 0.7]) * np.cos(phase)
    rdot = -a * (2 * np.pi * f * np.array([1.0, 1.3, 0.7])) ** 2 * np.sin(phase)
    turned = turn_body(tr, theta, rate, rdot)
    rel = quat_multiply(quat_conjugate(tr.q_nb), turned.q_nb)
    assert np.allclose(quat_to_rotvec(rel), theta, rtol=0, atol=1e-15)
    dq = (turned.q_nb[2:] - turned.q_nb[:-2]) * 500.0
    w = 2 * quat_multiply(quat_conjugate(turned.q_nb[1:-1]), dq)[:, 1:]
    first_order = a * np.abs(rate).max() + a * np.abs(tr.omega_b_rps).max()
    err = np.abs(w - turned.omega_b_rps[1:-1]).max()
    assert err < 1e-5 + first_order  # 1e-5: the central difference's, as the flight's own
    assert err < np.abs(rate).max() / 100  # far below the turn's own rate change
    # the turn's part of the rate derivative: central differences of the rate's change
    dw = turned.omega_b_rps - tr.omega_b_rps
    fd = (dw[2:] - dw[:-2]) * 500.0
    dwd = (turned.omega_dot_b_rps2 - tr.omega_dot_b_rps2)[1:-1]
    assert np.abs(fd - dwd).max() < 1e-3 * np.abs(rdot).max()
    assert np.array_equal(turned.pos_ned_m, tr.pos_ned_m)


def test_static_rocks_at_its_zero_rate_update_s_sigma():
    scn = load_flight("static")
    assert scn.rocking_rate_dps == scn.rest.rate_sigma_dps > 0
    run = simulate_flight(scn, 0)
    still = simulate_flight(load_flight("static", ["flight.rocking_rate_dps=0"]), 0)
    ratio = np.rad2deg(run.truth.omega_b_rps).std(0) / scn.rocking_rate_dps
    assert np.all(np.abs(ratio - 1.0) < 0.02)
    assert not np.any(still.truth.omega_b_rps)
    # the rocking draws its own numbers: the run's other draws are the still run's
    assert np.array_equal(run.config.scale, still.config.scale)
    assert np.array_equal(run.channel_bias_mps2, still.channel_bias_mps2)


def test_a_negative_rocking_is_refused():
    with pytest.raises(ValueError, match=r"flight\.rocking_rate_dps: expected a number >= 0"):
        load_flight("static", ["flight.rocking_rate_dps=-1"])
