"""A lost track, recovered (filters.recovery): the start again's attitude, its estimates
and what the outputs say about them, on the real filter."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from filters.evaluate import run_errors
from filters.output import read_estimates_csv, write_estimates_csv
from filters.pipeline import FIX_OUTCOMES, GATE_PROBABILITY, Pipeline
from filters.recovery import RESTART_MIN_INTERVAL_S, triad
from ngnav.errors import CovarianceError
from ngnav.geodesy import LocalTangentPlane
from ngnav.rotation import dcm_from_quat, quat_from_euler
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from telemetry import ngnav_mavlink as mavlink
from telemetry.outputs import EstimateEncoder, OutputSettings

LOSS_S = 25.0


@pytest.mark.parametrize("seed", range(5))
def test_triad_puts_the_force_on_its_direction_and_levels_by_the_heading(seed):
    """At rest (force straight up) the force and the heading fix any attitude exactly;
    in flight the force's direction is matched exactly whatever the heading."""
    rng = np.random.default_rng(seed)
    roll, pitch, yaw = rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(-3, 3)
    c = dcm_from_quat(quat_from_euler(roll, pitch, yaw))
    f_n = np.array([0.0, 0.0, -9.80665])
    np.testing.assert_allclose(triad(c.T @ f_n, f_n, yaw), c, atol=1e-12)
    f_n = rng.normal(0.0, 5.0, 3) + np.array([0.0, 0.0, -9.8])
    got = triad(c.T @ f_n, f_n, yaw + rng.normal(0.0, 0.3))
    np.testing.assert_allclose(got @ c.T @ f_n, f_n, atol=1e-10)
    np.testing.assert_allclose(got.T @ got, np.eye(3), atol=1e-12)


@pytest.fixture(scope="module")
def lost_run():
    """tactical run 0 (200 Hz array) told its track is lost at 25 s, with every epoch's
    ESTIMATOR_STATUS from the real encoder."""
    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    cfg = sim.config
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    settings = OutputSettings(rates_hz={"estimator_status": 1000.0})
    enc = EstimateEncoder(settings, ltp, GATE_PROBABILITY, 5.0, "gm11")
    flags: list[tuple[float, bool, int]] = []

    def on_epoch(est):
        for msg in enc.epoch(est):
            if msg.get_type() == "ESTIMATOR_STATUS":
                flags.append((est.t_s, est.valid, msg.flags))

    pipe = Pipeline(cfg, on_epoch=on_epoch, truth=sim.truth, lose_track_at_s=(LOSS_S,))
    f = sim.fixes
    arrival = f.t_s + f.latency_s
    j, s = 0, sim.samples
    for i in range(0, s.t_s.shape[0], 20):
        while j < len(f) and arrival[j] <= s.t_s[i]:
            pipe.push_fix(
                f.t_s[j], f.lat_deg[j], f.lon_deg[j], f.alt_m[j], f.vel_ned_mps[j],
                f.h_acc_m[j], f.v_acc_m[j], f.vel_acc_mps[j],
            )  # fmt: skip
            j += 1
        pipe.push_samples(s.t_s[i : i + 20], s.accel_mps2[i : i + 20])
    while j < len(f):
        pipe.push_fix(
            f.t_s[j], f.lat_deg[j], f.lon_deg[j], f.alt_m[j], f.vel_ned_mps[j],
            f.h_acc_m[j], f.v_acc_m[j], f.vel_acc_mps[j],
        )  # fmt: skip
        j += 1
    pipe.finish()
    return sim, pipe.result(), flags


def test_a_lost_track_starts_again_at_the_next_fixes_and_is_valid_within_10_s(lost_run):
    sim, res, _ = lost_run
    (loss,) = res.track_losses
    assert loss.reason == "forced" and LOSS_S - 0.02 <= loss.lost_at_s <= LOSS_S
    # two fixes at 10 Hz give the acceleration the tilt needs
    assert 0.0 < loss.restarted_s - loss.lost_at_s <= 0.25
    assert res.counts["track losses (filter started again)"] == 1
    est = res.estimates
    gap = (est.t_s > loss.lost_at_s) & (est.t_s < loss.restarted_s - 1e-9)
    assert np.any(gap) and np.all(np.isnan(est.pos_ned_m[gap])) and not np.any(est.valid[gap])
    after = est.t_s >= loss.restarted_s - 1e-9
    first_valid = est.t_s[after & est.valid][0]
    assert first_valid - loss.lost_at_s <= 10.0
    assert np.all(est.valid[est.t_s < loss.lost_at_s])
    assert np.all(est.valid[est.t_s >= first_valid])
    # every fix pushed ends in one outcome, the two that started it again included
    assert sum(res.counts[o] for o in FIX_OUTCOMES) == len(sim.fixes)
    assert res.counts["gps fixes while the track was lost"] >= 2


