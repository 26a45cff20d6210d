"""Flight truth, geodesy, sensor presets and GPS model: checked against exact references."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ngnav.conventions import G0_MPS2
from ngnav.geodesy import LocalTangentPlane, ecef_to_geodetic, geodetic_to_ecef
from ngnav.rotation import (
    dcm_from_quat,
    euler_from_quat,
    quat_conjugate,
    quat_from_euler,
    quat_multiply,
)
from ngnav.sim.flight import FlightPlan, LiftLaw, Profile, Transition, fly
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.sensors import PRESET_NAMES, sensor_preset


def _turning_plan() -> FlightPlan:
    return FlightPlan(
        duration_s=6.0,
        bank=Profile(0.0, (Transition(0.5, 1.0, np.deg2rad(40)), Transition(3.0, 1.5, -0.9))),
        pitch=Profile(0.0, (Transition(1.0, 2.0, np.deg2rad(10)),)),
        speed=Profile(30.0, (Transition(0.0, 4.0, 5.0),)),
        heading0_rad=0.3,
        # angle of attack rising with the turn's load factor and falling as it ends
        aoa=Profile(0.03, (Transition(0.5, 1.0, 0.04), Transition(3.2, 1.2, -0.05))),
    )


def test_rate_derivative_is_the_exact_derivative_of_the_rate():
    # central differences converge at second order to the analytic derivative (away
    # from the ramp ends, where the jerk of a minimum-jerk step jumps by design)
    knots = np.array([0.0, 0.5, 1.0, 1.5, 3.0, 3.2, 4.0, 4.4, 4.5])
    errs = []
    for rate in (200.0, 400.0, 800.0):
        tr = fly(_turning_plan(), rate)
        fd = (tr.omega_b_rps[2:] - tr.omega_b_rps[:-2]) * rate / 2
        t = tr.t_s[1:-1]
        smooth = np.min(np.abs(t[:, None] - knots), axis=1) > 0.05
        errs.append(np.abs(fd - tr.omega_dot_b_rps2[1:-1])[smooth].max())
    assert errs[1] < errs[0] / 3.5 and errs[2] < errs[1] / 3.5


def _lift_plan() -> FlightPlan:
    """From the runway: take-off run, rotation, a pull-up into a climbing banked turn."""
    return FlightPlan(
        duration_s=14.0,
        bank=Profile(0.0, (Transition(8.0, 1.5, np.deg2rad(35)),)),
        pitch=Profile(0.0, (Transition(5.0, 2.0, np.deg2rad(10)), Transition(10.0, 2.5, -0.1))),
        speed=Profile(0.0, (Transition(0.0, 6.0, 22.0), Transition(9.0, 3.0, 4.0))),
        heading0_rad=-0.4,
        lift=LiftLaw(np.deg2rad(-1.0), 2.0, 18.0),
    )


def test_lift_law_flight_is_exact():
    """The lift law's angle of attack is what the truth's own specific force asks for,
    and its rate derivative is the exact derivative of its rate (second-order
    convergence of central differences, away from the ramp ends)."""
    plan = _lift_plan()
    tr = fly(plan, 1000.0)
    c_nb = dcm_from_quat(tr.q_nb)
    v_b = np.einsum("tji,tj->ti", c_nb, tr.vel_ned_mps)
    speed = np.linalg.norm(tr.vel_ned_mps, axis=1)
    flying = speed > 18.0
    alpha = np.arctan2(v_b[:, 2], v_b[:, 0])
    # wind-frame normal load from the body's specific force: n_w = sin(a) f_x - cos(a) f_z
    n_w = np.sin(alpha) * tr.f_b_mps2[:, 0] - np.cos(alpha) * tr.f_b_mps2[:, 2]
    law = np.deg2rad(-1.0) + 2.0 * n_w / np.maximum(speed, 1.0) ** 2
    np.testing.assert_allclose(alpha[flying], law[flying], rtol=0, atol=1e-12)
    # the law is exercised: about 2.5 deg at lift-off, less as the push-over unloads the wing
    assert np.ptp(np.rad2deg(alpha[flying])) > 1.0 and np.rad2deg(alpha[flying]).min() > 0.0
    rest = speed < 0.8 * 18.0
    assert np.abs(alpha[rest & (speed > 1.0)]).max() < 1e-12  # on its wheels: none
    # ramp ends, and where the speed crosses the ends of the lift-off and taxi blends
    t_fine = np.linspace(0.0, plan.duration_s, 140_001)
    v_fine = plan.speed.evaluate(t_fine)[0]
    crossings = [t_fine[np.argmax(v_fine >= v)] for v in (1.0, 2.0, 0.8 * 18.0, 18.0)]
    knots = np.array([0.0, 5.0, 6.0, 7.0, 8.0, 9.0, 9.5, 10.0, 12.0, 12.5, *crossings])
    errs = []
    for rate in (200.0, 400.0, 800.0):
        tr = fly(plan, rate)
        fd = (tr.omega_b_rps[2:] - tr.omega_b_rps[:-2]) * rate / 2
        t = tr.t_s[1:-1]
        smooth = np.min(np.abs(t[:, None] - knots), axis=1) > 0.05
        errs.append(np.abs(fd - tr.omega_dot_b_rps2[1:-1])[smooth].max())
    assert errs[1] < errs[0] / 3.5 and errs[2] < errs[1] / 3.5
    dq = (tr.q_nb[2:] - tr.q_nb[:-2]) * 400.0
    w = 2 * quat_multiply(quat_conjugate(tr.q_nb[1:-1]), dq)[:, 1:]
    assert np.abs(w - tr.omega_b_rps[1:-1]).max() < 1e-4
    with pytest.raises(ValueError, match="not both"):
        dataclasses.replace(plan, aoa=Profile(0.05))


def test_sampled_rate_derivative_integrates_to_the_rate_across_ramp_ends():
    """The trapezoid of the sampled rate derivative converges to the rate at second
    order even where ramps start and end on the sample grid. The lift law puts the
    pitch profile's jerk, which jumps at a ramp's ends, into the pitch acceleration;
    sampled one-sided there, the trapezoid misses the rate by half a sample interval
    times each jump (first order, the same sign in every run)."""
    plan = FlightPlan(
        duration_s=6.0,
        bank=Profile(0.0, (Transition(0.5, 1.0, np.deg2rad(50)), Transition(2.0, 1.0, -0.87))),
        pitch=Profile(0.0, (Transition(1.0, 1.0, np.deg2rad(8)), Transition(3.0, 0.5, -0.14))),
        speed=Profile(60.0, (Transition(4.0, 1.5, 10.0),)),
        heading0_rad=0.2,
        lift=LiftLaw(np.deg2rad(-1.5), 18.0, 30.0),
    )
    jumps = np.array([1.0, 2.0, 3.0, 3.5])  # the pitch ramps' ends, on every grid below
    errs = []
    for rate in (400.0, 800.0, 1600.0):
        tr = fly(plan, rate)
        wd = tr.omega_dot_b_rps2
        trapezoid = np.cumsum((wd[1:] + wd[:-1]) / (2.0 * rate), axis=0)
        e = tr.omega_b_rps[1:] - tr.omega_b_rps[0] - trapezoid
        # beside a jump the trapezoid's own error is first order for one sample
        away = np.min(np.abs(tr.t_s[1:, None] - jumps), axis=1) > 1.5 / rate
        errs.append(np.abs(e[away]).max())
    assert errs[1] < errs[0] / 3.5 and errs[2] < errs[1] / 3.5


def _spinning_plan(spin: Profile) -> FlightPlan:
    return dataclasses.replace(_turning_plan(), spin_rate=spin)


def test_a_spinning_body_is_the_flight_rolled_by_the_spin_angle():
    """The spin rolls the body about its x axis by the spin rate's exact integral (a
    minimum-jerk rate ramp integrates to ``d T (2.5 u^4 - 3 u^5 + u^6)``), and nothing
    else: the path is the same, the force and the flight's own rate are seen rolled."""
    delta, start, dur = np.deg2rad(720.0), 0.7, 2.0
    spun = fly(_spinning_plan(Profile(0.0, (Transition(start, dur, delta),))), 500.0)
    flat = fly(_turning_plan(), 500.0)
    u = np.clip((flat.t_s - start) / dur, 0.0, 1.0)
    angle = delta * dur * (2.5 * u**4 - 3 * u**5 + u**6)
    angle += delta * np.maximum(flat.t_s - start - dur, 0.0)
    q_x = np.stack([np.cos(angle / 2), np.sin(angle / 2), 0 * angle, 0 * angle], -1)
    assert np.allclose(spun.q_nb, quat_multiply(flat.q_nb, q_x), atol=1e-12, rtol=0)
    assert np.array_equal(spun.pos_ned_m, flat.pos_ned_m)
    assert np.array_equal(spun.vel_ned_mps, flat.vel_ned_mps)
    c, s_ = np.cos(angle), np.sin(angle)
    f = flat.f_b_mps2
    rolled = np.stack([f[:, 0], c * f[:, 1] + s_ * f[:, 2], -s_ * f[:, 1] + c * f[:, 2]], -1)
    assert np.allclose(spun.f_b_mps2, rolled, atol=1e-10, rtol=0)  # angles up to 60 rad
    assert np.rad2deg(spun.omega_b_rps[-1, 0] - flat.omega_b_rps[-1, 0]) == pytest.approx(
        720.0, abs=1e-9
    )


