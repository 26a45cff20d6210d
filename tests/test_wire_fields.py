"""Every wire field and CSV column ngnav writes or reads, against an independent reference.

Frames ngnav writes are decoded by pymavlink's own ``common`` dialect, or, for
the ngnav dialect's messages, by the XML-driven struct codec of
:mod:`tests.wire_reference`; frames ngnav reads are built the same independent
way. Expected values are written out here with their units (degE7, mm, cm/s,
cdeg, rad, us), from values chosen so that a wrong scale, a swapped field or a
wrong sign changes the result. CSV files are read back with the ``csv`` module
and compared column by column; hand-written CSV files are read by ngnav.
"""

from __future__ import annotations

import bisect
import csv
import itertools
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common
from scipy.stats import chi2

from filters.output import write_estimates_csv
from filters.pipeline import Pipeline
from ngnav.geodesy import LocalTangentPlane
from ngnav.records import (
    ArraySamples,
    Estimates,
    FlightTruth,
    GpsFixes,
    GpsUpdateResult,
    NavEstimate,
)
from ngnav.runconfig import run_config_text
from ngnav.runio import (
    read_array_csv,
    read_gps_csv,
    read_truth_csv,
    write_array_csv,
    write_gps_csv,
    write_truth_csv,
)
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from telemetry.frames import FrameDecoder
from telemetry.inputs import (
    GpsDefaults,
    InputAssembler,
    batch_messages,
    config_messages,
    gps_input_message,
    input_frames,
)
from telemetry.outputs import EstimateEncoder, OutputSettings
from telemetry.session import StreamSession
from telemetry.tlog import EPOCH_BASE_US, FrameWriter, read_tlog, write_tlog
from tests.wire_reference import (
    EPOCH_2026_US,
    dcm,
    euler,
    f32,
    ned_to_geodetic,
    odometry_jacobians,
    pack_custom,
    parse_header,
    radii,
    unpack_custom,
    upper,
)

# Constants written out from common.xml (not taken from the generated modules)
MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_PX4 = 12
MAV_STATE_STANDBY, MAV_STATE_ACTIVE, MAV_STATE_CRITICAL = 3, 4, 5
MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_FRD = 1, 12
MAV_ESTIMATOR_TYPE_GPS_INS = 5
IGNORE_ALT, IGNORE_HDOP, IGNORE_VDOP = 1, 2, 4
IGNORE_VEL_HORIZ, IGNORE_VEL_VERT = 8, 16
IGNORE_SPEED_ACC, IGNORE_HORIZ_ACC, IGNORE_VERT_ACC = 32, 64, 128
# ESTIMATOR_STATUS_FLAGS: always set by ngnav (attitude, velocity horiz/vert, pos horiz rel,
# pos vert abs, predicted pos horiz rel/abs), then horiz abs while aided, and GPS glitch
EST_ALWAYS = 1 | 2 | 4 | 8 | 32 | 256 | 512
EST_POS_HORIZ_ABS, EST_GPS_GLITCH = 16, 1024
# ngnav.xml: NGNAV_HEALTH_FLAGS and NGNAV_COMPENSATION
HEALTH_ALIGNED, HEALTH_GPS_AIDED, HEALTH_RATE_REJECTED, HEALTH_FALLBACK = 1, 2, 4, 8
COMPENSATION_GM11 = 1

#: The encoder's "GPS aided" window (shorter than the fixture's outage) and gate probability.
GAP_S = 0.5
GATE_P = 0.9999
STREAMS = (
    "heartbeat",
    "system_time",
    "attitude_quaternion",
    "attitude",
    "local_position_ned",
    "global_position_int",
    "odometry",
    "estimator_status",
    "array_health",
)


def make_session(settings: OutputSettings | None = None, **kw) -> StreamSession:
    """A StreamSession running the real filter."""
    return StreamSession(lambda cfg, cb: Pipeline(cfg, on_epoch=cb), settings, **kw)


def decode_common(frame: bytes):
    """Decode one frame with pymavlink's common dialect (CRC checked by pymavlink)."""
    msg = common.MAVLink(None).decode(bytearray(frame))
    assert not isinstance(msg, common.MAVLink_unknown), "common.xml does not know this frame"
    return msg


def common_frame(msg, *, sysid: int = 7, compid: int = 42, seq: int = 0, v1: bool = False):
    """Pack a message built with pymavlink's common dialect (not ngnav's encoder)."""
    mav = common.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return bytes(msg.pack(mav, force_mavlink1=v1))


# ====================================================================== source run
@pytest.fixture(scope="module")
def scenario():
    """The short tactical flight (200 Hz) with a GPS glitch at 1 s."""
    return simulate_flight(
        load_flight(
            "tactical",
            [
                "run.rate_hz=200",
                "gps.glitch_times_s=[1.0]",
            ],
        ),
        0,
    )


@dataclass
class EpochRecord:
    """The filter state at one epoch and the frames ngnav encoded from it."""

    t_s: float
    q: np.ndarray
    w: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    cov: np.ndarray
    t_last_fix: float
    gps: tuple[float, float, float, bool] | None
    resets: int
    innovation: np.ndarray
    rate_nis: float
    rate_rejected_now: bool
    fallback_now: bool
    held: int
    rate_rejected: int
    fallbacks: int
    faulty: int
    valid: bool = True
    unix_usec: int | None = None
    frames: dict[str, bytes] = field(default_factory=dict)
    default_rate_types: list[str] = field(default_factory=list)

    @property
    def t_us(self) -> int:
        return round(self.t_s * 1e6)


def _gps(g) -> tuple[float, float, float, bool] | None:
    return None if g is None else (g.nis_vel, g.nis_pos_h, g.nis_pos_v, bool(g.pos_accepted))


def _snapshot(obj: NavEstimate) -> EpochRecord:
    """What the encoder is given at an epoch (``Pipeline.on_epoch``'s record), copied out."""
    inn = obj.rate_innovation
    return EpochRecord(
        t_s=float(obj.t_s),
        q=np.array(obj.q_nb, dtype=float),
        w=np.array(obj.omega_b_rps, dtype=float),
        pos=np.array(obj.pos_ned_m, dtype=float),
        vel=np.array(obj.vel_ned_mps, dtype=float),
        cov=np.array(obj.cov_nav),
        t_last_fix=float(obj.t_last_position_fix_s),
        gps=_gps(obj.last_gps),
        resets=obj.resets,
        innovation=np.zeros(0) if inn is None else np.array(inn, dtype=float),
        rate_nis=float(obj.rate_nis),
        rate_rejected_now=bool(obj.rate_rejected),
        fallback_now=bool(obj.forecast_fallback),
        held=obj.held_samples,
        rate_rejected=obj.rate_updates_rejected,
        fallbacks=obj.forecast_fallbacks,
        faulty=obj.faulty_channels,
        valid=bool(obj.valid),
    )


@pytest.fixture(scope="module")
def epochs(scenario) -> list[EpochRecord]:
    """3 s of the real filter; every epoch's state and its estimate frames (all streams due).

    The input has held samples (NaN, saturated), a GPS glitch (rejected fix) and an
    outage longer than the encoder's aided window, so flags and counters take both values. Every
    other epoch gives SYSTEM_TIME a wall clock.
    """
    s, f, cfg = scenario.samples, scenario.fixes, scenario.config
    ks = s.t_s <= 3.0
    t, a = s.t_s[ks], s.accel_mps2[ks].copy()
    a[100:104, 4] = np.nan
    a[150:152, 2] = 1e3
    f = f.select((f.t_s <= 3.0) & ~((f.t_s > 1.5) & (f.t_s < 2.3)))
    settings = OutputSettings(
        system_id=7,
        component_id=42,
        vehicle_type=MAV_TYPE_QUADROTOR,
        autopilot=MAV_AUTOPILOT_PX4,
        rates_hz=dict.fromkeys(STREAMS, 1000.0),
    )
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    enc = EstimateEncoder(settings, ltp, GATE_P, GAP_S, "gm11")
    enc_default = EstimateEncoder(OutputSettings(), ltp, GATE_P, GAP_S, "gm11")
    writer = FrameWriter(7, 42)
    out: list[EpochRecord] = []

    def on_epoch(obj: NavEstimate) -> None:
        rec = _snapshot(obj)
        k = len(out)
        rec.unix_usec = None if k % 2 == 0 else 1_700_000_000_123_456 + k
        for msg in enc.epoch(obj, rec.unix_usec):
            assert msg.get_type() not in rec.frames
            rec.frames[msg.get_type()] = writer.pack(msg)
        rec.default_rate_types = [m.get_type() for m in enc_default.epoch(obj)]
        out.append(rec)

    pipe = Pipeline(cfg, on_epoch=on_epoch)
    arrival = f.t_s + f.latency_s
    j = 0
    for i in range(0, t.shape[0], 10):
        while j < len(f) and arrival[j] <= t[i]:
            pipe.push_fix(
                f.t_s[j],
                f.lat_deg[j],
                f.lon_deg[j],
                f.alt_m[j],
                f.vel_ned_mps[j],
                f.h_acc_m[j],
                f.v_acc_m[j],
                f.vel_acc_mps[j],
            )
            j += 1
        pipe.push_samples(t[i : i + 10], a[i : i + 10])
    pipe.finish()
    assert len(out) > 200
    # the run exercises both sides of every flag the tests check
    assert any(r.gps is not None and not r.gps[3] for r in out), "no rejected fix"
    assert any(r.t_s - r.t_last_fix > GAP_S for r in out), "never unaided"
    assert out[-1].held > 0
    return out


