"""The sideslip remainder measured against a truth (``ngnav remainder``)."""

import dataclasses
import itertools
import json

import numpy as np
import pytest

from filters.pipeline import run_filter
from filters.vehicle_model import (
    CALM_AIR_SIGMA_DEG,
    COAST_REMAINDER_UPDATES,
    LATERAL,
    SIDESLIP_REMAINDER_UPDATES,
    VERTICAL,
    remainder_variance,
)
from ngnav.records import FlightTruth
from ngnav.rotation import dcm_from_quat, quat_from_rotvec, quat_multiply
from ngnav.settings import VehicleSettings
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from studies.remainder import (
    RHO_MAX,
    RealizedRemainders,
    integrated_autocorrelation,
    realized_remainder,
    realized_remainders,
    rotvec_between,
    updates_per_value,
    window_persistence,
)
from tests.helpers import SHORT_TACTICAL_ARGS, level_filter, run_study


def _one_update(slip_mps: float = 0.0):
    """A filter at a banked, climbing nominal state (20 m/s along the body x axis plus
    ``slip_mps`` along its y axis), after one logged sideslip update."""
    nf, _, _ = level_filter()
    nf.q = quat_from_rotvec(np.array([0.3, -0.1, 2.0]))
    c = dcm_from_quat(nf.q)
    nf.vel = 20.0 * c[:, 0] + slip_mps * c[:, 1]
    q0, v0 = nf.q.copy(), nf.vel.copy()
    nf.body_velocity_log = []
    nf.update_sideslip(np.deg2rad(0.01), 5.0)
    (rec,) = nf.body_velocity_log
    return nf, rec, q0, v0


def test_the_log_holds_the_state_the_update_linearised_at():
    nf, rec, q0, v0 = _one_update()
    np.testing.assert_array_equal(rec.q_nb, q0)
    np.testing.assert_array_equal(rec.vel_ned_mps, v0)
    v_lat, h = nf.body_velocity_model(q0, v0)
    assert rec.v_axis_mps == v_lat
    np.testing.assert_array_equal(rec.h_att, h[0, 6:9])
    np.testing.assert_array_equal(rec.h_vel, h[0, 3:6])
    assert (rec.axis, rec.aoa_rad, rec.dv_daoa_mps) == (LATERAL, 0.0, 0.0)
    assert rec.accepted and nf.counters.sideslip_used == 1
    assert not np.array_equal(nf.q, q0)  # the update moved the state after the record
    # a rejected update is recorded too
    nf, rec, _, _ = _one_update(slip_mps=1.0)
    assert not rec.accepted and nf.counters.sideslip_rejected == 1


def test_realized_remainder_is_the_rotations_second_order_term():
    """Against the exponential map's expansion, written with cross products.

    With ``a = C e_y`` the true lateral velocity is ``(exp([dtheta]x) a) . (v + dv)``
    and ``exp([dtheta]x) a = a + dtheta x a + dtheta x (dtheta x a) / 2 + O(3)``: the
    terms beyond the linear ones are ``(dtheta x a) . dv + (dtheta x (dtheta x a)) .
    v / 2``, the last one the attitude-product part. What is left must shrink as the
    third power of the error's size.
    """
    _, rec, q0, v0 = _one_update()
    a = dcm_from_quat(q0)[:, 1]
    dth0 = np.array([0.02, -0.03, 0.025])
    dv0 = np.array([0.4, -0.3, 0.2])
    left = []
    for eps in (1.0, 0.5, 0.25):
        dth, dv = eps * dth0, eps * dv0
        q_true = quat_multiply(quat_from_rotvec(dth), q0)
        np.testing.assert_allclose(rotvec_between(q_true, q0), dth, atol=1e-14)
        np.testing.assert_allclose(rotvec_between(-q_true, q0), dth, atol=1e-14)
        r, r_att = realized_remainder(rec, q_true, v0 + dv)
        second_att = 0.5 * np.cross(dth, np.cross(dth, a)) @ v0
        second = np.cross(dth, a) @ dv + second_att
        assert r_att == pytest.approx(second_att, rel=1e-12)
        assert abs(second) > 1e-4 * eps**2  # the term is exercised
        left.append(abs(r - second))
    assert left[-1] < 0.05 * abs(second)  # third order is small at the smallest size
    for big, small in itertools.pairwise(left):
        assert 6.0 < big / small < 10.0  # halving the error divides it by 8


