"""The vehicle models' remainder as a consider state (``filter.remainder_consider``).

Checked against exact references: Isserlis' theorem for the covariance of two
Gaussian quadratic forms (Monte Carlo), the Schmidt filter's own definition for a
Gauss-Markov error it does not estimate (Monte Carlo of the filter it describes),
and a simulated survey flight's truth for the remainder's variance and correlation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from filters.ekf import NavFilter
from filters.pipeline import Pipeline, _feed
from filters.updates import refresh_markov_state, update_consider
from filters.vehicle_model import LATERAL, remainder_covariance, remainder_moments
from ngnav.flight_scenario import load_flight
from ngnav.runconfig import FilterSettings
from ngnav.simulate import simulate_flight
from studies.remainder import lag1_correlation, realized_remainders


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T / n + 0.1 * np.eye(n)


def _sym(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return 0.5 * (a + a.T)


def test_remainder_covariance_is_isserlis_for_gaussian_errors():
    """Two quadratic forms of jointly Gaussian errors (4 and 3 states): the closed form
    against 400 000 draws, within 5 standard errors; with the same error twice it is
    ``remainder_moments``' variance."""
    rng = np.random.default_rng(7)
    joint = _spd(rng, 7)
    mk, mj = _sym(rng, 4), _sym(rng, 3)
    c_kj = joint[:4, 4:]
    got = remainder_covariance(mk, mj, c_kj)
    draws = rng.multivariate_normal(np.zeros(7), joint, size=400_000)
    x, y = draws[:, :4], draws[:, 4:]
    qk = 0.5 * np.einsum("ni,ij,nj->n", x, mk, x)
    qj = 0.5 * np.einsum("ni,ij,nj->n", y, mj, y)
    prod = (qk - qk.mean()) * (qj - qj.mean())
    se = prod.std() / np.sqrt(prod.size)
    assert abs(prod.mean() - got) < 5.0 * se
    assert abs(got) > 10.0 * se  # a covariance the draws can tell from zero
    pk = joint[:4, :4]
    assert remainder_covariance(mk, mk, pk) == pytest.approx(remainder_moments(mk, pk).var)


def test_refresh_markov_state_keeps_the_covariance_positive_semidefinite():
    rng = np.random.default_rng(3)
    for _ in range(50):
        p = _spd(rng, 6)
        out = refresh_markov_state(p.copy(), 4, float(rng.uniform(0.0, 5.0)), rng.uniform(-1, 1))
        assert np.linalg.eigvalsh(out).min() > -1e-12
    p = _spd(rng, 3)
    p[2, :] = p[:, 2] = 0.0
    out = refresh_markov_state(p.copy(), 2, 2.0, 0.9)  # first step: a fresh error
    assert out[2, 2] == 2.0 and np.all(out[2, :2] == 0.0)
    with pytest.raises(ValueError, match="var must be"):
        refresh_markov_state(p.copy(), 2, -1.0, 0.5)
    with pytest.raises(ValueError, match="phi must be"):
        refresh_markov_state(p.copy(), 2, 1.0, 1.5)


def test_schmidt_filter_with_a_markov_error_reports_its_own_error_variance():
    """A constant state measured 60 times with an unestimated Gauss-Markov error of
    growing variance (correlation 0.95 between updates) and a little white noise: the
    consider filter's reported variance is the variance of its errors over 20 000
    simulated runs (within 5 standard errors, at five updates), while the filter that
    takes the error as white noise (its variance in R) reports a variance several
    times too small, outside those errors."""
    rng = np.random.default_rng(11)
    runs, steps, phi, sig_w = 20_000, 60, 0.95, 0.01
    x_true = rng.normal(0.0, 2.0, runs)
    b = np.zeros(runs)
    x_con = np.zeros(runs)
    x_white = np.zeros(runs)
    p = np.diag([4.0, 0.0])
    p_white = 4.0
    v_prev = 0.0
    h = np.array([[1.0, 1.0]])
    for k in range(steps):
        v = 1.0 + 0.05 * k
        if k == 0:
            b = rng.normal(0.0, np.sqrt(v), runs)
        else:
            b = phi * np.sqrt(v / v_prev) * b + rng.normal(0.0, np.sqrt((1 - phi**2) * v), runs)
        v_prev = v
        z = x_true + b + rng.normal(0.0, sig_w, runs)
        p = refresh_markov_state(p, 1, v, 0.0 if k == 0 else phi)
        r = np.array([[sig_w**2]])
        _, p, gain = update_consider(np.zeros(2), p, np.zeros(1), r, h, None, np.array([1]), True)
        assert gain[1, 0] == 0.0
        x_con += gain[0, 0] * (z - x_con)
        k_white = p_white / (p_white + v + sig_w**2)
        x_white += k_white * (z - x_white)
        p_white *= 1.0 - k_white
        if k in (0, 1, 5, 20, 59):
            e = x_true - x_con
            se = np.sqrt(2.0 / runs) * p[0, 0]
            assert abs(np.var(e) - p[0, 0]) < 5.0 * se, k
            if k >= 20:
                ew = x_true - x_white
                assert np.var(ew) - p_white > 5.0 * np.sqrt(2.0 / runs) * np.var(ew), k