def _all_frames(epochs: list[EpochRecord], name: str):
    return [(r, r.frames[name]) for r in epochs]


# ====================================================================== outputs
def test_estimate_frames_carry_the_sender_ids_and_a_running_sequence(epochs):
    """Header: MAVLink 2, system 7, component 42 (not swapped), seq +1 per frame mod 256."""
    seq = 0
    names = ("HEARTBEAT", "SYSTEM_TIME", "ATTITUDE_QUATERNION", "ATTITUDE")
    for r in epochs:
        assert sorted(r.frames) == sorted(
            [
                *names,
                "LOCAL_POSITION_NED",
                "GLOBAL_POSITION_INT",
                "ODOMETRY",
                "ESTIMATOR_STATUS",
                "NGNAV_ARRAY_HEALTH",
            ]
        )
        for fr in r.frames.values():
            h = parse_header(fr)
            assert (h.sysid, h.compid, h.incompat, h.seq) == (7, 42, 0, seq % 256)
            seq += 1
    assert seq > 256  # the sequence wrapped


def test_heartbeat_fields(epochs):
    """HEARTBEAT while estimating: the configured type/autopilot, version 3; the epoch's
    state: MAV_STATE_ACTIVE, or CRITICAL while its estimate is not valid yet (converging)
    or a channel fails a health test."""
    seen = set()
    for r, fr in _all_frames(epochs, "HEARTBEAT"):
        m = decode_common(fr)
        assert (m.type, m.autopilot, m.base_mode, m.custom_mode) == (
            MAV_TYPE_QUADROTOR,
            MAV_AUTOPILOT_PX4,
            0,
            0,
        )
        ok = r.valid and not r.faulty
        want = MAV_STATE_ACTIVE if ok else MAV_STATE_CRITICAL
        assert (m.system_status, m.mavlink_version) == (want, 3)
        assert (m.get_srcSystem(), m.get_srcComponent()) == (7, 42)
        seen.add(m.system_status)
    assert MAV_STATE_ACTIVE in seen


def test_system_time_fields(epochs):
    """SYSTEM_TIME: boot ms of the run clock; UNIX us = 2026-01-01 + run clock, or wall clock."""
    assert EPOCH_BASE_US == EPOCH_2026_US
    for r, fr in _all_frames(epochs, "SYSTEM_TIME"):
        m = decode_common(fr)
        assert m.time_boot_ms == r.t_us // 1000
        unix = EPOCH_2026_US + r.t_us if r.unix_usec is None else r.unix_usec
        assert m.time_unix_usec == unix


def test_attitude_quaternion_fields(epochs):
    """ATTITUDE_QUATERNION: q1..q4 = w, x, y, z; body rates rad/s; no offset quaternion."""
    for r, fr in _all_frames(epochs, "ATTITUDE_QUATERNION"):
        m = decode_common(fr)
        assert m.time_boot_ms == r.t_us // 1000
        assert [m.q1, m.q2, m.q3, m.q4] == [f32(x) for x in r.q]
        assert [m.rollspeed, m.pitchspeed, m.yawspeed] == [f32(x) for x in r.w]
        assert list(m.repr_offset_q) == [0.0] * 4


def test_attitude_fields(epochs):
    """ATTITUDE: ZYX roll, pitch, yaw in rad (from the quaternion's matrix here), rates rad/s."""
    yaws = []
    for r, fr in _all_frames(epochs, "ATTITUDE"):
        m = decode_common(fr)
        assert m.time_boot_ms == r.t_us // 1000
        np.testing.assert_allclose([m.roll, m.pitch, m.yaw], euler(r.q), rtol=0, atol=1e-6)
        assert [m.rollspeed, m.pitchspeed, m.yawspeed] == [f32(x) for x in r.w]
        yaws.append(m.yaw)
    # east-bound launch: yaw near +90 deg, in rad
    assert 1.3 < np.median(yaws) < 1.8


def test_local_position_ned_fields(epochs):
    """LOCAL_POSITION_NED: x, y, z = N, E, D (m); vx, vy, vz = vN, vE, vD (m/s)."""
    for r, fr in _all_frames(epochs, "LOCAL_POSITION_NED"):
        m = decode_common(fr)
        assert m.time_boot_ms == r.t_us // 1000
        assert [m.x, m.y, m.z] == [f32(x) for x in r.pos]
        assert [m.vx, m.vy, m.vz] == [f32(x) for x in r.vel]