def test_a_spinning_body_rate_derivative_and_attitude_rate_are_exact():
    # central differences converge at second order to the analytic rate derivative, and
    # the attitude's derivative gives the rate, at 720 deg/s of spin
    plan = _spinning_plan(Profile(0.0, (Transition(0.7, 2.0, np.deg2rad(720.0)),)))
    knots = np.array([0.0, 0.5, 0.7, 1.0, 1.5, 2.7, 3.0, 3.2, 4.0, 4.4, 4.5])
    errs, att_errs = [], []
    for rate in (400.0, 800.0, 1600.0):
        tr = fly(plan, rate)
        fd = (tr.omega_b_rps[2:] - tr.omega_b_rps[:-2]) * rate / 2
        smooth = np.min(np.abs(tr.t_s[1:-1, None] - knots), axis=1) > 0.05
        errs.append(np.abs(fd - tr.omega_dot_b_rps2[1:-1])[smooth].max())
        dq = (tr.q_nb[2:] - tr.q_nb[:-2]) * rate / 2
        w = 2 * quat_multiply(quat_conjugate(tr.q_nb[1:-1]), dq)[:, 1:]
        att_errs.append(np.abs(w - tr.omega_b_rps[1:-1]).max())
    assert errs[1] < errs[0] / 3.5 and errs[2] < errs[1] / 3.5
    assert att_errs[1] < att_errs[0] / 3.5 and att_errs[2] < att_errs[1] / 3.5