def _survey_start(sets: list[str]):
    """``uav-survey``'s take-off, climb, cruise and first turn (106 s, GPS throughout)."""
    scn = load_flight(
        "uav-survey",
        [
            "flight.legs=[{ duration_s = 10.0, ramp_s = 1.0, speed_mps = 0.0 },"
            " { duration_s = 10.0, ramp_s = 8.0, speed_mps = 20.0 },"
            " { duration_s = 40.0, ramp_s = 2.0, pitch_deg = 8.0 },"
            " { duration_s = 30.0, ramp_s = 2.0, pitch_deg = 0.0 },"
            " { duration_s = 16.0, ramp_s = 2.0, bank_deg = 25.0 }]",
            "gps.outage_s=0",
            *sets,
        ],
    )
    return simulate_flight(scn, 0)


def test_remainder_consider_is_a_setting_that_carries_two_consider_states():
    """Off by default; on, the filter carries the two ``RB`` states, never moves them,
    keeps P positive definite, and its estimates differ from the counted remainder's."""
    assert FilterSettings().remainder_consider is False
    sim = _survey_start([])
    ends = {}
    for on in (False, True):
        cfg = replace(sim.config, filter=replace(sim.config.filter, remainder_consider=on))
        pipe = Pipeline(cfg)
        _feed(pipe, sim.samples, sim.fixes, None)
        nf: NavFilter = pipe.nf
        assert nf.layout.n_rb == (2 if on else 0)
        nf.check_covariance("the test's end")
        if on:
            rb = nf.layout.rb
            assert np.all(np.diagonal(nf.P)[rb] > 0.0)
            assert nf.counters.sideslip_used > 100 and nf.counters.aoa_used > 100
        ends[on] = nf.vel.copy()
    assert not np.allclose(ends[True], ends[False], rtol=0.0, atol=1e-9)


def test_remainder_state_matches_the_truths_remainder_in_gps_held_flight(monkeypatch):
    """Against the truth of the survey's first 106 s (from 30 s, GPS held): the sideslip
    model's realized remainder standardised by the variance the filter gave its
    ``RB`` state has a mean square inside chi-square's 99.9 % bounds for its
    effective number of independent samples, and its lag-1 correlation is the
    correlation the filter gave the state (median over the updates) within 0.1."""
    sim = _survey_start(["filter.remainder_consider=true"])
    log = []
    pipe = Pipeline(sim.config, body_velocity_log=log)
    steps = []
    step = NavFilter._step_remainder_state

    def record(self, axis, mq, sel, var):
        phi = step(self, axis, mq, sel, var)
        if axis == LATERAL:
            steps.append((self.t_s, phi))
        return phi

    monkeypatch.setattr(NavFilter, "_step_remainder_state", record)
    _feed(pipe, sim.samples, sim.fixes, None)
    recs = [r for r in log if r.axis == LATERAL]
    rr = realized_remainders(recs, sim.truth)
    keep = rr.t_s >= 30.0
    z = rr.z()[keep]
    # the state's correlations at the same updates (the hand-over's hold has none)
    t_phi = dict(steps)
    phi_model = float(np.median([t_phi[t] for t in rr.t_s[keep]]))
    rho = lag1_correlation(z)
    n_eff = z.size * (1.0 - rho) / (1.0 + rho)
    lo, hi = chi2.ppf([0.0005, 0.9995], n_eff) / n_eff
    assert lo < np.mean(z**2) < hi
    assert abs(rho - phi_model) < 0.1
    assert 0.5 < phi_model < 0.99  # the remainder is neither white nor constant