def test_global_position_int_fields(scenario, epochs):
    """GLOBAL_POSITION_INT: lat/lon degE7, alt mm (ellipsoidal), relative_alt = -D mm,
    velocity cm/s NED, hdg cdeg in [0, 36000); lat/lon/alt from a WGS-84 conversion here."""
    cfg = scenario.config
    for r, fr in _all_frames(epochs, "GLOBAL_POSITION_INT"):
        m = decode_common(fr)
        lat, lon, alt = ned_to_geodetic(r.pos, cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
        assert m.time_boot_ms == r.t_us // 1000
        assert abs(m.lat - round(lat * 1e7)) <= 1
        assert abs(m.lon - round(lon * 1e7)) <= 1
        assert abs(m.alt - round(alt * 1000.0)) <= 1
        assert abs(m.relative_alt - round(-r.pos[2] * 1000.0)) <= 1
        for got, v in zip((m.vx, m.vy, m.vz), r.vel, strict=True):
            assert abs(got - round(v * 100.0)) <= 1
        hdg = round(math.degrees(euler(r.q)[2]) * 100.0) % 36000
        assert 0 <= m.hdg < 36000
        assert min(abs(m.hdg - hdg), 36000 - abs(m.hdg - hdg)) <= 1
    # the run leaves the origin by ~180 m east: the scale of lon shows
    assert abs(m.lon - round(cfg.lon0_deg * 1e7)) > 10_000


def test_odometry_fields(epochs):
    """ODOMETRY: frames LOCAL_NED/BODY_FRD, NED position, q, velocity in body FRD (C^T v),
    rates, both covariances (numerical Jacobians here), resets, GPS_INS, time in us."""
    for r, fr in _all_frames(epochs, "ODOMETRY"):
        m = decode_common(fr)
        assert m.time_usec == r.t_us
        assert (m.frame_id, m.child_frame_id) == (MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_FRD)
        assert [m.x, m.y, m.z] == [f32(x) for x in r.pos]
        assert list(m.q) == [f32(x) for x in r.q]
        v_b = dcm(r.q).T @ r.vel
        np.testing.assert_allclose([m.vx, m.vy, m.vz], v_b, rtol=1e-6, atol=1e-5)
        assert [m.rollspeed, m.pitchspeed, m.yawspeed] == [f32(x) for x in r.w]
        jp, jt = odometry_jacobians(r.q, r.vel)
        pose, twist = jp @ r.cov @ jp.T, jt @ r.cov @ jt.T
        for got, cov in ((m.pose_covariance, pose), (m.velocity_covariance, twist)):
            exp = np.array(upper(cov))
            np.testing.assert_allclose(got, exp, rtol=1e-5, atol=1e-6 * np.abs(exp).max())
        assert m.reset_counter == r.resets % 256
        assert (m.estimator_type, m.quality) == (MAV_ESTIMATOR_TYPE_GPS_INS, 0)
    # the velocity is not NED: the flight goes east, the body forward
    assert abs(m.vx) > 30 and abs(m.vy) < 10


def _ratio(nis: float, dof: int) -> float:
    return nis / chi2.ppf(GATE_P, dof) if math.isfinite(nis) else math.inf


def test_estimator_status_fields(epochs):
    """ESTIMATOR_STATUS: flags, NIS ratios over the gate of their own dof (vel 3, horiz 2,
    vert 1), unused ratios 0, accuracies sqrt(Pnn + Pee) and sqrt(Pdd) m, time in us."""
    seen_flags = set()
    for r, fr in _all_frames(epochs, "ESTIMATOR_STATUS"):
        m = decode_common(fr)
        assert m.time_usec == r.t_us
        flags = EST_ALWAYS
        if r.t_s - r.t_last_fix <= GAP_S:
            flags |= EST_POS_HORIZ_ABS
        if r.gps is not None and not r.gps[3]:
            flags |= EST_GPS_GLITCH
        assert m.flags == flags
        seen_flags.add(flags)
        if r.gps is None:
            exp = (0.0, 0.0, 0.0)
        else:
            exp = (_ratio(r.gps[0], 3), _ratio(r.gps[1], 2), _ratio(r.gps[2], 1))
        np.testing.assert_allclose(
            [m.vel_ratio, m.pos_horiz_ratio, m.pos_vert_ratio], exp, rtol=1e-6
        )
        assert (m.mag_ratio, m.hagl_ratio, m.tas_ratio) == (0.0, 0.0, 0.0)
        np.testing.assert_allclose(
            [m.pos_horiz_accuracy, m.pos_vert_accuracy],
            [math.sqrt(r.cov[0, 0] + r.cov[1, 1]), math.sqrt(r.cov[2, 2])],
            rtol=1e-6,
        )
    assert len(seen_flags) >= 3


def test_array_health_fields(epochs):
    """NGNAV_ARRAY_HEALTH (ngnav.xml, unpacked here): residuals, NIS, the counters in their
    own fields, faulty channels, flags and GM11 = 1."""
    for r, fr in _all_frames(epochs, "NGNAV_ARRAY_HEALTH"):
        h, name, v = unpack_custom(fr)
        assert (name, h.sysid, h.compid) == ("NGNAV_ARRAY_HEALTH", 7, 42)
        assert v["time_usec"] == r.t_us
        assert v["rate_residual"] == [f32(x) for x in r.innovation[:3]]
        if math.isnan(r.rate_nis):
            assert math.isnan(v["rate_nis"])
        else:
            assert v["rate_nis"] == f32(r.rate_nis)
        assert v["samples_held"] == r.held
        assert v["rate_rejected"] == r.rate_rejected
        assert v["forecast_fallbacks"] == r.fallbacks
        assert v["faulty_channels"] == r.faulty & 0xFFFF
        flags = HEALTH_ALIGNED
        if r.t_s - r.t_last_fix <= GAP_S:
            flags |= HEALTH_GPS_AIDED
        if r.rate_rejected_now:
            flags |= HEALTH_RATE_REJECTED
        if r.fallback_now:
            flags |= HEALTH_FALLBACK
        assert v["flags"] == flags
        assert v["compensation"] == COMPENSATION_GM11
    assert epochs[-1].held == 6  # 4 NaN rows + 2 saturated rows


def _hand_estimate() -> NavEstimate:
    """An epoch with every value chosen: 12.345678 s, 1234.5 m N, 400 m/s down (beyond
    int16 cm/s), yaw -2.5 rad, NIS at 2, 0.5 and 3 times their 95 % gates, a rejected
    fix 0.85 s ago, 258 resets, no rate innovation, NaN rate NIS."""
    return NavEstimate(
        t_s=12.345678,
        pos_ned_m=np.array([1234.5, -2345.25, -100.75]),
        vel_ned_mps=np.array([12.34, -56.78, 400.0]),
        q_nb=np.array(_quat_from_euler(0.1, -0.2, -2.5)),
        omega_b_rps=np.array([0.01, -0.02, 0.03]),
        bias=np.zeros(9),
        cov=np.diag([4.0, 9.0, 16.0, 0.25, 0.36, 0.49, 1e-4, 4e-4, 9e-4, 1e-6, 4e-6, 9e-6]),
        last_gps=GpsUpdateResult(
            nis_pos=9.0,
            nis_vel=2 * 7.814727903251178,
            pos_accepted=False,
            vel_accepted=True,
            nis_pos_h=0.5 * 5.991464547107979,
            nis_pos_v=3 * 3.841458820694124,
        ),
        t_last_position_fix_s=11.5,
        resets=258,
        rate_innovation=None,
        rate_nis=math.nan,
        rate_rejected=True,
        forecast_fallback=True,
        forecast_fallbacks=3,
        held_samples=17,
        rate_updates_rejected=5,
        faulty_channels=0x105,
    )


def test_hand_built_estimate_to_literal_wire_values(scenario):
    """One chosen NavEstimate through the encoder (gate 0.95, gap 0.5 s, compensation
    'line'): every wire value below is written out by hand."""
    cfg = scenario.config
    enc = EstimateEncoder(
        OutputSettings(rates_hz=dict.fromkeys(STREAMS, 1.0)),
        LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m),
        0.95,
        0.5,
        "line",
    )
    w = FrameWriter(1, 1)
    frames = {m.get_type(): w.pack(m) for m in enc.epoch(_hand_estimate())}
    assert len(frames) == 9
    m = decode_common(frames["HEARTBEAT"])
    # fixed wing; CRITICAL: the estimate marks channels 1, 3 and 9 faulty
    assert (m.type, m.autopilot, m.system_status) == (1, 0, MAV_STATE_CRITICAL)
    m = decode_common(frames["SYSTEM_TIME"])
    assert (m.time_boot_ms, m.time_unix_usec) == (12_345, EPOCH_2026_US + 12_345_678)
    m = decode_common(frames["ATTITUDE"])
    np.testing.assert_allclose([m.roll, m.pitch, m.yaw], [0.1, -0.2, -2.5], atol=1e-6)
    m = decode_common(frames["LOCAL_POSITION_NED"])
    assert [m.x, m.y, m.z, m.vx, m.vy, m.vz] == [
        1234.5, -2345.25, -100.75, f32(12.34), f32(-56.78), 400.0
    ]  # fmt: skip
    m = decode_common(frames["GLOBAL_POSITION_INT"])
    assert (m.time_boot_ms, m.relative_alt) == (12_345, 100_750)
    assert (m.vx, m.vy, m.vz, m.hdg) == (1234, -5678, 32767, 21676)  # vz saturated
    lat, lon, alt = ned_to_geodetic(
        np.array([1234.5, -2345.25, -100.75]), cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m
    )
    assert abs(m.lat - round(lat * 1e7)) <= 1 and abs(m.lon - round(lon * 1e7)) <= 1
    assert abs(m.alt - round(alt * 1000)) <= 1 and 1_601_000 < m.alt < 1_602_000
    m = decode_common(frames["ODOMETRY"])
    assert (m.time_usec, m.reset_counter) == (12_345_678, 2)
    m = decode_common(frames["ESTIMATOR_STATUS"])
    assert (m.time_usec, m.flags) == (12_345_678, EST_ALWAYS | EST_GPS_GLITCH)
    np.testing.assert_allclose(
        [m.vel_ratio, m.pos_horiz_ratio, m.pos_vert_ratio, m.pos_horiz_accuracy],
        [2.0, 0.5, 3.0, math.sqrt(13.0)],
        rtol=1e-6,
    )
    assert m.pos_vert_accuracy == 4.0
    _, _, v = unpack_custom(frames["NGNAV_ARRAY_HEALTH"])
    assert math.isnan(v.pop("rate_nis"))
    assert v == {
        "time_usec": 12_345_678,
        "rate_residual": [0.0, 0.0, 0.0],
        "samples_held": 17,
        "rate_rejected": 5,
        "forecast_fallbacks": 3,
        "faulty_channels": 0x105,
        "flags": HEALTH_ALIGNED | HEALTH_RATE_REJECTED | HEALTH_FALLBACK,
        "compensation": 2,  # NGNAV_COMPENSATION_LINE
    }