def test_after_a_start_again_the_errors_stay_inside_their_sigmas(lost_run):
    """From 20 s after the loss every navigation error is inside 5 sigma (fixed seed)."""
    sim, res, _ = lost_run
    est = res.estimates
    late = est.t_s >= LOSS_S + 20.0
    errs = run_errors(est, sim.truth).stacked()[late]
    sig = np.sqrt(np.einsum("eii->ei", est.cov_nav[late]))
    assert np.all(np.abs(errs) <= 5.0 * sig)
    # and the start again did something: the attitude's sigma came down by 10x or more
    att_sig = np.sqrt(est.cov_nav[:, 6, 6])
    restart = np.argmax(est.t_s >= res.track_losses[0].restarted_s - 1e-9)
    assert att_sig[restart] > 10.0 * att_sig[late].max()


def test_estimator_status_vouches_for_nothing_until_valid_again(lost_run):
    _, _, flags = lost_run
    seen = {valid for _, valid, _ in flags}
    assert seen == {True, False}
    for _, valid, fl in flags:
        assert bool(fl & mavlink.ESTIMATOR_ATTITUDE) == valid
        if not valid:
            assert fl == 0


def test_estimates_csv_keeps_the_lost_epochs_empty_and_not_valid(lost_run, tmp_path):
    sim, res, _ = lost_run
    write_estimates_csv(tmp_path / "e.csv", res.estimates, sim.config)
    back = read_estimates_csv(tmp_path / "e.csv")
    np.testing.assert_array_equal(back.valid, res.estimates.valid)
    np.testing.assert_array_equal(np.isnan(back.pos_ned_m), np.isnan(res.estimates.pos_ned_m))


def test_a_loss_soon_after_a_start_again_stops_the_run():
    """Needing a start again within RESTART_MIN_INTERVAL_S of the last is a divergence:
    the run stops with its estimates so far."""
    from filters.pipeline import run_filter

    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    with pytest.raises(CovarianceError, match="lost again") as info:
        run_filter(
            sim.samples,
            sim.fixes,
            sim.config,
            lose_track_at_s=(LOSS_S, LOSS_S + 0.5 * RESTART_MIN_INTERVAL_S),
        )
    assert info.value.partial is not None
    assert len(info.value.partial.track_losses) == 1


def test_a_start_again_with_a_channel_excluded_carries_on():
    """A track lost after a dead channel was excluded starts again on the reduced solve:
    the feature no remaining channel solves keeps a bias prior (its zero row had left the
    start's covariance singular and the run stopped)."""
    from filters.pipeline import run_filter

    scn = load_flight(
        "tactical",
        ["run.rate_hz=200", 'faults.inject=[{channel=6, kind="dead", start_s=15.0}]'],
    )
    sim = simulate_flight(scn, 0)
    res = run_filter(sim.samples, sim.fixes, sim.config, lose_track_at_s=(LOSS_S,))
    assert [ev.channels for ev in res.faults] == [(6,)]
    (loss,) = res.track_losses
    est = res.estimates
    assert est.t_s[-1] == pytest.approx(sim.truth.t_s[-1], abs=0.02)  # ran to the end
    first_valid = est.t_s[(est.t_s >= loss.restarted_s - 1e-9) & est.valid][0]
    assert first_valid - loss.lost_at_s <= 10.0
    late = est.t_s >= LOSS_S + 20.0
    errs = run_errors(est, sim.truth).stacked()[late]
    sig = np.sqrt(np.einsum("eii->ei", est.cov_nav[late]))
    assert np.all(np.abs(errs) <= 5.0 * sig)


def test_a_heading_lost_in_a_coast_starts_again_on_the_course():
    """``uav-survey`` at ``mems-consumer``, run 9: its 30 s coast ends with the tilt's
    1-sigma 25 deg (under the limit) and the heading's 41 deg. Fused on from there, the
    next fixes pulled the heading to 14 deg off with a 1 deg sigma (heading NEES about
    170 over 345-400 s). A fixed-wing's heading is its course, so the fix finds the track
    lost and the filter starts again on the course: the heading is honest again."""
    from filters.bench import _first_seconds
    from filters.pipeline import run_filter

    sim = simulate_flight(load_flight("uav-survey", ["sensor.preset=mems-consumer"]), 9)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, 400.0)
    res = run_filter(samples, fixes, sim.config)
    (loss,) = res.track_losses
    assert 329.9 < loss.lost_at_s < 331.0 and "heading 1-sigma" in loss.reason
    assert loss.restarted_s - loss.lost_at_s < 1.0
    est = res.estimates
    after = (est.t_s > 345.0) & (est.t_s < 400.0)
    z = run_errors(est, sim.truth).att_ned_rad[after, 2] / np.sqrt(est.cov_nav[after, 8, 8])
    assert np.mean(z * z) < 2.0  # 1 for an honest sigma