def test_realized_vertical_remainder_is_the_second_order_term_with_the_angle():
    """The angle-of-attack model: the wind-normal axis ``n_b(alpha)`` turns with the
    angle, ``n_b(alpha + da) = n_b - da t_b - da^2 n_b / 2 + O(3)``, so beyond the
    linear terms (``b = C t_b``) the true velocity along it holds ``(dtheta x a) . dv +
    (dtheta x (dtheta x a)) . v / 2 - da b . dv - da (dtheta x b) . v - da^2 (a . v) / 2``;
    what is left shrinks as the cube of the error's size."""
    nf, _, _ = level_filter(aoa_sigma_rad=0.02)
    nf.q = quat_from_rotvec(np.array([0.3, -0.1, 2.0]))
    nf.aoa_b = np.deg2rad(3.0)
    c = dcm_from_quat(nf.q)
    al = nf.aoa
    nf.vel = 20.0 * (c @ [np.cos(al), 0.0, np.sin(al)])  # at the angle of attack
    q0, v0 = nf.q.copy(), nf.vel.copy()
    nf.body_velocity_log = []
    nf.update_angle_of_attack(np.deg2rad(0.01), 5.0)
    (rec,) = nf.body_velocity_log
    assert rec.axis == VERTICAL and rec.aoa_rad == pytest.approx(al)
    a = c @ [-np.sin(al), 0.0, np.cos(al)]
    b = c @ [np.cos(al), 0.0, np.sin(al)]
    assert rec.dv_daoa_mps == pytest.approx(-(b @ v0), rel=1e-12)
    dth0, dv0, da0 = np.array([0.02, -0.03, 0.025]), np.array([0.4, -0.3, 0.2]), 0.03
    left = []
    for eps in (1.0, 0.5, 0.25, 0.125):
        dth, dv, da = eps * dth0, eps * dv0, eps * da0
        q_true = quat_multiply(quat_from_rotvec(dth), q0)
        r, r_att = realized_remainder(rec, q_true, v0 + dv, al + da)
        second_att = 0.5 * np.cross(dth, np.cross(dth, a)) @ v0
        second = (
            np.cross(dth, a) @ dv
            + second_att
            - da * (b @ dv)
            - da * (np.cross(dth, b) @ v0)
            - 0.5 * da * da * (a @ v0)
        )
        assert r_att == pytest.approx(second_att, rel=1e-12)
        left.append(abs(r - second))
    assert left[-1] < 0.05 * abs(second)
    for big, small in itertools.pairwise(left):
        assert 6.0 < big / small < 10.0


def _truth(t_s: np.ndarray, q_nb: np.ndarray, vel: np.ndarray) -> FlightTruth:
    n = t_s.shape[0]
    z = np.zeros((n, 3))
    return FlightTruth(t_s, z, vel, q_nb, z, z, z)


