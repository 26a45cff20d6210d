"""MAVLink estimate outputs: covariance mapping, identity checks, rates, and the stream pipeline."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from filters.pipeline import Pipeline, run_filter
from ngnav.rotation import dcm_from_quat, euler_from_quat, quat_from_rotvec, quat_multiply
from telemetry import ngnav_mavlink as mavlink
from telemetry.outputs import OutputSettings, odometry_covariances, parse_rates, upper_triangle


def _state(q: np.ndarray, v: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """(x, y, z, roll, pitch, yaw, vx_b, vy_b, vz_b, w) of a state perturbed by error ``dx``."""
    qt = quat_multiply(quat_from_rotvec(dx[6:9]), q)
    vt = v + dx[3:6]
    return np.concatenate([dx[0:3], euler_from_quat(qt), dcm_from_quat(qt).T @ vt, dx[9:12]])


@settings(max_examples=30, deadline=None)
@given(
    rpy=st.tuples(st.floats(-3.0, 3.0), st.floats(-1.3, 1.3), st.floats(-3.0, 3.0)),
    v=st.tuples(*[st.floats(-80, 80)] * 3),
)
def test_odometry_covariances_are_the_first_order_map_of_the_error_state(rpy, v):
    # the exact reference: a numerical Jacobian of the state the error describes
    from ngnav.rotation import quat_from_euler

    q = quat_from_euler(*rpy)
    vel = np.array(v)
    rng = np.random.default_rng(5)
    a = rng.normal(size=(12, 12))
    cov = a @ a.T * 1e-4
    j = np.zeros((12, 12))
    h = 1e-7
    base = _state(q, vel, np.zeros(12))
    for k in range(12):
        dx = np.zeros(12)
        dx[k] = h
        d = _state(q, vel, dx) - base
        d[3:6] = (d[3:6] + np.pi) % (2 * np.pi) - np.pi
        j[:, k] = d / h
    pose, twist = odometry_covariances(q, vel, cov)
    ref = j @ cov @ j.T
    scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref))) + 1e-12
    assert np.max(np.abs(pose - ref[0:6, 0:6]) / scale[0:6, 0:6]) < 1e-4
    assert np.max(np.abs(twist - ref[6:12, 6:12]) / scale[6:12, 6:12]) < 1e-4


def test_upper_triangle_is_row_major_like_mavlink():
    m = np.arange(36.0).reshape(6, 6)
    u = upper_triangle(m)
    assert len(u) == 21
    # first row (6), then the second row from its diagonal (5), ...
    assert u[:6] == [0, 1, 2, 3, 4, 5] and u[6:11] == [7, 8, 9, 10, 11] and u[-1] == 35


def test_output_settings_refuse_what_ground_stations_ignore():
    with pytest.raises(ValueError, match="1-254"):
        OutputSettings(system_id=255)
    with pytest.raises(ValueError, match="INVALID"):
        OutputSettings(autopilot=mavlink.MAV_AUTOPILOT_INVALID)
    with pytest.raises(ValueError, match="unknown output stream 'attitud'"):
        OutputSettings(rates_hz={"attitud": 5})
    with pytest.raises(ValueError, match="STREAM=HZ"):
        parse_rates(["odometry:5"])
    s = OutputSettings(rates_hz=parse_rates(["odometry=10", "attitude=0"]))
    assert s.rates_hz["odometry"] == 10 and s.rates_hz["attitude"] == 0
    assert s.rates_hz["heartbeat"] == 1


@pytest.fixture(scope="module")
def tactical_run():
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    scn = load_flight("tactical", ["run.rate_hz=200"])
    return simulate_flight(scn, 0)


def test_stream_pipeline_in_any_chunks_equals_the_batch_run(tactical_run):
    """Samples in 7-sample chunks, fixes at their arrival: the batch run's estimates."""
    sim = tactical_run
    ref = run_filter(sim.samples, sim.fixes, sim.config)
    t, acc, fx = sim.samples.t_s, sim.samples.accel_mps2, sim.fixes
    dt = float(np.median(np.diff(t)))
    pipe = Pipeline(sim.config, dt_s=dt)
    arrival = fx.t_s + fx.latency_s
    m = 0

    def fixes_until(t_arrival: float) -> None:
        nonlocal m
        while m < len(fx) and arrival[m] <= t_arrival:
            pipe.push_fix(
                fx.t_s[m],
                fx.lat_deg[m],
                fx.lon_deg[m],
                fx.alt_m[m],
                fx.vel_ned_mps[m],
                fx.h_acc_m[m],
                fx.v_acc_m[m],
                fx.vel_acc_mps[m],
            )
            m += 1

    for i in range(0, t.shape[0], 7):
        pipe.push_samples(t[i : i + 7], acc[i : i + 7])
        fixes_until(t[min(i + 6, t.shape[0] - 1)])
    fixes_until(np.inf)
    pipe.finish()
    got = pipe.result()
    assert got.counts["gps fixes later than the fusion lag"] == 0
    assert got.estimates.t_s.shape == ref.estimates.t_s.shape
    np.testing.assert_allclose(got.estimates.pos_ned_m, ref.estimates.pos_ned_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.estimates.q_nb, ref.estimates.q_nb, rtol=0, atol=1e-12)


def test_fix_later_than_the_fusion_lag_is_fused_late_and_counted(tactical_run):
    """A fix arriving 0.5 s late (lag 0.1 s): used at the next block, shifted by v dt."""
    from dataclasses import replace

    sim = tactical_run
    fx = sim.fixes
    late = np.zeros(len(fx))
    late[100:110] = 0.5
    fx2 = replace(fx, latency_s=fx.latency_s + late)
    res = run_filter(sim.samples, fx2, sim.config)
    ref = run_filter(sim.samples, fx, sim.config)
    assert res.counts["gps fixes later than the fusion lag"] == 10
    assert res.counts["gps fixes used"] == ref.counts["gps fixes used"]
    # the v dt shift is first order (0.45 s in a 2 g turn): the estimate moves off the
    # on-time run's, but its error stays inside 3 sigma of the truth
    from filters.evaluate import run_errors

    err = run_errors(res.estimates, sim.truth).pos_ned_m
    sig = np.sqrt(np.einsum("eii->ei", res.estimates.cov_nav[:, 0:3, 0:3]))
    window = (res.estimates.t_s > 9.0) & (res.estimates.t_s < 16.0)
    assert np.all(np.abs(err[window]) < 3 * sig[window])