def test_a_start_again_keeps_the_biases_and_the_split_of_pitch_and_angle_of_attack():
    """``uav-survey`` at ``mems-consumer``, run 10: its coast ends with the tilt lost (31 deg)
    and the filter starts again at 330.4 s. Started with the biases at their 5 mg prior
    (0.29 deg of tilt), level flight learned the pitch and the zero-lift angle again together
    and they drifted under sigmas that did not follow: over 400-520 s the angle of attack's
    mean z^2 read 2.52 and the attitude's NEES 4.60 (3 dof). The array's biases do not change
    when the track is lost; kept, they read 0.63 and 3.03."""
    from filters.bench import _first_seconds
    from filters.evaluate import truth_aoa_rad, truth_indices
    from filters.pipeline import run_filter

    sim = simulate_flight(load_flight("uav-survey", ["sensor.preset=mems-consumer"]), 10)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, 520.0)
    res = run_filter(samples, fixes, sim.config)
    (loss,) = res.track_losses
    assert 329.9 < loss.lost_at_s < 331.0 and "tilt 1-sigma" in loss.reason
    est = res.estimates
    m = (est.t_s > 400.0) & (est.t_s < 520.0)
    e = truth_aoa_rad(sim.truth, truth_indices(sim.truth, est.t_s[m])) - est.aoa_rad[m]
    assert np.mean((e / est.aoa_sigma_rad[m]) ** 2) < 1.5  # 1 for an honest sigma
    err = run_errors(est, sim.truth).att_ned_rad[m]
    nees = np.einsum(
        "ei,ei->e", err, np.linalg.solve(est.cov_nav[m][:, 6:9, 6:9], err[..., None])[..., 0]
    )
    assert np.mean(nees) < 3.9  # 3 for an honest covariance


def test_a_lost_run_keeps_the_series_a_campaign_averages(lost_run):
    """Epochs, GPS innovations and rate NIS: one entry each as in the same run without the
    loss (NaN where there was none), so Monte Carlo runs with and without losses average."""
    from filters.pipeline import run_filter

    sim, res, _ = lost_run
    clean = run_filter(sim.samples, sim.fixes, sim.config)
    for got, want in (
        (res.estimates.t_s, clean.estimates.t_s),
        (res.innovations.t_s, clean.innovations.t_s),
        (res.rate_nis_t_s, clean.rate_nis_t_s),
    ):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    lost = (res.innovations.t_s > res.track_losses[0].lost_at_s) & (
        res.innovations.t_s <= res.track_losses[0].restarted_s
    )
    assert np.all(np.isnan(res.innovations.nis_pos[lost])) and np.any(lost)


def test_a_lost_track_is_reported_on_the_live_link():
    """Over real loopback UDP (``telemetry.live.serve``): tactical's first 40 s at 10x real
    time, its track lost at 25 s. Every HEARTBEAT goes CRITICAL with the epoch's
    ESTIMATOR_STATUS vouching for nothing, and ACTIVE again once it vouches again."""
    from filters.bench import _first_seconds
    from telemetry.inputs import input_frames
    from telemetry.live import Endpoint, free_udp_port, play_frames, serve
    from telemetry.tlog import FrameWriter, frames_of

    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, 40.0)
    frames = list(frames_of(input_frames(samples, fixes, sim.config), FrameWriter()))
    p_in, p_out = free_udp_port(), free_udp_port()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", p_out))
    rx.settimeout(0.2)
    got: list[bytes] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            try:
                got.append(rx.recv(65536))
            except TimeoutError:
                pass

    def ready() -> None:
        dest = Endpoint("udpout", "127.0.0.1", p_in)
        threading.Thread(target=play_frames, args=(frames, dest, 10.0), daemon=True).start()

    def factory(cfg, on_epoch):
        return Pipeline(cfg, on_epoch=on_epoch, lose_track_at_s=(LOSS_S,))

    settings = OutputSettings(rates_hz={"heartbeat": 20.0, "estimator_status": 20.0})
    th = threading.Thread(target=receive)
    th.start()
    try:
        stats = serve(
            Endpoint("udpin", "127.0.0.1", p_in),
            Endpoint("udpout", "127.0.0.1", p_out),
            factory,
            settings,
            idle_exit_s=1.0,
            duration_s=120.0,
            ready=ready,
        )
    finally:
        time.sleep(0.3)
        done.set()
        th.join()
        rx.close()
    assert "filter failed" not in stats.counts
    mav = mavlink.MAVLink(None)
    msgs = [m for d in got for m in (mav.parse_buffer(d) or [])]
    # each epoch's HEARTBEAT comes before its ESTIMATOR_STATUS (both due at 20 Hz)
    pairs, hb = [], None
    for m in msgs:
        if m.get_type() == "HEARTBEAT":
            hb = m.system_status
        elif m.get_type() == "ESTIMATOR_STATUS" and hb is not None:
            pairs.append((m.time_usec * 1e-6, hb, m.flags))
            hb = None
    t = np.array([p[0] for p in pairs])
    status = np.array([p[1] for p in pairs])
    vouched = np.array([p[2] != 0 for p in pairs])
    assert t.min() < LOSS_S - 5.0 and t.max() > LOSS_S + 10.0
    lost = ~vouched & (t > LOSS_S - 0.1)
    assert np.any(lost) and np.all(status[lost] == mavlink.MAV_STATE_CRITICAL)
    assert np.all(status[vouched] == mavlink.MAV_STATE_ACTIVE)
    assert vouched[-1] and np.all(vouched[(t > 5.0) & (t < LOSS_S - 0.1)])
