"""The filter's estimates as standard MAVLink messages any ground station reads.

:class:`EstimateEncoder` is called at every filter epoch (the pipeline's
``on_epoch``) and returns the messages due at that epoch's time, each stream
at its own rate (:class:`OutputSettings`). Rates run on the *run clock* (the
epochs' times), so a tlog replay and a live link of the same run produce the
same messages; only ``SYSTEM_TIME.time_unix_usec`` and a live link's idle
heartbeats follow the wall clock.

Messages and fields (frames: NED about the run's reference point, body FRD,
Hamilton scalar-first body-to-NED quaternion)
-------------------------------------------------------------------------------
- ``HEARTBEAT``: ``type`` (default ``MAV_TYPE_FIXED_WING``), ``autopilot``
  (default ``MAV_AUTOPILOT_GENERIC``), ``system_status`` ``MAV_STATE_ACTIVE``
  while estimating, ``MAV_STATE_STANDBY`` before the filter starts or when
  the input link is silent, ``MAV_STATE_CRITICAL`` after the filter failed, while its
  track is lost or its estimates not valid again yet, or while a channel fails a health
  test.
- ``SYSTEM_TIME``: ``time_boot_ms`` (run clock), ``time_unix_usec`` (the run
  clock on :data:`telemetry.tlog.EPOCH_BASE_US` in a replay, the wall clock live).
- ``ATTITUDE_QUATERNION``: ``q1..q4`` (w, x, y, z), body rates rad/s.
- ``ATTITUDE``: roll, pitch, yaw (rad, ZYX), body rates rad/s.
- ``LOCAL_POSITION_NED``: position m and velocity m/s, NED.
- ``GLOBAL_POSITION_INT``: ``lat``/``lon`` degE7, ``alt`` mm (WGS-84
  ellipsoidal height, as ngnav carries it everywhere; MAVLink defines MSL),
  ``relative_alt`` mm above the reference point, velocity cm/s NED, ``hdg``
  cdeg.
- ``ODOMETRY``: ``frame_id`` ``MAV_FRAME_LOCAL_NED``, ``child_frame_id``
  ``MAV_FRAME_BODY_FRD``, position NED, quaternion, velocity in *body FRD*
  (the child frame, as MAVLink defines it), body rates;
  ``pose_covariance`` (x, y, z, roll, pitch, yaw) and
  ``velocity_covariance`` (vx, vy, vz, rollspeed, pitchspeed, yawspeed) as
  the 21-float row-major upper triangle, mapped from the filter's error
  covariance by :func:`odometry_covariances`; ``reset_counter`` counts
  position/velocity resets; ``estimator_type`` ``MAV_ESTIMATOR_TYPE_GPS_INS``.
- ``ESTIMATOR_STATUS``: ``pos_horiz_ratio`` = horizontal position NIS over
  the 2-dof chi-square gate, ``pos_vert_ratio`` = vertical NIS over the 1-dof
  gate, ``vel_ratio`` = velocity NIS over the 3-dof gate, all at the filter's
  ``gate_probability`` (< 0.5 normal, > 1 beyond the gate; the filter gates
  the joint 3-D position NIS, and ``ESTIMATOR_GPS_GLITCH`` marks a fix it
  actually rejected); ``pos_horiz_accuracy``/``pos_vert_accuracy`` 1-sigma m;
  unused ratios 0. Flags: attitude, velocity, relative position and
  predicted position while the estimate is valid (none in the seconds after the
  filter started again from a lost track); absolute position while GPS aided (a
  position accepted within ``filter.gps_gap_reset_s``); GPS glitch.
- ``NGNAV_ARRAY_HEALTH``: the rate-product innovation and NIS, held samples,
  rejected rate updates, forecast fallbacks, the channels invalid or
  saturated in the last block, the compensation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from ngnav.geodesy import LocalTangentPlane
from ngnav.records import NavEstimate
from ngnav.rotation import dcm_from_quat, euler_from_quat, skew
from telemetry import ngnav_mavlink as mavlink

#: Output streams and their default rates, Hz (0 switches a stream off).
DEFAULT_RATES_HZ: dict[str, float] = {
    "heartbeat": 1.0,
    "system_time": 1.0,
    "attitude_quaternion": 50.0,
    "attitude": 50.0,
    "local_position_ned": 50.0,
    "global_position_int": 50.0,
    "odometry": 50.0,
    "estimator_status": 5.0,
    "array_health": 1.0,
}

_COMPENSATION_IDS = {
    "none": mavlink.NGNAV_COMPENSATION_NONE,
    "gm11": mavlink.NGNAV_COMPENSATION_GM11,
    "line": mavlink.NGNAV_COMPENSATION_LINE,
    "last": mavlink.NGNAV_COMPENSATION_LAST,
    "oracle": mavlink.NGNAV_COMPENSATION_ORACLE,
}
_IU, _JU = np.triu_indices(6)


@dataclass(frozen=True)
class OutputSettings:
    """Who the estimates say they come from, and how often each stream is sent.

    Parameters
    ----------
    system_id : int
        MAVLink system id, 1-254 (255 is reserved for ground stations).
    component_id : int
        MAVLink component id, 1-255 (1: the autopilot, which ground stations
        show as the vehicle).
    vehicle_type : int
        ``MAV_TYPE`` in the heartbeat.
    autopilot : int
        ``MAV_AUTOPILOT`` in the heartbeat (``MAV_AUTOPILOT_INVALID`` is refused:
        ground stations then ignore the system).
    rates_hz : dict
        Stream name (a key of :data:`DEFAULT_RATES_HZ`) to rate, Hz.
    """

    system_id: int = 1
    component_id: int = 1
    vehicle_type: int = mavlink.MAV_TYPE_FIXED_WING
    autopilot: int = mavlink.MAV_AUTOPILOT_GENERIC
    rates_hz: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_RATES_HZ))

    def __post_init__(self) -> None:
        if not 1 <= self.system_id <= 254:
            raise ValueError(f"system id must be 1-254, got {self.system_id}")
        if not 1 <= self.component_id <= 255:
            raise ValueError(f"component id must be 1-255, got {self.component_id}")
        if self.vehicle_type not in mavlink.enums["MAV_TYPE"]:
            raise ValueError(f"unknown MAV_TYPE {self.vehicle_type}")
        if self.autopilot not in mavlink.enums["MAV_AUTOPILOT"]:
            raise ValueError(f"unknown MAV_AUTOPILOT {self.autopilot}")
        if self.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
            raise ValueError(
                "autopilot MAV_AUTOPILOT_INVALID makes ground stations ignore the system"
            )
        rates = dict(DEFAULT_RATES_HZ)
        for name, hz in self.rates_hz.items():
            if name not in DEFAULT_RATES_HZ:
                raise ValueError(
                    f"unknown output stream {name!r}; streams: {', '.join(DEFAULT_RATES_HZ)}"
                )
            if not (math.isfinite(hz) and 0.0 <= hz <= 1000.0):
                raise ValueError(f"rate of {name!r} must be in [0, 1000] Hz, got {hz}")
            rates[name] = float(hz)
        object.__setattr__(self, "rates_hz", rates)

    def heartbeat(self, status: int) -> mavlink.MAVLink_message:
        """A HEARTBEAT of this sender with the given ``MAV_STATE``."""
        return mavlink.MAVLink_heartbeat_message(self.vehicle_type, self.autopilot, 0, 0, status, 3)


def parse_rates(items: list[str]) -> dict[str, float]:
    """``["odometry=10", ...]`` to ``{"odometry": 10.0}`` (ValueError naming the bad item)."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"output rate {item!r} is not STREAM=HZ") from None
    return out


