"""A vehicle whose heading is its GPS course measures it again when position and velocity go
onto a fix after a coast (``filters.step``, ``initial.heading_source = "gps"``)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from filters.pipeline import run_filter
from filters.state import ATT
from ngnav.rotation import quat_conjugate, quat_multiply, quat_to_rotvec
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from tests.helpers import level_filter

HEADING = ATT.start + 2


@pytest.mark.parametrize("roll_deg, pitch_deg, yaw_deg", [(0, 0, 30), (10, 25, -140), (-5, 60, 95)])
def test_heading_jacobian_is_the_yaws_derivative(roll_deg, pitch_deg, yaw_deg):
    """The heading model's Jacobian against central differences of the ZYX yaw of
    ``exp([dtheta]x) C`` (scipy's rotations as the reference)."""
    nf, _, _ = level_filter()
    r = Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True)
    x, y, z, w = r.as_quat()
    nf.q = np.array([w, x, y, z])
    yaw, h = nf.heading_model()
    assert yaw == pytest.approx(np.deg2rad(yaw_deg), abs=1e-12)
    eps = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        up = (Rotation.from_rotvec(d) * r).as_euler("ZYX")[0]
        down = (Rotation.from_rotvec(-d) * r).as_euler("ZYX")[0]
        assert h[ATT.start + i] == pytest.approx((up - down) / (2 * eps), abs=1e-8)
    assert np.count_nonzero(h) <= 3


def _after_the_tunnel(sets: list[str]):
    """`ground` run 0 (a 15 s outage from 120 s): the run's counts, and at the first epoch
    after the first fix past the outage the heading's error and 1-sigma (rad) and the
    course's own noise ``atan(sigma_v / speed)`` that fix gives."""
    sim = simulate_flight(load_flight("ground", sets), 0)
    res = run_filter(sim.samples, sim.fixes, sim.config)
    fixes, est = sim.fixes, res.estimates
    k = int(np.flatnonzero(fixes.t_s > 135.0)[0])
    speed = float(np.hypot(*fixes.vel_ned_mps[k, :2]))
    course_sigma = float(np.arctan2(fixes.vel_acc_mps[k], speed))
    e = int(np.searchsorted(est.t_s, fixes.t_s[k]))
    j = int(np.searchsorted(sim.truth.t_s, est.t_s[e]))
    dq = quat_multiply(sim.truth.q_nb[j], quat_conjugate(est.q_nb[e]))
    err = float(quat_to_rotvec(dq)[2])
    return res.counts, err, float(np.sqrt(est.cov_nav[e, HEADING, HEADING])), course_sigma


def test_the_course_measures_the_heading_again_after_a_coast():
    counts, err, sigma, course_sigma = _after_the_tunnel([])
    assert counts["gps resets after an outage"] == 1
    assert counts["heading updates from the GPS course"] == 1
    assert counts["heading resets to the GPS course"] == 0
    # the coast's heading is tens of times less sure than the course: the update leaves
    # the course's sigma, which the yaw rate's grows a little by the next epoch
    assert 0.99 * course_sigma < sigma < 1.25 * course_sigma
    assert abs(err) < 3.0 * sigma
    # a heading from the configuration keeps the coast's, several times less sure
    counts, _, sigma_cfg, _ = _after_the_tunnel(['initial.heading_source="config"'])
    assert counts["heading updates from the GPS course"] == 0
    assert sigma_cfg > 5.0 * course_sigma


@pytest.mark.parametrize("sigma_deg", [4.0, 15.0])
def test_the_parked_heading_keeps_its_configured_sigma_until_the_course(sigma_deg):
    """Until the first course the heading is the configured one with the configured sigma
    (the simulation draws the configured heading's error with that sigma); parked, the
    rest's small forces tell it little."""
    sim = simulate_flight(load_flight("ground", [f"initial.heading_sigma_deg={sigma_deg}"]), 0)
    res = run_filter(sim.samples, sim.fixes, sim.config)
    est = res.estimates
    sd = np.rad2deg(np.sqrt(est.cov_nav[:, HEADING, HEADING]))
    parked = est.t_s < 10.0  # the car drives off at 10 s
    assert sd[0] == pytest.approx(sigma_deg, rel=1e-6)
    assert sd[parked] == pytest.approx(sigma_deg, rel=1e-2)
    assert res.counts["heading resets to the GPS course"] == 0
    assert sd[-1] < 2.0  # the course and the turns have told it since


def test_a_start_again_takes_the_heading_from_the_course():
    """A vehicle whose heading is its course starts again on the course (its own noise at
    three sigmas), not on the configured heading with 60 deg: `ground` run 0, its track lost
    at 60 s on the straight after the first turn (the truth heads 180 deg, the
    configuration says 90)."""
    scn = load_flight("ground", ["faults.lose_track_at_s=[60.0]"])
    sim = simulate_flight(scn, 0)
    res = run_filter(sim.samples, sim.fixes, sim.config, lose_track_at_s=scn.lose_track_at_s)
    (loss,) = res.track_losses
    est = res.estimates
    e = int(np.searchsorted(est.t_s, loss.restarted_s - 1e-9))
    j = int(np.searchsorted(sim.truth.t_s, est.t_s[e]))
    dq = quat_multiply(sim.truth.q_nb[j], quat_conjugate(est.q_nb[e]))
    err = float(quat_to_rotvec(dq)[2])
    sigma = float(np.sqrt(est.cov_nav[e, HEADING, HEADING]))
    assert sigma < np.deg2rad(3.0)
    assert abs(err) < 3.0 * sigma
    first_valid = est.t_s[(est.t_s >= loss.restarted_s - 1e-9) & est.valid][0]
    assert first_valid - loss.lost_at_s <= 10.0