@pytest.mark.parametrize(
    ("name", "value"), [("none", 0), ("gm11", 1), ("line", 2), ("last", 3), ("oracle", 4)]
)
def test_compensation_ids(scenario, name: str, value: int):
    """NGNAV_ARRAY_HEALTH.compensation: the NGNAV_COMPENSATION value of ngnav.xml."""
    cfg = scenario.config
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    enc = EstimateEncoder(OutputSettings(rates_hz={"array_health": 1.0}), ltp, 0.95, 0.5, name)
    (msg,) = [m for m in enc.epoch(_hand_estimate()) if m.get_type() == "NGNAV_ARRAY_HEALTH"]
    assert unpack_custom(FrameWriter().pack(msg))[2]["compensation"] == value


def test_default_rates_send_each_stream_once_per_period(epochs):
    """With the default rates each stream goes out at the first epoch of each of its periods:
    1 Hz heartbeat/system time, 50 Hz attitude/position/odometry, 5 Hz status, 1 Hz health."""
    period_us = {
        "HEARTBEAT": 1_000_000,
        "SYSTEM_TIME": 1_000_000,
        "ATTITUDE_QUATERNION": 20_000,
        "ATTITUDE": 20_000,
        "LOCAL_POSITION_NED": 20_000,
        "GLOBAL_POSITION_INT": 20_000,
        "ODOMETRY": 20_000,
        "ESTIMATOR_STATUS": 200_000,
        "NGNAV_ARRAY_HEALTH": 1_000_000,
    }
    seen: dict[str, set[int]] = {k: set() for k in period_us}
    for r in epochs:
        for name, p in period_us.items():
            first = r.t_us // p not in seen[name]
            assert (name in r.default_rate_types) == first, (name, r.t_us)
            seen[name].add(r.t_us // p)


def test_session_heartbeat_before_the_filter_and_after_a_failure():
    """A session's own HEARTBEAT: its ids, STANDBY before the filter, CRITICAL after a bad
    configuration arrives (a config text whose CRC-32 is right but whose TOML is not)."""
    settings = OutputSettings(system_id=9, component_id=200, vehicle_type=MAV_TYPE_QUADROTOR)
    sess = make_session(settings)
    hb = sess.heartbeat()
    m = decode_common(hb.frame)
    assert (m.get_srcSystem(), m.get_srcComponent()) == (9, 200)
    assert (m.type, m.autopilot, m.system_status, m.mavlink_version) == (
        MAV_TYPE_QUADROTOR,
        0,
        MAV_STATE_STANDBY,
        3,
    )
    text = b"this is = not [valid toml"
    fr = pack_custom(
        "NGNAV_CONFIG_TEXT",
        {
            "config_id": zlib.crc32(text),
            "seq": 0,
            "total": 1,
            "length": len(text),
            "data": list(text) + [0] * (200 - len(text)),
        },
    )
    sess.feed_datagram(fr)
    assert sess.counts.as_dict() == {"frames decoded": 1, "bad configuration": 1}
    assert decode_common(sess.heartbeat().frame).system_status == MAV_STATE_CRITICAL


# ====================================================================== inputs ngnav writes
def _fixes() -> GpsFixes:
    return GpsFixes(
        t_s=np.array([10.25, 10.35]),
        lat_deg=np.array([34.0123456789, -33.9876543211]),
        lon_deg=np.array([-106.4987654321, 151.2093456789]),
        alt_m=np.array([1523.625, -12.25]),
        vel_ned_mps=np.array([[12.5, -3.25, 0.75], [-40.125, 60.5, -2.0]]),
        h_acc_m=np.array([1.75, 2.5]),
        v_acc_m=np.array([3.5, 4.0]),
        vel_acc_mps=np.array([0.125, 0.25]),
        latency_s=np.array([0.05, 0.125]),
    )


def test_gps_input_written_fields():
    """GPS_INPUT ngnav sends: time of validity us, arrival us, degE7 (hand-rounded), alt m,
    NED m/s, accuracies in their own fields, HDOP|VDOP ignored, fix 3, 12 satellites."""
    fx = _fixes()
    exp = [
        # time_usec, arrival, lat degE7, lon degE7
        (10_250_000, 10_300_000, 340123457, -1064987654),
        (10_350_000, 10_475_000, -339876543, 1512093457),
    ]
    w = FrameWriter(7, 42)
    for k, (t_us, arr, lat, lon) in enumerate(exp):
        arrival, msg = gps_input_message(fx, k)
        assert arrival == arr
        m = decode_common(w.pack(msg))
        assert m.get_type() == "GPS_INPUT"
        assert (m.time_usec, m.gps_id, m.time_week_ms, m.time_week) == (t_us, 0, 0, 0)
        assert m.ignore_flags == IGNORE_HDOP | IGNORE_VDOP
        assert (m.fix_type, m.lat, m.lon) == (3, lat, lon)
        assert m.alt == f32(fx.alt_m[k])
        assert (m.hdop, m.vdop) == (0.0, 0.0)
        assert [m.vn, m.ve, m.vd] == [f32(x) for x in fx.vel_ned_mps[k]]
        assert m.speed_accuracy == f32(fx.vel_acc_mps[k])
        assert m.horiz_accuracy == f32(fx.h_acc_m[k])
        assert m.vert_accuracy == f32(fx.v_acc_m[k])
        assert m.satellites_visible == 12


@pytest.mark.parametrize(("n_ch", "per"), [(9, 6), (10, 5), (16, 3)])
def test_array_batch_written_fields(n_ch: int, per: int):
    """NGNAV_ARRAY_BATCH ngnav sends: floor(54 / channels) samples (at most 6) sample-major,
    first-sample time and dt in us, valid/saturated bits per sample, count and n; yielded
    at the batch's last sample time."""
    t = 2.5 + 0.005 * np.arange(14)
    a = np.array([[(k + 1) * 1.0 + i * 0.125 - 4.0 for i in range(n_ch)] for k in range(14)])
    a[3, 5] = np.nan
    a[7, 2] = 40.0  # at the range: saturated
    a[8, 0] = -41.5
    samples = ArraySamples(t, a)
    got = list(batch_messages(samples, 40.0))
    starts = list(range(0, 14, per))
    assert len(got) == len(starts)
    w = FrameWriter(7, 42)
    for (t_send, msg), k0 in zip(got, starts, strict=True):
        k1 = min(k0 + per, 14)
        m = k1 - k0
        _, name, v = unpack_custom(w.pack(msg))
        assert name == "NGNAV_ARRAY_BATCH"
        assert t_send == 2_500_000 + 5_000 * (k1 - 1)
        assert v["time_usec"] == 2_500_000 + 5_000 * k0
        assert (v["dt_usec"], v["count"], v["n"]) == (5_000, n_ch, m)
        exp_acc = [0.0] * 54
        valid = [0] * 6
        sat = [0] * 6
        for j in range(m):
            for i in range(n_ch):
                x = a[k0 + j, i]
                if np.isfinite(x):
                    exp_acc[j * n_ch + i] = x
                    valid[j] |= 1 << i
                    if abs(x) >= 40.0:
                        sat[j] |= 1 << i
        assert v["accel"] == exp_acc
        assert (v["valid"], v["saturated"]) == (valid, sat)


def test_config_text_and_array_config_written_fields(scenario):
    """NGNAV_CONFIG_TEXT: config.toml in 200-byte chunks, seq/total/length, CRC-32 id;
    NGNAV_ARRAY_CONFIG: every channel's geometry, errors and calibration in its own field."""
    cfg = scenario.config
    text = run_config_text(cfg).encode()
    cid = zlib.crc32(text)
    msgs = config_messages(cfg)
    n_chunks = -(-len(text) // 200)
    assert len(msgs) == n_chunks + 9
    w = FrameWriter(7, 42)
    parts = []
    for k, msg in enumerate(msgs[:n_chunks]):
        _, name, v = unpack_custom(w.pack(msg))
        assert name == "NGNAV_CONFIG_TEXT"
        assert (v["config_id"], v["seq"], v["total"]) == (cid, k, n_chunks)
        assert v["length"] == min(200, len(text) - 200 * k)
        assert v["data"][v["length"] :] == [0] * (200 - v["length"])
        parts.append(bytes(v["data"][: v["length"]]))
    assert b"".join(parts) == text
    lay, err = cfg.layout, cfg.known_errors
    for i, msg in enumerate(msgs[n_chunks:]):
        _, name, v = unpack_custom(w.pack(msg))
        assert name == "NGNAV_ARRAY_CONFIG"
        assert (v["config_id"], v["channel"], v["count"]) == (cid, i, 9)
        assert v["position"] == [f32(x) for x in lay.positions_b_m[i]]
        assert v["axis"] == [f32(x) for x in lay.axes_b[i]]
        assert v["position_error"] == [f32(x) for x in err.position_error_b_m[i]]
        assert v["axis_error"] == [f32(x) for x in err.axis_error_rad[i]]
        assert v["scale"] == f32(cfg.scale[i])
        assert v["offset"] == f32(cfg.offset_mps2[i])
        assert v["noise_sigma"] == f32(cfg.noise_sigma_mps2[i])


def test_input_frames_send_order(scenario):
    """input_frames: configuration first at t0 and again at the first batch of every 10 s;
    a batch at its last sample's time; a fix at time + latency, before the first batch not
    earlier than its arrival; send times never go back."""
    s, f, cfg = scenario.samples, scenario.fixes, scenario.config
    items = list(input_frames(s, f, cfg))
    names = [m.get_type() for _, m in items]
    times = [t for t, _ in items]
    n_cfg = -(-len(run_config_text(cfg).encode()) // 200) + 9
    assert all(n.startswith("NGNAV_") and "CONFIG" in n for n in names[:n_cfg])
    assert times[:n_cfg] == [0] * n_cfg
    assert all(b >= a for a, b in itertools.pairwise(times))
    batch_t = [t for t, m in items if m.get_type() == "NGNAV_ARRAY_BATCH"]
    for t, m in items:
        if m.get_type() == "NGNAV_ARRAY_BATCH":
            assert t == m.time_usec + (m.n - 1) * m.dt_usec
    gps = [(k, t, m) for k, (t, m) in enumerate(items) if m.get_type() == "GPS_INPUT"]
    assert sorted(m.time_usec for _, _, m in gps) == [round(x * 1e6) for x in f.t_s]
    batch_k = [k for k, (_, m) in enumerate(items) if m.get_type() == "NGNAV_ARRAY_BATCH"]
    for k, t, m in gps:
        assert t == m.time_usec + 50_000  # the scenario's 0.05 s latency
        nb = bisect.bisect_left(batch_k, k)  # batches sent before this fix
        assert (nb == 0 or batch_t[nb - 1] < t) and (nb == len(batch_t) or batch_t[nb] >= t)
    repeats = [
        t for k, (t, m) in enumerate(items) if m.get_type() == "NGNAV_CONFIG_TEXT" and k >= n_cfg
    ]
    n_text = n_cfg - 9
    marks = [
        min(b for b in batch_t if b >= 10_000_000 * j)
        for j in range(1, batch_t[-1] // 10_000_000 + 1)
    ]
    assert len(marks) == 6  # 0 to 60 s
    assert repeats == [x for x in marks for _ in range(n_text)]


def test_frame_writer_and_tlog_records(tmp_path: Path):
    """tlog: big-endian uint64 us of 2026-01-01 + run clock, then the frame; the writer's
    system/component ids and a sequence wrapping at 256; read_tlog gives the same back."""
    msgs = [
        (1_000 * k + 7, common.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)) for k in range(300)
    ]
    path = tmp_path / "hb.tlog"
    assert write_tlog(path, msgs, FrameWriter(7, 42)) == 300
    blob = path.read_bytes()
    i = 0
    for k in range(300):
        ts = int.from_bytes(blob[i : i + 8], "big")
        assert ts == EPOCH_2026_US + 1_000 * k + 7
        ln = 12 + blob[i + 9]
        h = parse_header(blob[i + 8 : i + 8 + ln])
        assert (h.sysid, h.compid, h.seq, h.msg_id) == (7, 42, k % 256, 0)
        i += 8 + ln
    assert i == len(blob)
    back = list(read_tlog(path))
    assert [ts for ts, _ in back] == [EPOCH_2026_US + 1_000 * k + 7 for k in range(300)]
    assert all(m.get_type() == "HEARTBEAT" and m.autopilot == 12 for _, m in back)


# ====================================================================== inputs ngnav reads
DEFAULTS = GpsDefaults(h_acc_m=4.25, v_acc_m=6.5, vel_acc_mps=0.625)


def _read_fixes(*frames: bytes, defaults: GpsDefaults = DEFAULTS):
    """Decode frames with ngnav (frame layer and assembler); the fixes and the counts."""
    dec = FrameDecoder()
    got: list[tuple[int, tuple[float, ...]]] = []
    asm = InputAssembler(
        gps_defaults=defaults, counts=dec.counts, on_fix=lambda t, row: got.append((t, row))
    )
    for fr in frames:
        for msg in dec.decode_buffer(fr):
            asm.add(msg)
    return got, dec.counts.as_dict()


def _gps_input(fix_type: int = 3, ignore: int = 0, t_us: int = 1_234_567):
    return common.MAVLink_gps_input_message(
        t_us, 0, ignore, 0, 0, fix_type, 347654321, -1065432109, 1523.25,
        0.9, 1.1, 12.5, -3.25, 0.75, 0.125, 1.75, 3.5, 9,
    )  # fmt: skip


#: The hand-computed SI row of _gps_input(): deg, deg, m, m/s x3, h/v accuracy m, speed m/s
GPS_INPUT_ROW = (34.7654321, -106.5432109, 1523.25, 12.5, -3.25, 0.75, 1.75, 3.5, 0.125)


def test_gps_input_read_fields():
    """GPS_INPUT from pymavlink: lat/lon degE7 -> deg (1e-7), alt m, NED m/s, each accuracy
    from its own field, time_usec as is."""
    got, counts = _read_fixes(common_frame(_gps_input()))
    assert counts == {"frames decoded": 1}
    ((t_us, row),) = got
    assert t_us == 1_234_567
    np.testing.assert_allclose(row, GPS_INPUT_ROW, rtol=0, atol=1e-12)


@pytest.mark.parametrize(("fix_type", "kept"), [(0, 0), (1, 0), (2, 0), (3, 1), (4, 1), (6, 1)])
def test_gps_input_fix_type(fix_type: int, kept: int):
    """fix_type < 3 (no fix, 2-D) is skipped and counted; 3-D, DGPS, RTK are taken."""
    got, counts = _read_fixes(common_frame(_gps_input(fix_type)))
    assert len(got) == kept
    assert counts.get("gps without fix", 0) == 1 - kept


def _gps_input_at(lat_e7: int, lon_e7: int, alt_m: float, vn_mps: float, t_us: int = 1_000_000):
    return common.MAVLink_gps_input_message(
        t_us, 0, 0, 0, 0, 3, lat_e7, lon_e7, alt_m,
        0.9, 1.1, vn_mps, 0.0, 0.0, 0.125, 1.75, 3.5, 9,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("lat_e7", "lon_e7", "alt_m", "vn_mps", "kind"),
    [
        (900_000_001, 0, 0.0, 0.0, "gps latitude beyond +-90 deg"),
        (-900_000_001, 0, 0.0, 0.0, "gps latitude beyond +-90 deg"),
        (0, 1_800_000_001, 0.0, 0.0, "gps longitude beyond +-180 deg"),
        (0, -2_147_483_648, 0.0, 0.0, "gps longitude beyond +-180 deg"),
        (0, 0, -1000.5, 0.0, "gps altitude outside -1 km .. 100 km"),
        (0, 0, 100_000.5, 0.0, "gps altitude outside -1 km .. 100 km"),
        (0, 0, 0.0, 3000.5, "gps speed above 3 km/s"),
        (0, 0, 0.0, -3000.5, "gps speed above 3 km/s"),
    ],
)
def test_gps_input_out_of_range_is_dropped_and_counted_by_kind(lat_e7, lon_e7, alt_m, vn_mps, kind):
    """A latitude, longitude, altitude or speed no flying vehicle reports is dropped at input
    and counted by its kind; the limits themselves are taken."""
    got, counts = _read_fixes(common_frame(_gps_input_at(lat_e7, lon_e7, alt_m, vn_mps)))
    assert got == [] and counts == {"frames decoded": 1, kind: 1}


def test_gps_input_at_the_range_limits_is_taken():
    got, counts = _read_fixes(
        common_frame(_gps_input_at(900_000_000, 1_800_000_000, -1000.0, 3000.0, 1_000_000)),
        common_frame(
            _gps_input_at(-900_000_000, -1_800_000_000, 100_000.0, -3000.0, 2_000_000), seq=1
        ),
    )
    assert len(got) == 2 and counts == {"frames decoded": 2}


@pytest.mark.parametrize(
    ("flag", "index", "default"),
    [(IGNORE_HORIZ_ACC, 6, 4.25), (IGNORE_VERT_ACC, 7, 6.5), (IGNORE_SPEED_ACC, 8, 0.625)],
)
def test_gps_input_ignored_accuracy_falls_back_to_its_default(flag: int, index: int, default):
    """An accuracy flagged ignored is replaced by its own default; nothing else changes
    (HDOP/VDOP flags, which ngnav sends, change nothing)."""
    got, _ = _read_fixes(common_frame(_gps_input(ignore=flag | IGNORE_HDOP | IGNORE_VDOP)))
    ((_, row),) = got
    exp = list(GPS_INPUT_ROW)
    exp[index] = default
    np.testing.assert_allclose(row, exp, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("flag", "absent", "kinds"),
    [
        (IGNORE_ALT, [2], ["gps without altitude (the rest used)"]),
        (IGNORE_VEL_HORIZ, [3, 4], ["gps without horizontal velocity (the rest used)"]),
        (IGNORE_VEL_VERT, [5], ["gps without vertical velocity (the rest used)"]),
        (
            IGNORE_ALT | IGNORE_VEL_VERT,
            [2, 5],
            [
                "gps without altitude (the rest used)",
                "gps without vertical velocity (the rest used)",
            ],
        ),
    ],
)
def test_gps_input_ignored_fields_go_on_as_not_given(flag: int, absent, kinds):
    """An altitude or velocity flagged ignored goes on as NaN (the filter fuses the rest),
    counted per field; every other field is read as usual."""
    got, counts = _read_fixes(common_frame(_gps_input(ignore=flag)))
    ((_, row),) = got
    exp = [math.nan if i in absent else x for i, x in enumerate(GPS_INPUT_ROW)]
    np.testing.assert_allclose(row, exp, rtol=0, atol=1e-12)
    assert counts == {"frames decoded": 1, **{k: 1 for k in kinds}}


def test_gps_input_encodes_a_missing_field_as_ignored():
    """A fix lacking its altitude and vertical velocity (NaN) is written with those ignore
    flags, and reads back the same."""
    fixes = GpsFixes(
        t_s=np.array([1.5]),
        lat_deg=np.array([34.7654321]),
        lon_deg=np.array([-106.5432109]),
        alt_m=np.array([np.nan]),
        vel_ned_mps=np.array([[12.5, -3.25, np.nan]]),
        h_acc_m=np.array([1.75]),
        v_acc_m=np.array([3.5]),
        vel_acc_mps=np.array([0.125]),
        latency_s=np.array([0.0]),
    )
    _, msg = gps_input_message(fixes, 0)
    assert msg.ignore_flags & (IGNORE_ALT | IGNORE_VEL_VERT) == IGNORE_ALT | IGNORE_VEL_VERT
    assert not msg.ignore_flags & IGNORE_VEL_HORIZ
    ((_, row),) = _read_fixes(common_frame(msg))[0]
    exp = [34.7654321, -106.5432109, math.nan, 12.5, -3.25, math.nan, 1.75, 3.5, 0.125]
    np.testing.assert_allclose(row, exp, rtol=0, atol=1e-9)


def test_gps_raw_int_read_fields():
    """GPS_RAW_INT: degE7, alt mm -> m, speed cm/s along cog cdeg -> vN = v cos, vE = v sin,
    vD not given (NaN, counted); accuracies from the defaults. An unknown speed or course
    leaves the velocity out, not the fix."""
    msg = common.MAVLink_gps_raw_int_message(
        2_000_000, 3, 347654321, -1065432109, 1523250, 120, 250, 2000, 3000, 11
    )
    got, counts = _read_fixes(common_frame(msg))
    vertical = "gps without vertical velocity (the rest used)"
    assert counts == {"frames decoded": 1, vertical: 1}
    ((t_us, row),) = got
    assert t_us == 2_000_000
    exp = (34.7654321, -106.5432109, 1523.25, 20.0 * math.sqrt(3) / 2, 10.0, math.nan)
    np.testing.assert_allclose(row, (*exp, 4.25, 6.5, 0.625), rtol=0, atol=1e-9)
    for vel, cog in ((65535, 3000), (2000, 65535)):
        unknown = common.MAVLink_gps_raw_int_message(
            3_000_000, 3, 347654321, -1065432109, 1523250, 120, 250, vel, cog, 11
        )
        got, counts = _read_fixes(common_frame(unknown))
        ((_, row),) = got
        assert np.isnan(row[3:6]).all()
        np.testing.assert_allclose(row[0:3], exp[0:3], rtol=0, atol=1e-9)
        assert counts[vertical] == counts["gps without horizontal velocity (the rest used)"] == 1
    got, counts = _read_fixes(
        common_frame(common.MAVLink_gps_raw_int_message(1, 2, 1, 1, 1, 1, 1, 1, 1, 1))
    )
    assert got == [] and counts["gps without fix"] == 1


def test_hil_gps_read_fields():
    """HIL_GPS: degE7, alt mm -> m, vn/ve/vd cm/s -> m/s (its speed and course unused)."""
    msg = common.MAVLink_hil_gps_message(
        2_500_000, 3, -339876543, 1512093457, -12250, 100, 200, 65535, 1250, -325, 75, 65535, 9
    )
    got, counts = _read_fixes(common_frame(msg))
    assert counts == {"frames decoded": 1}
    ((t_us, row),) = got
    assert t_us == 2_500_000
    exp = (-33.9876543, 151.2093457, -12.25, 12.5, -3.25, 0.75, 4.25, 6.5, 0.625)
    np.testing.assert_allclose(row, exp, rtol=0, atol=1e-12)


def _batch(t_us: int, vals: np.ndarray, valid: list[int], dt: int = 5_000, seq: int = 0):
    n, c = vals.shape
    acc = list(vals.ravel()) + [0.0] * (54 - n * c)
    return pack_custom(
        "NGNAV_ARRAY_BATCH",
        {
            "time_usec": t_us,
            "accel": acc,
            "dt_usec": dt,
            "valid": valid + [0] * (6 - n),
            "saturated": [0] * 6,
            "count": c,
            "n": n,
        },
        seq=seq,
    )


def _read_samples(*frames: bytes) -> tuple[ArraySamples, dict]:
    dec = FrameDecoder()
    asm = InputAssembler(counts=dec.counts)
    for fr in frames:
        for msg in dec.decode_buffer(fr):
            asm.add(msg)
    return asm.samples(), dec.counts.as_dict()


def test_array_batch_read_fields():
    """NGNAV_ARRAY_BATCH (packed here): sample j of channel i is accel[j * count + i], at
    time_usec + j dt_usec; a clear valid bit makes that channel NaN."""
    vals = np.array([[0.25 * i - 1.5 * j + 3.0 for i in range(9)] for j in range(6)])
    b1 = _batch(1_000_000, vals[:3], [0x1FF, 0x1FF & ~(1 << 4), 0x1FF])
    b2 = _batch(1_015_000, vals[3:], [0x1FF, 0x1FF, 0x1FF & ~1], seq=1)
    s, counts = _read_samples(b1, b2)
    assert counts == {"frames decoded": 2}
    np.testing.assert_allclose(s.t_s, 1.0 + 0.005 * np.arange(6), rtol=0, atol=1e-12)
    exp = vals.copy()
    exp[1, 4] = np.nan
    exp[5, 0] = np.nan
    np.testing.assert_array_equal(s.accel_mps2, exp)


def test_array_sample_read_fields():
    """NGNAV_ARRAY_SAMPLE (packed here): the first ``count`` floats are the channels (the rest
    ignored), time_usec in us; a clear valid bit makes that channel NaN."""
    frames = []
    exp = []
    for k in range(10):
        row = [0.5 * i - 0.25 * k + 1.0 for i in range(9)]
        valid = 0x1FF & ~(1 << 8) if k == 3 else 0x1FF
        frames.append(
            pack_custom(
                "NGNAV_ARRAY_SAMPLE",
                {
                    "time_usec": 5_000_000 + 2_500 * k,
                    "accel": row + [99.0] * 7,
                    "valid": valid,
                    "saturated": 0,
                    "count": 9,
                },
                seq=k,
            )
        )
        exp.append([*row[:8], np.nan] if k == 3 else row)
    s, counts = _read_samples(*frames)
    assert counts == {"frames decoded": 10}
    np.testing.assert_allclose(s.t_s, 5.0 + 0.0025 * np.arange(10), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(s.accel_mps2, np.array(exp))


def _config_chunks(text: bytes, cid: int | None = None) -> list[bytes]:
    cid = zlib.crc32(text) if cid is None else cid
    chunks = [text[i : i + 200] for i in range(0, len(text), 200)]
    return [
        pack_custom(
            "NGNAV_CONFIG_TEXT",
            {
                "config_id": cid,
                "seq": k,
                "total": len(chunks),
                "length": len(c),
                "data": list(c) + [0] * (200 - len(c)),
            },
            seq=k,
        )
        for k, c in enumerate(chunks)
    ]


def test_config_text_read_in_any_order(scenario):
    """NGNAV_CONFIG_TEXT (packed here, sent last chunk first): the text whole, once; a set
    whose CRC-32 does not match the text is counted and not used."""
    text = run_config_text(scenario.config).encode()
    got: list[str] = []
    dec = FrameDecoder()
    asm = InputAssembler(counts=dec.counts, on_config=got.append)
    for fr in reversed(_config_chunks(text)):
        for msg in dec.decode_buffer(fr):
            asm.add(msg)
    assert got == [text.decode()]
    assert asm.config().layout.n_sensors == 9
    dec = FrameDecoder()
    asm = InputAssembler(counts=dec.counts, on_config=got.append)
    for fr in _config_chunks(text, cid=zlib.crc32(text) ^ 1):
        for msg in dec.decode_buffer(fr):
            asm.add(msg)
    assert len(got) == 1 and dec.counts.as_dict()["bad config chunk"] == 1


# ====================================================================== CSV
def _csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def test_array_csv_written_columns(tmp_path: Path):
    """array.csv: t_s, a1_mps2..aN_mps2 in channel order, 10 significant digits, NaN as nan."""
    a = np.array([[9.80665, -0.125, 12.3456789], [1.5e-3, 2.0, -3.75], [4.0, np.nan, 6.25]])
    write_array_csv(tmp_path / "array.csv", ArraySamples(np.array([0.0, 0.005, 0.01]), a))
    header, rows = _csv(tmp_path / "array.csv")
    assert header == ["t_s", "a1_mps2", "a2_mps2", "a3_mps2"]
    assert [float(r[0]) for r in rows] == [0.0, 0.005, 0.01]
    got = np.array([[float(x) for x in r[1:]] for r in rows])
    np.testing.assert_array_equal(got, a)


def test_array_csv_read_hand_written(tmp_path: Path):
    """array.csv read by header name (any order, extra columns ignored); an empty cell is a
    NaN sample (counted); a missing grid point becomes a NaN row (counted)."""
    (tmp_path / "array.csv").write_text(
        "a3_mps2,t_s,a1_mps2,a2_mps2,temp_c\n"
        "3.5,0.00,1.25,-2.5,20\n"
        "3.75,0.01,1.5,,20\n"
        "4.0,0.02,1.75,-3.0,21\n"
        "4.5,0.04,2.25,-4.0,21\n"
    )
    s, rep = read_array_csv(tmp_path / "array.csv", 3)
    np.testing.assert_allclose(s.t_s, [0.0, 0.01, 0.02, 0.03, 0.04], rtol=0, atol=1e-12)
    nan = np.nan
    exp = [[1.25, -2.5, 3.5], [1.5, nan, 3.75], [1.75, -3.0, 4.0], [nan] * 3, [2.25, -4.0, 4.5]]
    np.testing.assert_array_equal(s.accel_mps2, np.array(exp))
    assert rep.counts == {"missing samples filled": 1, "bad samples (non-finite cell)": 1}
    (tmp_path / "bad.csv").write_text("t_s,a1_mps2,a3_mps2\n0,1,2\n")
    with pytest.raises(ValueError, match="a2_mps2"):
        read_array_csv(tmp_path / "bad.csv", 3)


GPS_HEADER = (
    "t_s,lat_deg,lon_deg,alt_m,vn_mps,ve_mps,vd_mps,h_acc_m,v_acc_m,vel_acc_mps,fix_type,latency_s"
)


def test_gps_csv_written_columns(tmp_path: Path):
    """gps.csv: every column in its place and unit at its precision (t us, lat/lon 1e-10 deg,
    alt 0.1 mm, velocity 1e-5 m/s, accuracies 0.1 mm), fix_type 3, latency s."""
    write_gps_csv(tmp_path / "gps.csv", _fixes())
    header, rows = _csv(tmp_path / "gps.csv")
    assert ",".join(header) == GPS_HEADER
    assert ",".join(rows[0]) == (
        "10.250000,34.0123456789,-106.4987654321,1523.6250,12.50000,-3.25000,0.75000,"
        "1.7500,3.5000,0.1250,3,0.0500"
    )
    assert ",".join(rows[1]) == (
        "10.350000,-33.9876543211,151.2093456789,-12.2500,-40.12500,60.50000,-2.00000,"
        "2.5000,4.0000,0.2500,3,0.1250"
    )


def test_gps_csv_read_hand_written(tmp_path: Path):
    """gps.csv read by header name; fix_type < 3, an empty latitude, a zero accuracy and each
    out-of-range field are skipped and counted; an empty altitude or vertical velocity is
    a field not given (NaN, counted); latency_s read; every field of the kept fixes in its
    place."""
    (tmp_path / "gps.csv").write_text(
        "lon_deg,t_s,lat_deg,alt_m,vd_mps,ve_mps,vn_mps,vel_acc_mps,v_acc_m,h_acc_m,"
        "latency_s,fix_type\n"
        "-106.5,0.0,34.0,1500.0,0.5,60.0,1.0,0.1,3.0,1.5,0.05,3\n"
        "-106.4,0.1,34.1,1501.0,0.5,60.0,1.0,0.1,3.0,1.5,0.05,2\n"
        "-106.3,0.2,34.2,1502.0,,60.0,1.0,0.1,3.0,1.5,0.05,3\n"
        "-106.3,0.25,34.25,,0.5,60.0,1.0,0.1,,1.5,0.05,3\n"
        "-106.3,0.27,,1502.0,0.5,60.0,1.0,0.1,3.0,1.5,0.05,3\n"
        "-106.2,0.3,34.3,1503.0,0.5,60.0,1.0,0.1,3.0,0.0,0.05,3\n"
        "-106.1,0.4,34.4,1504.5,-0.25,-61.0,2.5,0.2,4.0,2.5,0.125,4\n"
        "-106.0,0.5,91.0,1505.0,0.5,60.0,1.0,0.1,3.0,1.5,0.05,3\n"
        "-186.0,0.6,34.6,1505.0,0.5,60.0,1.0,0.1,3.0,1.5,0.05,3\n"
        "-106.0,0.7,34.7,150500.0,0.5,60.0,1.0,0.1,3.0,1.5,0.05,3\n"
        "-106.0,0.8,34.8,1505.0,0.5,3000.0,100.0,0.1,3.0,1.5,0.05,3\n"
    )
    fx, rep = read_gps_csv(tmp_path / "gps.csv")
    assert rep.counts == {
        "no fix (fix_type < 3)": 1,
        "no fix (empty or nan cell)": 1,
        "no fix (accuracy not positive)": 1,
        "no fix (latitude beyond +-90 deg)": 1,
        "no fix (longitude beyond +-180 deg)": 1,
        "no fix (altitude outside -1 km .. 100 km)": 1,
        "no fix (speed above 3 km/s)": 1,
        "fixes without vertical velocity (the rest used)": 1,
        "fixes without altitude (the rest used)": 1,
    }
    np.testing.assert_array_equal(fx.t_s, [0.0, 0.2, 0.25, 0.4])
    np.testing.assert_array_equal(fx.lat_deg, [34.0, 34.2, 34.25, 34.4])
    np.testing.assert_array_equal(fx.lon_deg, [-106.5, -106.3, -106.3, -106.1])
    np.testing.assert_array_equal(fx.alt_m, [1500.0, 1502.0, np.nan, 1504.5])
    np.testing.assert_array_equal(
        fx.vel_ned_mps,
        [[1.0, 60.0, 0.5], [1.0, 60.0, np.nan], [1.0, 60.0, 0.5], [2.5, -61.0, -0.25]],
    )
    np.testing.assert_array_equal(fx.h_acc_m, [1.5, 1.5, 1.5, 2.5])
    np.testing.assert_array_equal(fx.vel_acc_mps, [0.1, 0.1, 0.1, 0.2])
    np.testing.assert_array_equal(fx.latency_s, [0.05, 0.05, 0.05, 0.125])


TRUTH_HEADER = [
    "t_s", "n_m", "e_m", "d_m", "vn_mps", "ve_mps", "vd_mps", "qw", "qx", "qy", "qz",
    "wx_radps", "wy_radps", "wz_radps", "wdx_radps2", "wdy_radps2", "wdz_radps2",
    "fx_mps2", "fy_mps2", "fz_mps2",
]  # fmt: skip


def test_truth_csv_written_and_read(tmp_path: Path):
    """truth.csv: the 20 columns in order, each holding its own quantity; read back by name."""
    vals = np.array([[c + 0.5 * r + 0.125 for c in range(20)] for r in range(3)])
    vals[:, 0] = [0.0, 0.01, 0.02]
    tr = FlightTruth(
        vals[:, 0], vals[:, 1:4], vals[:, 4:7], vals[:, 7:11], vals[:, 11:14], vals[:, 14:17],
        vals[:, 17:20],
    )  # fmt: skip
    write_truth_csv(tmp_path / "truth.csv", tr)
    header, rows = _csv(tmp_path / "truth.csv")
    assert header == TRUTH_HEADER
    np.testing.assert_array_equal(np.array(rows, dtype=float), vals)
    # a hand-written file with the columns reversed and an extra one
    lines = [",".join(["extra", *reversed(TRUTH_HEADER)])]
    lines += [",".join(["7", *(repr(float(x)) for x in reversed(v))]) for v in vals]
    (tmp_path / "rev.csv").write_text("\n".join(lines) + "\n")
    back = read_truth_csv(tmp_path / "rev.csv")
    np.testing.assert_array_equal(back.t_s, vals[:, 0])
    np.testing.assert_array_equal(back.pos_ned_m, vals[:, 1:4])
    np.testing.assert_array_equal(back.vel_ned_mps, vals[:, 4:7])
    np.testing.assert_array_equal(back.q_nb, vals[:, 7:11])
    np.testing.assert_array_equal(back.omega_b_rps, vals[:, 11:14])
    np.testing.assert_array_equal(back.omega_dot_b_rps2, vals[:, 14:17])
    np.testing.assert_array_equal(back.f_b_mps2, vals[:, 17:20])


ESTIMATE_HEADER = [
    "t_s", "lat_deg", "lon_deg", "alt_m", "n_m", "e_m", "d_m", "vn_mps", "ve_mps", "vd_mps",
    "qw", "qx", "qy", "qz", "wx_radps", "wy_radps", "wz_radps",
    "lat_deg_sigma", "lon_deg_sigma", "alt_m_sigma", "n_m_sigma", "e_m_sigma", "d_m_sigma",
    "vn_mps_sigma", "ve_mps_sigma", "vd_mps_sigma",
    "att_n_rad_sigma", "att_e_rad_sigma", "att_d_rad_sigma",
    "wx_radps_sigma", "wy_radps_sigma", "wz_radps_sigma",
    "roll_deg", "pitch_deg", "yaw_deg", "aoa_deg", "aoa_deg_sigma", "faulty_channels", "valid",
]  # fmt: skip


def _quat_from_euler(roll: float, pitch: float, yaw: float) -> list[float]:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return [
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]


@pytest.mark.parametrize("with_aoa", [True, False])
def test_estimates_csv_columns(tmp_path: Path, scenario, with_aoa: bool):
    """estimates.csv: each of the 39 columns against its hand formula (WGS-84 lat/lon/alt,
    sigmas sqrt(P) with lat/lon sigma = sigma_N/(M+h), sigma_E/((N+h) cos lat) in deg, ZYX
    angles and angle of attack in deg, empty angle of attack without the state, the
    faulty-channels bitmask as an integer, valid as 1 or 0)."""
    cfg = scenario.config
    rpy = np.array([[0.1, -0.2, 2.5], [-0.3, 0.15, -1.25]])
    pos = np.array([[120.0, -340.0, -25.0], [121.5, -338.0, -24.0]])
    vel = np.array([[12.0, -3.5, 0.25], [11.5, -3.0, 0.5]])
    w = np.array([[0.01, -0.02, 0.03], [0.04, 0.05, -0.06]])
    diag = np.array([(k + 1) * 0.01 for k in range(12)])
    cov = np.stack([np.diag(diag), np.diag(diag * 4.0)])
    aoa = (np.array([0.05, 0.06]), np.array([0.01, 0.011])) if with_aoa else (None, None)
    est = Estimates(
        t_s=np.array([12.5, 12.51]),
        pos_ned_m=pos,
        vel_ned_mps=vel,
        q_nb=np.array([_quat_from_euler(*r) for r in rpy]),
        omega_b_rps=w,
        bias=np.zeros((2, 9)),
        cov_nav=cov,
        aoa_rad=aoa[0],
        aoa_sigma_rad=aoa[1],
        faulty_channels=np.array([0, 0b100100000]),
        valid=np.array([True, False]),
    )
    write_estimates_csv(tmp_path / "est.csv", est, cfg)
    header, rows = _csv(tmp_path / "est.csv")
    assert header == ESTIMATE_HEADER
    for e, row in enumerate(rows):
        got = dict(zip(header, (float(x) for x in row), strict=True))
        lat, lon, alt = ned_to_geodetic(pos[e], cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
        sig = np.sqrt(np.diag(cov[e]))
        m_r, n_r = radii(lat)
        exp = {
            "t_s": [12.5, 12.51][e],
            "lat_deg": lat,
            "lon_deg": lon,
            "alt_m": alt,
            **dict(zip(("n_m", "e_m", "d_m"), pos[e], strict=True)),
            **dict(zip(("vn_mps", "ve_mps", "vd_mps"), vel[e], strict=True)),
            **dict(zip(("qw", "qx", "qy", "qz"), est.q_nb[e], strict=True)),
            **dict(zip(("wx_radps", "wy_radps", "wz_radps"), w[e], strict=True)),
            "lat_deg_sigma": math.degrees(sig[0] / (m_r + alt)),
            "lon_deg_sigma": math.degrees(sig[1] / ((n_r + alt) * math.cos(math.radians(lat)))),
            "alt_m_sigma": sig[2],
            **{c: sig[k] for k, c in enumerate(ESTIMATE_HEADER[20:32])},
            **dict(zip(("roll_deg", "pitch_deg", "yaw_deg"), np.degrees(rpy[e]), strict=True)),
            "aoa_deg": math.degrees(aoa[0][e]) if with_aoa else math.nan,
            "aoa_deg_sigma": math.degrees(aoa[1][e]) if with_aoa else math.nan,
            "faulty_channels": [0, 288][e],
            "valid": [1, 0][e],
        }
        assert list(exp) == ESTIMATE_HEADER
        for col in ESTIMATE_HEADER:
            if col in ("t_s",):
                assert abs(got[col] - exp[col]) <= 5e-7, col
            elif col in ("lat_deg", "lon_deg"):
                assert abs(got[col] - exp[col]) <= 2e-10, col
            elif math.isnan(exp[col]):
                assert math.isnan(got[col]), col
            else:
                assert got[col] == pytest.approx(exp[col], rel=1e-5, abs=1e-12), col
