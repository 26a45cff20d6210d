"""The zero-rate update at detected rest: the update, the detector, and `static` held."""

import numpy as np
import pytest
from scipy.stats import chi2

from filters.ekf import FilterNoise, NavFilter
from filters.evaluate import nees, run_errors
from filters.pipeline import Pipeline, run_filter
from filters.rest import CONFIRM_S, FIX_MAX_AGE_S, RestDetector
from filters.state import ATT, RATE, VEL
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from tests.helpers import level_filter

BLOCK_S = 0.01
BLOCK_N = 10


def _detector(seed: int = 0) -> tuple[RestDetector, np.ndarray, np.random.Generator]:
    """A detector on a random positive-definite per-sample covariance, with its factor."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(6, 6)) * 0.01
    cov = a @ a.T + np.diag([0.04] * 3 + [4e-4] * 3)
    return RestDetector(cov, BLOCK_S, BLOCK_N), np.linalg.cholesky(cov / BLOCK_N), rng


# ------------------------------------------------------------------------ the update
def test_zero_rate_update_is_the_information_form():
    nf, _, _ = level_filter()
    rng = np.random.default_rng(5)
    n = nf.layout.n
    a = rng.normal(size=(n, n))
    p = a @ a.T * 1e-4 + np.eye(n) * 1e-5
    # no correlation of the rate with the attitude or velocity: the reset is the identity
    for blk in (ATT, VEL):
        p[blk, :] = 0.0
        p[:, blk] = 0.0
        p[blk, blk] = np.eye(3) * 1e-4
    nf.P = p.copy()
    w = np.array([2e-3, -1e-3, 4e-3])
    nf.w = w.copy()
    bias0 = nf.bias.copy()
    sigma = 1e-3
    nis, ok = nf.update_zero_rate(sigma)
    h = np.zeros((3, n))
    h[:, RATE] = np.eye(3)
    r_inv = np.eye(3) / sigma**2
    p_post = np.linalg.inv(np.linalg.inv(p) + h.T @ r_inv @ h)
    dx = p_post @ h.T @ r_inv @ (-w)
    assert ok
    assert nis == pytest.approx(float(w @ np.linalg.solve(p[RATE, RATE] + np.eye(3) * sigma**2, w)))
    assert np.allclose(nf.P, p_post, rtol=1e-7, atol=1e-15)
    assert np.allclose(nf.w, w + dx[RATE], rtol=0, atol=1e-12)
    assert np.allclose(nf.bias, bias0 + dx[nf.layout.bias], rtol=0, atol=1e-12)
    assert nf.counters.zero_rate_used == 1


def test_zero_rate_update_is_gated_and_checked():
    nf, _, _ = level_filter()
    nf.w = np.array([0.0, 0.0, 1.0])  # a turn 100 sigma from zero
    p0, w0 = nf.P.copy(), nf.w.copy()
    nis, ok = nf.update_zero_rate(1e-3)
    assert not ok and nis > nf.gate3
    assert np.array_equal(nf.P, p0) and np.array_equal(nf.w, w0)
    assert nf.counters.zero_rate_rejected == 1
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="sigma_rps"):
            nf.update_zero_rate(bad)


def test_rate_reset_each_block_gives_the_rate_one_blocks_own_noise():
    _, _, solver = level_filter()
    cov = solver.covariance()
    mapped = cov.copy()
    mapped[0:3, 0:3] *= 0.8  # what a loop's mapping takes off
    nf = NavFilter(
        FilterNoise(mapped, cov, cov * 1e-6, block_wdot_cov=cov[0:3, 0:3]),
        np.array([[1, 2], [0, 2], [0, 1]]),
        np.zeros(3),
    )
    k, dt = 10, 1e-3
    c = np.eye(3)
    _, q_loop = nf.propagation_matrices(k, dt, c, np.zeros(3))
    nf.rate_reset_each_block = True
    _, q_block = nf.propagation_matrices(k, dt, c, np.zeros(3))
    assert np.allclose(q_loop[RATE, RATE], k * dt**2 * mapped[0:3, 0:3], rtol=1e-12)
    assert np.allclose(q_block[RATE, RATE], k * dt**2 * cov[0:3, 0:3], rtol=1e-12)
    # only the angular acceleration's own terms change
    diff = q_block - q_loop
    keep = np.r_[ATT, RATE]
    assert np.abs(np.delete(np.delete(diff, keep, 0), keep, 1)).max() == 0.0
    with pytest.raises(ValueError, match="block_wdot_cov"):
        NavFilter(
            FilterNoise(cov, cov, cov, block_wdot_cov=np.eye(2)),
            np.array([[1, 2], [0, 2], [0, 1]]),
            np.zeros(3),
        )


# ------------------------------------------------------------------------ the detector
def test_detector_holds_rest_on_noise_with_few_false_alarms():
    det, chol, rng = _detector()
    ref = np.array([0.01, -0.02, 0.0, 0.1, -0.2, -9.8])
    det.start_at_rest(0.0, ref, 500)
    n = 20000  # 200 s of 100 Hz blocks; at 1e-6 per block and test, about 0.04 alarms
    for i in range(n):
        t = (i + 1) * BLOCK_S
        det.observe_block(t, ref + chol @ rng.normal(size=6), BLOCK_N)
        if i % 20 == 0:
            det.observe_fix(t, rng.normal(size=3) * 0.1, 0.1)
    assert det.unsteady_blocks <= 2
    assert det.at_rest or det.unsteady_blocks > 0


def test_detector_ends_rest_on_the_first_block_of_an_onset():
    det, chol, rng = _detector(1)
    ref = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -9.8])
    det.start_at_rest(0.0, ref, 500)
    for i in range(100):
        assert det.observe_block((i + 1) * BLOCK_S, ref + chol @ rng.normal(size=6), BLOCK_N)
    # a push along x of 10 sigma of one block's force noise (the test's limit: 6 for 6 dof)
    sd = np.sqrt(np.diag(chol @ chol.T))
    push = ref + np.array([0, 0, 0, 10.0 * sd[3], 0, 0])
    assert not det.observe_block(1.01, push + chol @ rng.normal(size=6), BLOCK_N)
    assert not det.at_rest


def test_detector_sees_a_slow_onset_one_block_hides():
    det, chol, rng = _detector(2)
    ref = np.zeros(6)
    det.start_at_rest(0.0, ref, 500)
    sd = np.sqrt(np.diag(chol @ chol.T))
    t_end = None
    for i in range(300):
        t = (i + 1) * BLOCK_S
        # the yaw acceleration ramps up at 2 sigma of one block per second
        x = ref + chol @ rng.normal(size=6)
        x[2] += 2.0 * sd[2] * max(0.0, t - 0.5)
        if not det.observe_block(t, x, BLOCK_N):
            t_end = t
            break
    # one block sees it only at about 5 sigma (2.5 s after the start); the mean, sooner
    assert t_end is not None and t_end < 2.0


def test_detector_enters_rest_after_its_confirmation_and_not_while_fixes_move():
    det, chol, rng = _detector(3)
    ref = np.array([0.0, 0.0, 0.0, 0.3, 0.0, -9.8])
    t = 0.0
    entered = None
    for i in range(300):
        t = (i + 1) * BLOCK_S
        if i % 20 == 0:  # 5 Hz fixes: moving at 1 m/s for the first second
            det.observe_fix(t, np.array([1.0 if t < 1.0 else 0.0, 0.0, 0.0]), 0.1)
        if det.observe_block(t, ref + chol @ rng.normal(size=6), BLOCK_N) and entered is None:
            entered = t
    # the first still fix at 1.01 s; confirmation takes CONFIRM_S of still fixes
    assert entered is not None
    assert 1.01 + CONFIRM_S - 1e-9 <= entered <= 1.01 + CONFIRM_S + 0.2
    assert det.moving_fixes == 5
    # a fix that reads motion ends the rest at once
    det.observe_fix(t, np.array([0.0, 0.8, 0.0]), 0.1)
    assert not det.at_rest


def test_detector_holds_rest_through_an_outage_but_does_not_enter_without_fixes():
    det, chol, rng = _detector(4)
    ref = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -9.8])
    det.start_at_rest(0.0, ref, 500)
    for i in range(500):  # 5 s, no fix
        assert det.observe_block((i + 1) * BLOCK_S, ref + chol @ rng.normal(size=6), BLOCK_N)
    det.interrupt(5.0)
    assert not det.at_rest
    for i in range(300):  # 3 s steady, still no fix: rest is not entered
        det.observe_block(5.0 + (i + 1) * BLOCK_S, ref + chol @ rng.normal(size=6), BLOCK_N)
    assert not det.at_rest
    # fixes again: still ones, for CONFIRM_S
    t = 8.0
    for i in range(round((CONFIRM_S + FIX_MAX_AGE_S) / BLOCK_S)):
        t = 8.0 + (i + 1) * BLOCK_S
        if i % 20 == 0:
            det.observe_fix(t, np.zeros(3), 0.1)
        det.observe_block(t, ref + chol @ rng.normal(size=6), BLOCK_N)
    assert det.at_rest


def test_detector_bad_inputs():
    with pytest.raises(ValueError, match="feature_cov"):
        RestDetector(np.eye(5), BLOCK_S, BLOCK_N)
    with pytest.raises(ValueError, match="positive definite"):
        RestDetector(np.zeros((6, 6)), BLOCK_S, BLOCK_N)
    with pytest.raises(ValueError, match="block_s"):
        RestDetector(np.eye(6), 0.0, BLOCK_N)
    det = RestDetector(np.eye(6), BLOCK_S, BLOCK_N)
    with pytest.raises(ValueError, match="ref_features"):
        det.start_at_rest(0.0, np.full(6, np.nan), 10)
    with pytest.raises(ValueError, match="features"):
        det.observe_block(0.0, np.zeros(3), BLOCK_N)
    det.start_at_rest(0.0, np.zeros(6), 10)
    # a NaN block or a fix without a velocity accuracy says nothing
    assert det.observe_block(0.01, np.full(6, np.nan), BLOCK_N)
    det.observe_fix(0.01, np.array([5.0, 0, 0]), 0.0)
    assert det.at_rest and det.unsteady_blocks == 0 and det.moving_fixes == 0


# ------------------------------------------------------------------------ in the pipeline
STOP_AND_GO = (
    "flight.legs=[{ duration_s = 6.0, ramp_s = 1.0, speed_mps = 0.0 },"
    " { duration_s = 5.0, ramp_s = 3.0, speed_mps = 4.0 },"
    " { duration_s = 5.0, ramp_s = 3.0, speed_mps = 0.0 },"
    " { duration_s = 6.0, ramp_s = 1.0, speed_mps = 0.0 }]"
)


def test_zero_rate_updates_fall_only_where_the_vehicle_stands():
    """`static` driven off and stopped again: the updates run in both rests, never in
    motion, and the second rest is found from the data (GPS and array) alone."""
    scn = load_flight("static", [STOP_AND_GO, "rest.rate_sigma_dps=1e-4"])
    sim = simulate_flight(scn, 0)
    t = sim.samples.t_s
    pipe = Pipeline(sim.config, dt_s=float(np.median(np.diff(t))), truth=sim.truth)
    log = []
    pipe.on_epoch = lambda est: log.append((est.t_s, pipe.rest.at_rest))
    pipe.replay(sim.samples, sim.fixes)
    t_ep = np.array([a for a, _ in log])
    at_rest = np.array([b for _, b in log])
    speed = np.linalg.norm(sim.truth.vel_ned_mps, axis=1)
    rate = np.linalg.norm(sim.truth.omega_b_rps, axis=1)
    i_ep = np.searchsorted(t, t_ep - 1e-9)
    # never in motion (the truth at the epoch: no speed, no rate beyond the bench's rocking)
    rocking_rps = np.deg2rad(scn.rocking_rate_dps)
    assert np.all(speed[i_ep[at_rest]] < 1e-3) and np.all(rate[i_ep[at_rest]] < 6 * rocking_rps)
    # the alignment's rest runs on to the drive-off (6 s), found within 0.2 s of it
    first = at_rest & (t_ep < 8.0)
    assert t_ep[first].max() > 5.9
    assert np.all(at_rest[(t_ep > t_ep[0]) & (t_ep < 5.8)])
    # the stop (speed zero from 16 s): rest found again within two seconds
    second = at_rest & (t_ep > 8.0)
    assert second.any() and t_ep[second].min() < 18.0
    assert np.all(at_rest[t_ep > 18.0])
    assert pipe.nf.counters.zero_rate_rejected == 0
    # one update per block that starts at rest (the first from the alignment's)
    n_rest = int(np.count_nonzero(at_rest))
    assert pipe.nf.counters.zero_rate_used == 1 + n_rest - int(at_rest[-1])


def test_two_minutes_at_rest_keep_the_heading_and_tell_the_truth():
    """`static` (at rest, heading known to 5 deg), here 55 s: without the zero-rate
    update the yaw rate's error grew to 0.19 rad/s by 120 s while its sigma stayed at
    0.03, and the joint NEES ran to the hundreds. With it, each run's joint NEES at the
    end is chi-square with 12 dof: their sum over 6 runs is inside chi-square(72)'s
    two-sided 99.9 % bounds."""
    scn = load_flight(
        "static",
        [
            "flight.legs=[{ duration_s = 55.0, ramp_s = 1.0, speed_mps = 0.0 }]",
            "rest.rate_sigma_dps=1e-4",
        ],
    )
    total = 0.0
    for i in range(6):
        sim = simulate_flight(scn, i)
        res = run_filter(sim.samples, sim.fixes, sim.config, truth=sim.truth)
        ne = nees(run_errors(res.estimates, sim.truth), res.estimates.cov_nav)
        total += float(ne["all"][-1])
    lo, hi = chi2.ppf(0.0005, 72), chi2.ppf(0.9995, 72)
    assert lo <= total <= hi, (total, lo, hi)