def test_each_update_meets_the_truth_at_its_own_time():
    _, rec, q0, v0 = _one_update()
    t = np.arange(5) * 0.01
    q = np.tile(q0, (5, 1))
    v = np.tile(v0, (5, 1))
    v[2] += [0.0, 1.0, 0.0]  # only sample 2 differs
    recs = [rec._replace(t_s=0.02), rec._replace(t_s=0.03)]
    got = realized_remainders(recs, _truth(t, q, v))
    expect2 = realized_remainder(rec, q0, v[2])[0]
    expect3 = realized_remainder(rec, q0, v0)[0]
    assert got.r_mps.tolist() == [expect2, expect3]
    assert expect2 != expect3
    np.testing.assert_array_equal(got.var_att_m2ps2, [rec.remainder.var_att] * 2)
    np.testing.assert_array_equal(got.mean_att_mps, [rec.remainder.mean_att] * 2)
    np.testing.assert_array_equal(got.r_m2ps2, [rec.r_m2ps2] * 2)
    (w,) = window_persistence([got], np.array([0.0, 1.0]))
    left2, left3 = expect2 - rec.remainder.mean, expect3 - rec.remainder.mean
    assert w.r_ratio == pytest.approx(2 * rec.r_m2ps2 / (left2**2 + left3**2), rel=1e-12)
    with pytest.raises(ValueError, match="must be measured apart"):
        realized_remainders([rec, rec._replace(axis=VERTICAL)], _truth(t, q, v))
    with pytest.raises(ValueError, match=r"updates against the truth: .* not truth sample times"):
        realized_remainders([rec._replace(t_s=0.015)], _truth(t, q, v))
    with pytest.raises(ValueError, match="no vehicle-model updates recorded"):
        realized_remainders([], _truth(t, q, v))


def test_updates_per_value():
    assert updates_per_value(0.6) == pytest.approx(4.0)
    assert updates_per_value(0.0) == 1.0
    assert updates_per_value(-0.3) == 1.0
    assert updates_per_value(1.0) == pytest.approx((1 + RHO_MAX) / (1 - RHO_MAX))
    assert np.isnan(updates_per_value(float("nan")))


def _ar1(rng, rho: float, n: int) -> np.ndarray:
    x = np.empty(n)
    x[0] = rng.normal()
    e = rng.normal(size=n) * np.sqrt(1.0 - rho * rho)
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x


def test_window_persistence_recovers_known_ar1_sequences():
    """Unit-variance AR(1) remainders (rho 0.6, and 0.9 for the attitude part) drawn
    about the model's mean with the model's variance: z^2 must be 1 and the counts 4
    and 19, within the sampling spread of 40 runs of 500 updates.

    z^2's standard error: z^2 has variance 2 and correlation rho^(2k), so the mean of
    N values has variance 2 (1 + rho^2) / (1 - rho^2) / N (0.015 for rho 0.6). A run's
    lag-1 estimate has sd sqrt((1 - rho^2) / n) (0.036) and a bias of about
    -(1 + 3 rho) / n (-0.006); the median of 40 has about 1.25 sd / sqrt(40) (0.007).
    """
    rng = np.random.default_rng(2026)
    runs, n = 40, 500
    t = np.arange(n) * 0.2
    out = []
    for _ in range(runs):
        mean, sd = rng.normal(size=n) * 1e-3, np.exp(rng.normal(size=n)) * 1e-3
        mean_a, sd_a = rng.normal(size=n) * 1e-3, np.exp(rng.normal(size=n)) * 1e-3
        out.append(
            RealizedRemainders(
                t,
                mean + sd * _ar1(rng, 0.6, n),
                mean_a + sd_a * _ar1(rng, 0.9, n),
                mean,
                sd * sd,
                mean_a,
                sd_a * sd_a,
            )
        )
    (w,) = window_persistence(out, np.array([0.0, 200.0]))
    assert w.updates == runs * n
    se = np.sqrt(2.0 * (1 + 0.36) / (1 - 0.36) / (runs * n))
    assert abs(w.z2 - 1.0) < 4.0 * se
    se_a = np.sqrt(2.0 * (1 + 0.81) / (1 - 0.81) / (runs * n))
    assert abs(w.z2_att - 1.0) < 4.0 * se_a
    assert abs(w.rho - 0.6) < 0.04
    assert abs(w.rho_att - 0.9) < 0.03
    assert 3.5 < w.count < 4.5
    assert 15.0 < w.count_att < 24.0
    assert np.isnan(w.r_ratio)  # no R given
    assert 3.0 < w.tau < 5.0
    assert 13.0 < w.tau_att < 25.0
    # windows split the updates; an empty window is left out
    ws = window_persistence(out, np.array([0.0, 50.0, 100.0, 300.0, 400.0]))
    assert [x.updates for x in ws] == [runs * 250, runs * 250]