def upper_triangle(m: np.ndarray) -> list[float]:
    """The 21 row-major upper-triangle entries of a 6x6 matrix (MAVLink's covariance layout)."""
    return [float(x) for x in m[_IU, _JU]]


def odometry_covariances(
    q_nb: np.ndarray,
    vel_ned_mps: np.ndarray,
    cov_nav: np.ndarray,
    rpy_rad: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """ODOMETRY's pose and twist covariances (6x6 each) from the filter's error covariance.

    Parameters
    ----------
    q_nb : array (4,)
        Estimated attitude (body to NED, scalar first).
    vel_ned_mps : array (3,)
        Estimated velocity, NED.
    cov_nav : array (12, 12)
        Covariance of the error states ``[dp_ned, dv_ned, dtheta_ned, dw_b]``
        (``q_true = exp(dtheta) q_est``).
    rpy_rad : array (3,), optional
        ``euler_from_quat(q_nb)`` when the caller has it already.

    Returns
    -------
    pose : array (6, 6)
        Of ``(x, y, z, roll, pitch, yaw)``: position NED, ZYX Euler angles.
    twist : array (6, 6)
        Of ``(vx, vy, vz)`` in body FRD and the body rates.

    Notes
    -----
    First order: the Euler-angle error is ``E^-1 C^T dtheta`` with ``E`` the
    Euler-rate matrix (``w_b = E [roll', pitch', yaw']``); the body velocity's
    is ``C^T dv + C^T [v x] dtheta``.
    """
    c = dcm_from_quat(q_nb)
    roll, pitch, _ = (euler_from_quat(q_nb) if rpy_rad is None else rpy_rad).tolist()
    sr, cr = math.sin(roll), math.cos(roll)
    tp, cp = math.tan(pitch), math.cos(pitch)
    e_inv = np.array(
        [[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]]
    )  # body rate to Euler rate
    jp = np.zeros((6, 12))
    jp[0:3, 0:3] = np.eye(3)
    jp[3:6, 6:9] = e_inv @ c.T
    jt = np.zeros((6, 12))
    jt[0:3, 3:6] = c.T
    jt[0:3, 6:9] = c.T @ skew(np.asarray(vel_ned_mps, dtype=float))
    jt[3:6, 9:12] = np.eye(3)
    return jp @ cov_nav @ jp.T, jt @ cov_nav @ jt.T


def _ms(t_us: int) -> int:
    return max(0, int(t_us // 1000)) % (1 << 32)


class EstimateEncoder:
    """Turn filter epochs into due MAVLink messages (see the module docstring).

    Parameters
    ----------
    settings : OutputSettings
    ltp : LocalTangentPlane
        The run's NED origin.
    gate_probability : float
        The filter's gate (for the ESTIMATOR_STATUS test ratios).
    gps_gap_s : float
        How long after an accepted position the estimate counts as GPS aided.
    compensation : str
        Compensation in use (for NGNAV_ARRAY_HEALTH).
    """

    def __init__(
        self,
        settings: OutputSettings,
        ltp: LocalTangentPlane,
        gate_probability: float,
        gps_gap_s: float,
        compensation: str,
    ) -> None:
        self.settings = settings
        self.ltp = ltp
        self._g1 = float(chi2.ppf(gate_probability, 1))
        self._g2 = float(chi2.ppf(gate_probability, 2))
        self._g3 = float(chi2.ppf(gate_probability, 3))
        self._gap_s = gps_gap_s if gps_gap_s > 0 else 5.0
        self._comp = _COMPENSATION_IDS.get(compensation, mavlink.NGNAV_COMPENSATION_NONE)
        self._period_us = {
            k: (round(1e6 / hz) if hz > 0 else 0) for k, hz in settings.rates_hz.items()
        }
        self._next_us: dict[str, int | None] = dict.fromkeys(self._period_us)
        self.sent: dict[str, int] = dict.fromkeys(self._period_us, 0)

    def _due(self, name: str, t_us: int) -> bool:
        period = self._period_us[name]
        if period == 0:
            return False
        nxt = self._next_us[name]
        if nxt is not None and t_us < nxt:
            return False
        # the next slot on the stream's grid, never behind the epoch
        self._next_us[name] = (t_us // period + 1) * period
        self.sent[name] += 1
        return True

    def epoch(
        self, est: NavEstimate, unix_usec: int | None = None
    ) -> list[mavlink.MAVLink_message]:
        """The messages due at the epoch ``est``.

        ``unix_usec`` is SYSTEM_TIME's wall clock (None: the run clock on the
        tlog epoch base).
        """
        from telemetry.tlog import EPOCH_BASE_US

        t_us = round(est.t_s * 1e6)
        ms = _ms(t_us)
        out: list[mavlink.MAVLink_message] = []
        if self._due("heartbeat", t_us):
            # the epoch's own state: not valid (a lost track, a start again not yet
            # trusted) or a channel failing a health test is CRITICAL, as a live link's
            # idle heartbeat says (telemetry.session.StreamSession.heartbeat_message)
            ok = est.valid and not est.faulty_channels
            status = mavlink.MAV_STATE_ACTIVE if ok else mavlink.MAV_STATE_CRITICAL
            out.append(self.settings.heartbeat(status))
        if self._due("system_time", t_us):
            unix = EPOCH_BASE_US + t_us if unix_usec is None else int(unix_usec)
            out.append(mavlink.MAVLink_system_time_message(unix, ms))
        q = est.q_nb
        w = est.omega_b_rps
        pos, vel = est.pos_ned_m, est.vel_ned_mps
        rpy = euler_from_quat(q)
        if self._due("attitude_quaternion", t_us):
            out.append(
                mavlink.MAVLink_attitude_quaternion_message(
                    ms, *(float(x) for x in q), *(float(x) for x in w), [0.0, 0.0, 0.0, 0.0]
                )
            )
        if self._due("attitude", t_us):
            out.append(
                mavlink.MAVLink_attitude_message(
                    ms, *(float(x) for x in rpy), *(float(x) for x in w)
                )
            )
        if self._due("local_position_ned", t_us):
            out.append(
                mavlink.MAVLink_local_position_ned_message(
                    ms, *(float(x) for x in pos), *(float(x) for x in vel)
                )
            )
        if self._due("global_position_int", t_us):
            lat, lon, alt = self.ltp.to_geodetic(pos[None, :])
            yaw = float(rpy[2])
            hdg = round(math.degrees(yaw) * 100.0) % 36000
            out.append(
                mavlink.MAVLink_global_position_int_message(
                    ms,
                    _int(float(lat[0]) * 1e7, 31),
                    _int(float(lon[0]) * 1e7, 31),
                    _int(float(alt[0]) * 1000.0, 31),
                    _int(-float(pos[2]) * 1000.0, 31),
                    *(_int(float(v) * 100.0, 15) for v in vel),
                    hdg,
                )
            )
        cov = est.cov_nav
        if self._due("odometry", t_us):
            pose, twist = odometry_covariances(q, vel, cov, rpy)
            v_b = dcm_from_quat(q).T @ vel
            resets = est.resets
            out.append(
                mavlink.MAVLink_odometry_message(
                    t_us,
                    mavlink.MAV_FRAME_LOCAL_NED,
                    mavlink.MAV_FRAME_BODY_FRD,
                    *(float(x) for x in pos),
                    [float(x) for x in q],
                    *(float(x) for x in v_b),
                    *(float(x) for x in w),
                    upper_triangle(pose),
                    upper_triangle(twist),
                    resets % 256,
                    mavlink.MAV_ESTIMATOR_TYPE_GPS_INS,
                    0,
                )
            )
        if self._due("estimator_status", t_us):
            out.append(self._status(est, t_us, cov))
        if self._due("array_health", t_us):
            out.append(self._health(est, t_us))
        return out

    def _status(self, est: NavEstimate, t_us: int, cov: np.ndarray) -> mavlink.MAVLink_message:
        g = est.last_gps
        flags = (
            mavlink.ESTIMATOR_ATTITUDE
            | mavlink.ESTIMATOR_VELOCITY_HORIZ
            | mavlink.ESTIMATOR_VELOCITY_VERT
            | mavlink.ESTIMATOR_POS_HORIZ_REL
            | mavlink.ESTIMATOR_POS_VERT_ABS
            | mavlink.ESTIMATOR_PRED_POS_HORIZ_REL
            | mavlink.ESTIMATOR_PRED_POS_HORIZ_ABS
        )
        if not est.valid:
            flags = 0  # started again from a lost track: no solution to vouch for yet
        aided = est.t_s - est.t_last_position_fix_s <= self._gap_s
        if aided and est.valid:
            flags |= mavlink.ESTIMATOR_POS_HORIZ_ABS
        vel_r = pos_h = pos_v = 0.0
        if g is not None:
            vel_r = _ratio(g.nis_vel, self._g3)
            pos_h = _ratio(g.nis_pos_h, self._g2)
            pos_v = _ratio(g.nis_pos_v, self._g1)
            if not g.pos_accepted:
                flags |= mavlink.ESTIMATOR_GPS_GLITCH
        return mavlink.MAVLink_estimator_status_message(
            t_us,
            flags,
            vel_r,
            pos_h,
            pos_v,
            0.0,
            0.0,
            0.0,
            float(math.sqrt(max(0.0, cov[0, 0] + cov[1, 1]))),
            float(math.sqrt(max(0.0, cov[2, 2]))),
        )

    def _health(self, est: NavEstimate, t_us: int) -> mavlink.MAVLink_message:
        res = np.zeros(3)
        y = est.rate_innovation if est.rate_innovation is not None else np.zeros(0)
        res[: min(3, y.shape[0])] = y[:3]
        flags = mavlink.NGNAV_HEALTH_ALIGNED
        if est.t_s - est.t_last_position_fix_s <= self._gap_s:
            flags |= mavlink.NGNAV_HEALTH_GPS_AIDED
        if est.rate_rejected:
            flags |= mavlink.NGNAV_HEALTH_RATE_REJECTED
        if est.forecast_fallback:
            flags |= mavlink.NGNAV_HEALTH_FORECAST_FALLBACK
        held = est.held_samples
        nis = est.rate_nis
        return mavlink.MAVLink_ngnav_array_health_message(
            t_us,
            [float(x) for x in res],
            float(nis) if math.isfinite(nis) else float("nan"),
            min(held, 2**32 - 1),
            min(est.rate_updates_rejected, 2**32 - 1),
            min(est.forecast_fallbacks, 2**32 - 1),
            est.faulty_channels & 0xFFFF,
            flags,
            self._comp,
        )


def _int(x: float, bits: int) -> int:
    """Round to a signed integer field of ``bits`` + 1 bits, saturating (0 for NaN)."""
    if not math.isfinite(x):
        return 0 if math.isnan(x) else (1 << bits) - 1 if x > 0 else -(1 << bits)
    return max(-(1 << bits), min((1 << bits) - 1, round(x)))


def _ratio(nis: float, gate: float) -> float:
    """A test ratio: NIS over its gate; 0 for a component not measured (NaN)."""
    return 0.0 if math.isnan(nis) else float(nis / gate)