def test_rate_is_the_rate_of_the_attitude():
    tr = fly(_turning_plan(), 1000.0)
    # omega_b = 2 * vec(conj(q) * dq/dt), dq/dt by central differences
    dq = (tr.q_nb[2:] - tr.q_nb[:-2]) * 500.0
    w = 2 * quat_multiply(quat_conjugate(tr.q_nb[1:-1]), dq)[:, 1:]
    assert np.abs(w - tr.omega_b_rps[1:-1]).max() < 1e-5


def test_specific_force_is_acceleration_minus_gravity():
    tr = fly(_turning_plan(), 1000.0)
    acc_n = (tr.vel_ned_mps[2:] - tr.vel_ned_mps[:-2]) * 500.0
    f_n = np.einsum("tij,tj->ti", dcm_from_quat(tr.q_nb[1:-1]), tr.f_b_mps2[1:-1])
    assert np.abs(f_n + np.array([0.0, 0.0, G0_MPS2]) - acc_n).max() < 1e-4
    pos_fd = (tr.pos_ned_m[2:] - tr.pos_ned_m[:-2]) * 500.0
    # central-difference truncation h^2/6 |d2v/dt2| is a few 1e-6 m/s at 1 kHz here
    assert np.abs(pos_fd - tr.vel_ned_mps[1:-1]).max() < 1e-5


def test_body_sees_its_velocity_at_the_angle_of_attack():
    plan = _turning_plan()
    tr = fly(plan, 500.0)
    v_b = np.einsum("tji,tj->ti", dcm_from_quat(tr.q_nb), tr.vel_ned_mps)
    alpha = plan.aoa.evaluate(tr.t_s)[0]
    assert np.abs(v_b[:, 1]).max() < 1e-12  # no sideslip
    assert np.allclose(np.arctan2(v_b[:, 2], v_b[:, 0]), alpha, atol=1e-12, rtol=0)
    # the same flight at zero angle of attack has the same path
    flat = fly(dataclasses.replace(plan, aoa=Profile(0.0)), 500.0)
    assert np.array_equal(flat.pos_ned_m, tr.pos_ned_m)
    assert np.array_equal(flat.vel_ned_mps, tr.vel_ned_mps)