def test_integrated_autocorrelation_sees_a_slow_part_the_lag1_correlation_misses():
    """Half the variance an AR(1) at 0.3, half at 0.95: tau = 0.5 (1.3 / 0.7) + 0.5
    (1.95 / 0.05) = 20.4 updates, while the lag-1 correlation (0.625) says 4.3 as an
    AR(1). 40 runs of 2000; Sokal's estimate has a standard deviation of about
    tau sqrt(2 (2 M + 1) / N) (1.5 here, M about 100)."""
    rng = np.random.default_rng(5)
    runs = [np.sqrt(0.5) * (_ar1(rng, 0.3, 2000) + _ar1(rng, 0.95, 2000)) for _ in range(40)]
    tau = integrated_autocorrelation(runs)
    assert abs(tau - 20.4) < 5.0
    rho = float(np.median([np.corrcoef(x[1:], x[:-1])[0, 1] for x in runs]))
    assert updates_per_value(rho) < 6.0  # the AR(1) reading misses the slow part
    # white noise: 1; too short or without spread: NaN
    assert abs(integrated_autocorrelation([rng.normal(size=5000)]) - 1.0) < 0.2
    assert np.isnan(integrated_autocorrelation([np.ones(2)]))
    assert np.isnan(integrated_autocorrelation([np.ones(10)]))


def test_remainder_counts_are_settings_that_reach_the_update():
    """``vehicle.remainder_updates`` and ``vehicle.attitude_remainder_updates`` reach the
    filter and the R of its sideslip updates: on the first update after the hand-over's
    hold (8 s from the vehicle models' first update, during which both count the coast's
    40), where both runs are still in the same state, the larger attitude count gives the
    larger R, and each R holds the remainder's variance at least once. (The R's formula,
    with the count weighted by the prior, is checked on the filter itself in
    tests/test_ekf_models.py.)"""
    with pytest.raises(ValueError, match=r"vehicle\.remainder_updates must be a number in"):
        VehicleSettings(remainder_updates=0.5)
    with pytest.raises(ValueError, match=r"vehicle\.attitude_remainder_updates must be"):
        VehicleSettings(attitude_remainder_updates=float("nan"))
    firsts = {}
    for n_att in (40.0, 7.0):
        scn = load_flight(
            "tactical",
            [
                "run.rate_hz=200",
                f"vehicle.attitude_remainder_updates={n_att}",
                # the NED error, whose remainder has the attitude part these counts
                # count (tactical.toml takes the body frame's, which has none), and its
                # hand-over count, which covers both attitude counts through the hold
                "vehicle.body_velocity_error=false",
                "vehicle.coast_remainder_updates=40",
            ],
        )
        assert scn.vehicle.attitude_remainder_updates == n_att
        sim = simulate_flight(scn, 0)
        log = []
        run_filter(sim.samples, sim.fixes, sim.config, body_velocity_log=log)
        # the first update after the hand-over's hold (from the models' first update),
        # before which the count is the hold's
        hold_s = scn.vehicle.coast_remainder_updates / 5.0
        t0 = min(r.t_s for r in log)
        firsts[n_att] = next(r for r in log if r.axis == LATERAL and r.t_s >= t0 + hold_s - 1e-6)
    a, b = firsts[40.0], firsts[7.0]
    assert a.t_s == b.t_s and a.remainder == b.remainder
    speed = np.hypot(*a.vel_ned_mps[:2])
    sigma2 = (speed * np.tan(np.deg2rad(CALM_AIR_SIGMA_DEG))) ** 2
    for rec in firsts.values():
        assert rec.r_m2ps2 >= sigma2 + rec.remainder.var * (1 - 1e-12)
    assert a.r_m2ps2 > b.r_m2ps2


def test_remainder_cli():
    """``python -m studies.remainder`` as a real subprocess on two short tactical runs."""
    proc = run_study("remainder", *SHORT_TACTICAL_ARGS, "--runs", "2", "--window", "30", "--json")
    out = json.loads(proc.stdout)
    assert out["runs"] == 2 and out["left_out"] == []
    counts = ("remainder_updates", "attitude_remainder_updates", "coast_remainder_updates")
    assert tuple(out[k] for k in counts) == (4.0, 7.0, 10.0)  # tactical.toml: 7, 10
    assert set(out["models"]) == {"lateral", "vertical"}  # tactical flies both models
    for m in out["models"].values():
        assert [(w["t0_s"], w["t1_s"]) for w in m["windows"]] == [(0.0, 30.0), (30.0, 60.0)]
        whole = m["whole"]
        assert whole["updates"] == sum(w["updates"] for w in m["windows"])
        # 5 Hz over two flights of about 60 s each
        assert 500 < whole["updates"] <= 2 * 5 * 62
    bad = run_study("remainder", "--scenario", "static", "--runs", "1", check=False)
    assert bad.returncode == 2
    assert "has no vehicle model" in bad.stderr


def test_coast_counts_the_remainder_longer_and_holds_after():
    """Past ``coast_after_s`` without an accepted GPS position the body-velocity
    updates count the whole remainder ``coast_remainder_updates`` times, and go on
    doing so for ``coast_hold_s`` after the last coasting update; the update's R
    carries the count (``sigma^2 + remainder_variance``)."""
    nf, _, _ = level_filter()
    nf.coast_hold_s = 8.0
    nf.vel = np.array([20.0, 0.0, 0.0])
    nf.body_velocity_log = []
    fixed = (SIDESLIP_REMAINDER_UPDATES, COAST_REMAINDER_UPDATES)
    sigma2 = (20.0 * np.tan(np.deg2rad(1e-3))) ** 2
    expected = []
    for t, t_fix, n in (
        (0.5, 0.0, fixed[0]),  # GPS holds
        (1.0, 0.0, fixed[0]),  # exactly coast_after_s: not yet
        (1.2, 0.0, fixed[1]),  # coasting
        (2.4, 2.2, fixed[1]),  # GPS back, inside the hold (until 9.2 s)
        (9.1, 9.0, fixed[1]),
        (9.3, 9.2, fixed[0]),
    ):
        nf.t_s, nf.t_last_position_fix = t, t_fix
        nf.update_sideslip(np.deg2rad(1e-3), 5.0)
        rec = nf.body_velocity_log[-1]
        expected.append(sigma2 + remainder_variance(rec.remainder, n, 40.0))
    got = [r.r_m2ps2 for r in nf.body_velocity_log]
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    # the coast's count shows in R: the fixed count would have given far less
    rem = nf.body_velocity_log[2].remainder
    assert got[2] > 1.5 * (sigma2 + remainder_variance(rem, fixed[0], 40.0))
    assert nf.counters.coast_model_updates == 3
    # a receiver at 1 Hz: its normal spacing is not a coast, five missed fixes are
    nf, _, _ = level_filter()
    for t in (0.0, 1.0, 2.0):
        nf.t_s = t
        assert nf.update_gps(np.zeros(3), np.zeros(3), np.ones(3), 0.1).pos_accepted
    assert nf.fix_interval_s == 1.0 and nf.t_last_position_fix == 2.0
    nf.vel = np.array([20.0, 0.0, 0.0])
    for t, n in ((3.5, fixed[0]), (6.9, fixed[0]), (7.1, fixed[1])):
        nf.t_s = t
        assert nf.current_remainder_updates() == n, t
    with pytest.raises(ValueError, match=r"vehicle\.coast_remainder_updates must be"):
        VehicleSettings(coast_remainder_updates=0.0)