def test_angle_of_attack_tilts_the_lift_into_the_body():
    """In a steady level turn at angle of attack alpha the specific force is the
    wind frame's ``[0, 0, -g / cos(bank)]`` seen from the body: ``x = +g sin(alpha) /
    cos(bank)`` (lift leans forward in body axes), ``z = -g cos(alpha) / cos(bank)``."""
    bank, alpha = np.deg2rad(30.0), np.deg2rad(4.0)
    plan = FlightPlan(
        8.0,
        Profile(0.0, (Transition(1.0, 2.0, bank),)),
        Profile(0.0),
        Profile(25.0),
        aoa=Profile(alpha),
    )
    tr = fly(plan, 200.0)
    steady = tr.t_s > 3.5
    n = G0_MPS2 / np.cos(bank)
    assert np.allclose(tr.f_b_mps2[steady, 0], n * np.sin(alpha), rtol=1e-9)
    assert np.abs(tr.f_b_mps2[steady, 1]).max() < 1e-9
    assert np.allclose(tr.f_b_mps2[steady, 2], -n * np.cos(alpha), rtol=1e-9)


def test_coordinated_turn_has_no_side_force():
    plan = FlightPlan(
        8.0, Profile(0.0, (Transition(1.0, 2.0, np.deg2rad(30)),)), Profile(0.0), Profile(25.0)
    )
    tr = fly(plan, 200.0)
    steady = tr.t_s > 3.5
    assert np.abs(tr.f_b_mps2[steady, 1]).max() < 1e-9
    # load factor 1/cos(bank)
    assert np.allclose(-tr.f_b_mps2[steady, 2], G0_MPS2 / np.cos(np.deg2rad(30)), rtol=1e-9)


def test_euler_round_trip():
    q = quat_from_euler(0.3, -0.2, 2.5)
    assert np.allclose(euler_from_quat(q), [0.3, -0.2, 2.5])


def test_shipped_flights_meet_their_descriptions():
    uav = load_flight("uav-survey")
    assert uav.plan().duration_s >= 600.0 and uav.gps.outage_s == 30.0
    tr = fly(load_flight("tactical").plan(), 200.0)
    assert 50.0 <= tr.t_s[-1] <= 70.0
    assert np.rad2deg(np.abs(tr.omega_b_rps).max()) <= 120.0
    assert np.abs(tr.f_b_mps2).max() <= 2.5 * G0_MPS2
    assert np.rad2deg(np.abs(tr.omega_b_rps[:, 0]).max()) > 100.0  # at the paper's limits
    assert np.abs(tr.f_b_mps2[:, 2]).max() > 2.0 * G0_MPS2
    proj = load_flight("projectile")
    tr = fly(proj.plan(), 1000.0)
    assert np.rad2deg(tr.omega_b_rps[:, 0].max()) == pytest.approx(720.0)  # several hundred
    assert 20.0 * G0_MPS2 < np.abs(tr.f_b_mps2).max() < proj.sensor.spec().range_g * G0_MPS2
    assert tr.t_s[-1] == pytest.approx(40.0)
    # multirotor: hovers (no motion at all), yaws in place, and loses GPS while hovering
    mr = load_flight("multirotor")
    tr = fly(mr.plan(), 200.0)
    speed = np.linalg.norm(tr.vel_ned_mps, axis=1)
    still = speed < 1e-9
    assert np.all(np.abs(tr.omega_b_rps[still & (tr.t_s < 15.0)]) < 1e-12)
    assert np.rad2deg(np.abs(tr.omega_b_rps[still, 2]).max()) == pytest.approx(30.0)
    out = (tr.t_s >= mr.gps.outage_start_s) & (tr.t_s <= mr.gps.outage_start_s + mr.gps.outage_s)
    assert mr.gps.outage_s >= 20.0 and np.all(still[out])
    # ground vehicle: stops, and turns flat (no roll: the turn's load is sideways)
    gv = load_flight("ground")
    tr = fly(gv.plan(), 200.0)
    speed = np.linalg.norm(tr.vel_ned_mps, axis=1)
    stops = np.flatnonzero(np.diff((speed < 1e-6).astype(int)) == 1)
    assert len(stops) >= 2  # stops after driving (the parking at the start not counted)
    assert np.abs(np.rad2deg(tr.omega_b_rps[:, 0])).max() < 1e-9
    assert np.abs(tr.f_b_mps2[:, 1]).max() > 2.0