def test_an_outage_switches_the_count_for_its_length_and_the_hold():
    """End to end: a short ``tactical`` flight with a 5 s GPS outage from 20 s counts
    its vehicle-model updates as coasting from 1 s into the outage until the coast's
    count of 5 Hz updates (``coast_remainder_updates``: 10, 2 s) after the GPS is back,
    both models; without an outage none. Either way its first that many updates, after
    the launcher's hand-over, count as the hand-over."""
    key = "vehicle-model updates counted as coasting"
    base = ["run.rate_hz=200"]
    scn = load_flight("tactical", base)
    count = scn.vehicle.coast_remainder_updates
    hold_s = count / 5.0
    sim = simulate_flight(scn, 0)
    counts = run_filter(sim.samples, sim.fixes, sim.config).counts
    assert counts[key] == 0
    # the hold at 5 Hz, both models, from the first update at the start
    assert counts["vehicle-model updates counted as the hand-over"] == 2 * count
    scn = load_flight("tactical", [*base, "gps.outage_start_s=20", "gps.outage_s=5"])
    sim = simulate_flight(scn, 0)
    n = run_filter(sim.samples, sim.fixes, sim.config).counts[key]
    # (5 s - 1 s + the hold) at 5 Hz, two models; the fixes' 0.1 s spacing and 0.05 s
    # latency move each end by at most a fix and an update
    assert abs(n - 2 * 5 * (4.0 + hold_s)) <= 2 * 2, n


def test_a_handover_counts_the_remainder_as_a_coasts_end():
    """After :meth:`NavFilter.initialise` the body-velocity updates count the whole
    remainder ``coast_remainder_updates`` times for ``handover_hold_s`` from the models'
    first update (at once after a hand-over, later after a static alignment), then
    ``remainder_updates``; the attitude part is never counted fewer times than the
    whole; without a hold none."""
    nf, _, _ = level_filter()
    assert nf.handover_hold_s == 0.0
    nf.vel = np.array([20.0, 0.0, 0.0])
    nf.t_s = nf.t_last_position_fix = 0.0
    assert nf.current_remainder_updates() == SIDESLIP_REMAINDER_UPDATES
    nf.handover_hold_s = 8.0
    nf.attitude_remainder_updates = 7.0
    nf.initialise(
        1.0, np.zeros(3), nf.vel, nf.q, np.zeros(3), np.ones(3), np.ones(3), np.ones(3), 0.01
    )
    nf.body_velocity_log = []
    sigma2 = (20.0 * np.tan(np.deg2rad(1e-3))) ** 2
    for t, n in ((1.0, COAST_REMAINDER_UPDATES), (8.9, COAST_REMAINDER_UPDATES), (9.0, 4.0)):
        nf.t_s = nf.t_last_position_fix = t
        nf.update_sideslip(np.deg2rad(1e-3), 5.0)
        rec = nf.body_velocity_log[-1]
        rem = rec.remainder
        # in the hold the whole count (40) covers the attitude part's 7
        att = max(7.0, n) - n
        assert rec.r_m2ps2 == pytest.approx(sigma2 + n * rem.var + att * rem.var_att, rel=1e-12)
    assert nf.counters.handover_model_updates == 2 and nf.counters.coast_model_updates == 0
    # a static alignment: the models' first update comes later (the take-off roll), and
    # the hold runs from it, not from the alignment
    nf.initialise(
        20.0, np.zeros(3), nf.vel, nf.q, np.zeros(3), np.ones(3), np.ones(3), np.ones(3), 0.01
    )
    nf.t_s = nf.t_last_position_fix = 24.0
    assert nf.counts_as_coast()  # the hold is still to come: the models run at 5 Hz
    for t, n in ((25.0, COAST_REMAINDER_UPDATES), (32.9, COAST_REMAINDER_UPDATES), (33.0, 4.0)):
        nf.t_s = nf.t_last_position_fix = t
        nf.update_sideslip(np.deg2rad(1e-3), 5.0)
        rem = nf.body_velocity_log[-1].remainder
        att = max(7.0, n) - n
        got = nf.body_velocity_log[-1].r_m2ps2
        assert got == pytest.approx(sigma2 + n * rem.var + att * rem.var_att, rel=1e-12)
    assert not nf.counts_as_coast()
    assert nf.counters.handover_model_updates == 4
    assert remainder_variance(rem, 40.0, 7.0) == pytest.approx(40.0 * rem.var)
    assert remainder_variance(rem, 4.0, 7.0) == pytest.approx(4.0 * rem.var + 3.0 * rem.var_att)
    with pytest.raises(ValueError, match="handover_hold_s must be a finite number"):
        dataclasses.replace(nf, handover_hold_s=-1.0)