@settings(max_examples=50, deadline=None)
@given(lat=st.floats(-89.0, 89.0), lon=st.floats(-180.0, 180.0), alt=st.floats(-500.0, 20000.0))
def test_geodetic_ecef_round_trip(lat, lon, alt):
    la, lo, h = ecef_to_geodetic(geodetic_to_ecef(lat, lon, alt))
    assert abs(la - lat) < 1e-9 and abs(h - alt) < 1e-4
    assert abs((lo - lon + 180) % 360 - 180) < 1e-9


def test_tangent_plane_known_values():
    ltp = LocalTangentPlane(0.0, 0.0, 0.0)
    # one arc-minute of longitude on the equator is a*pi/(180*60) east
    ned = ltp.to_ned(0.0, 1.0 / 60.0, 0.0)
    assert abs(ned[1] - 6378137.0 * np.pi / 10800) < 1e-2 and abs(ned[0]) < 1e-6
    assert np.allclose(ltp.to_ned(0.0, 0.0, 100.0), [0, 0, -100.0], atol=1e-6)
    lat, lon, alt = ltp.to_geodetic(np.array([1000.0, -2000.0, 50.0]))
    assert np.allclose(ltp.to_ned(lat, lon, alt), [1000.0, -2000.0, 50.0], atol=1e-6)


def test_presets_cite_sources_and_noise_scales_with_rate():
    for name in PRESET_NAMES:
        p = sensor_preset(name)
        assert len(p.sources) >= 3
        assert p.sample_sigma_mps2(400.0) > p.sample_sigma_mps2(100.0)
    with pytest.raises(ValueError, match="unknown sensor preset 'mems-x'"):
        sensor_preset("mems-x")


def test_sensor_simulation_statistics():
    spec = sensor_preset("mems-tactical")
    rng = np.random.default_rng(3)
    a = np.zeros((20000, 9))
    out, sat, bias = spec.simulate(a, 1000.0, np.zeros(9), rng)
    resid = out - bias
    sig = spec.sample_sigma_mps2(1000.0)
    # sample variance of 180000 values: within 2 % (about 6 standard errors)
    assert abs(resid.std() / sig - 1) < 0.02
    assert not sat.any()
    big, sat2, _ = spec.simulate(np.full((10, 9), 10 * G0_MPS2), 1000.0, np.zeros(9), rng)
    assert sat2.all() and np.allclose(np.abs(big), spec.range_g * G0_MPS2, atol=1e-3)


def test_a_turntable_truth_is_a_whole_body_truth():
    """The indexing head's truth (one record type for every simulation): the origin's
    position and velocity circle the fixed pivot, and differentiate into each other
    and into the specific force plus gravity, as any body's must."""
    from ngnav.conventions import gravity_n_mps2
    from ngnav.rotation import dcm_from_quat
    from ngnav.sim.turntable import fixed_axis_turn

    pivot = np.array([0.03, -0.05, 0.02])
    tr = fixed_axis_turn(
        np.deg2rad(90.0),
        duration_s=2.0,
        rest_before_s=0.5,
        rest_after_s=0.5,
        rate_hz=2000.0,
        axis_b=np.array([0.0, 0.0, 1.0]),
        pivot_b_m=pivot,
    )
    np.testing.assert_allclose(np.linalg.norm(tr.pos_ned_m, axis=1), np.linalg.norm(pivot))
    dt = 1 / 2000.0
    vel_fd = (tr.pos_ned_m[2:] - tr.pos_ned_m[:-2]) / (2 * dt)
    np.testing.assert_allclose(vel_fd, tr.vel_ned_mps[1:-1], atol=1e-6)
    acc_fd = (tr.vel_ned_mps[2:] - tr.vel_ned_mps[:-2]) / (2 * dt)
    c = dcm_from_quat(tr.q_nb[1:-1])
    f_n = np.einsum("tij,tj->ti", c, tr.f_b_mps2[1:-1])
    # the central difference is second order except where the minimum-jerk step's jerk
    # jumps (its start and end: 60 angle / duration^3 times the arm), off by dt * jump / 4
    jump = np.deg2rad(90.0) * 60.0 / 2.0**3 * np.linalg.norm(pivot)
    np.testing.assert_allclose(acc_fd, f_n + gravity_n_mps2(), atol=dt * jump / 4 + 1e-6)
