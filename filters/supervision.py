"""Supervision: every gate, rejection count, reset and reopen rule, and their thresholds.

The models (:mod:`filters.measurements`, :mod:`filters.constraints`) say what a
measurement predicts; this module says when to believe it, and what to do when the
filter's own errors no longer match its covariance. Every threshold is here, each with
its reason (measured ones in ``docs/design.md``, "Heuristics and thresholds").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from filters import kernels
from filters.state import ATT
from filters.updates import Measurement, quadratic_form
from filters.vehicle_model import (
    VERTICAL,
    constraint_axes,
)
from ngnav.errors import CovarianceError
from ngnav.rotation import (
    dcm_from_quat,
    euler_from_quat,
)

#: The innovation gate: a measurement whose NIS exceeds the chi-square quantile of this
#: probability (for its own dof) is rejected and counted: about one good fix in 10^4.
GATE_PROBABILITY = 0.9999
#: The first fix after this long without an accepted GPS position is not fused but puts
#: position and velocity on it (PX4 EKF2's reset after a fusion timeout): a long coast
#: builds its cross-covariances on a drifted trajectory, and fusing a large innovation
#: through them left ``uav-survey``'s vertical velocity several sigma off for 30 s, s.
GPS_GAP_RESET_S = 5.0
#: Consecutive rejected GPS positions after which the filter is put back on the fix.
RESET_AFTER_REJECTS = 25
#: Consecutive rejected GPS velocities after which tilt and rate variance is added back.
REOPEN_AFTER_VELOCITY_REJECTS = 10
#: Tilt 1-sigma added back then (per NED tilt axis), rad.
REOPEN_TILT_SIGMA_RAD = float(np.deg2rad(10.0))
#: Rate 1-sigma added back then (per body axis), rad/s.
REOPEN_RATE_SIGMA_RPS = float(np.deg2rad(2.0))
#: A second reopen within this time is a divergence (:class:`filters.ekf.LostTrackError`), s.
REOPEN_MIN_INTERVAL_S = 10.0
#: GPS velocities rejected in a row after which the vehicle model (sideslip and angle
#: of attack) pauses until one is accepted again. A state the velocity fixes contradict
#: has a covariance that no longer describes its errors, and a tight constraint fused
#: through it moves the rates by what those wrong correlations say: on ``tactical``
#: started with its pitch 15 deg off but told as 1 deg, one angle-of-attack update
#: put the pitch right and the pitch rate 21 deg/s off (2 deg/s sigma).
MODEL_PAUSE_AFTER_VELOCITY_REJECTS = 2
#: Tilt 1-sigma (either horizontal axis) beyond which a GPS fix finds the track lost, deg.
#: The error-state model is linear in the attitude error; with tilts this unknown its
#: transition is taken about an attitude that may be anywhere, and a start again from the
#: GPS acceleration and the array's force (``filters.recovery``) knows the tilt to 5 deg.
#: The healthy scenarios' coasts stay under 10 deg; at the paper's grade (``ic3022``)
#: ``uav-survey``'s 30 s coast ends at 100-200 deg, and fused on from there run 0 kept
#: velocity sigmas of 16 m/s to 10^6 m/s for 35 s of accepted fixes.
#: The same limit holds the heading of a vehicle that flies along its course (a fixed-wing,
#: or ``initial.heading_source = "gps"``) at a fix whose course a start again can take: a 41
#: deg heading 1-sigma at the end of ``uav-survey``'s coast at ``mems-consumer`` (tilt 25 deg,
#: under the limit) was pulled by the next fixes' linearised updates to a heading 14 deg off
#: under a 1 deg sigma (run 9: attitude NEES 430 for 20 s, 14-22 to the flight's end).
LOST_TILT_SIGMA_DEG = 30.0
#: Horizontal speed above which a GPS course can set the heading, m/s.
COURSE_MIN_SPEED_MPS = 5.0

#: Consecutive fixes after an outage that fail the position gate before the filter is put
#: on the fix anyway. The first fix after an outage resets position and velocity when it
#: passes the gate (a glitch then is one fix off, rejected); but a coast that ended more
#: sure of itself than its errors fails the gate on every fix, and waiting for the general
#: run of rejections (the pipeline's ``RESET_AFTER_REJECTS``, 5 s at 5 Hz) left
#: ``uav-survey`` run 11 off for 5 s after its outage. Three fixes in a row that disagree
#: with the coast are the receiver, not a glitch.
GAP_RESET_AFTER_REJECTS = 3


def tilt_sigma_rad(p: np.ndarray) -> float:
    """The tilt's 1-sigma, rad: the larger of the two horizontal NED attitude axes of the
    error covariance ``p`` (n, n)."""
    ia = ATT.start
    return float(np.sqrt(max(p[ia, ia], p[ia + 1, ia + 1])))


def heading_sigma_rad(p: np.ndarray) -> float:
    """The heading's 1-sigma, rad: the NED down attitude axis of the error covariance
    ``p`` (n, n)."""
    ia = ATT.start + 2
    return float(np.sqrt(p[ia, ia]))


@dataclass
class Counters:
    """What the filter did, for the run summary."""

    blocks: int = 0
    samples: int = 0
    gps_used: int = 0
    gps_rejected_pos: int = 0
    gps_rejected_vel: int = 0
    gps_resets: int = 0
    gps_gap_resets: int = 0
    rate_updates: int = 0
    rate_rejected: int = 0
    held_samples: int = 0
    sideslip_used: int = 0
    sideslip_rejected: int = 0
    aoa_used: int = 0
    aoa_rejected: int = 0
    heading_resets: int = 0
    course_updates: int = 0
    attitude_reopens: int = 0
    coast_model_updates: int = 0
    handover_model_updates: int = 0
    zero_rate_used: int = 0
    zero_rate_rejected: int = 0


class SupervisionMixin:
    """Gated updates, runs of rejections, the heading check, covariance checks."""

    def _gated_update(
        self, meas: Measurement, gate: float | None = None, s: np.ndarray | None = None
    ) -> tuple[float, bool]:
        """Fuse ``meas`` if its NIS passes ``gate`` (default the 3-dof one); (NIS, fused).

        ``s`` is the innovation covariance when the caller has it already.
        """
        nis = quadratic_form(meas.z, meas.innovation_cov(self.P) if s is None else s)
        return nis, self._fuse_if_passes(meas, nis, gate)

    def _fuse_if_passes(self, meas: Measurement, nis: float, gate: float | None = None) -> bool:
        """Fuse ``meas``, whose NIS is ``nis``, if that passes ``gate`` (default the 3-dof
        one); whether it was fused."""
        if not math.isfinite(nis) or nis > (self.gate3 if gate is None else gate):
            return False
        self._apply(meas)
        return True

    @property
    def consecutive_position_rejects(self) -> int:
        """Fixes in a row whose position was rejected (a divergence sign)."""
        return self._consec_rejects

    @property
    def consecutive_velocity_rejects(self) -> int:
        """GPS velocities in a row that failed the gate (the tilt or rate is lost)."""
        return self._consec_vel_rejects

    @property
    def consecutive_sideslip_rejects(self) -> int:
        """Sideslip updates in a row that failed the gate (a heading far off the course)."""
        return self._consec_slip_rejects

    def flies_backwards(self) -> bool:
        """Whether the nominal velocity points behind the body (``x`` of ``C^T v`` < 0):
        never so for a vehicle with the no-sideslip models moving at a course's speed."""
        return float(dcm_from_quat(self.q)[:, 0] @ self.vel) < 0.0

    def check_heading_against_course(self, course_rad: float, sigma_rad: float) -> bool:
        """Documented fallback: put the heading on a GPS course it contradicts.

        For a vehicle flying with no sideslip the heading is the course of its
        ground velocity. If the heading differs from ``course_rad`` by more than
        the 1-dof gate allows (``d^2 / (P_yaw + sigma^2)``, ``d`` wrapped to
        (-pi, pi]), :meth:`set_heading` puts it on the course with ``sigma_rad``
        and the reset is counted. The zero-sideslip model cannot catch this
        itself: a heading 180 deg off the course also has zero lateral velocity,
        and a heading tens of degrees off fails every sideslip gate. Returns
        True if the heading was reset.
        """
        # the course the attitude implies: the horizontal direction of the wind x
        # axis (the body x axis without the AOA state, whose heading is the yaw)
        _, t_b = constraint_axes(VERTICAL, self.aoa)
        x_n = dcm_from_quat(self.q) @ t_b
        d = float(np.angle(np.exp(1j * (np.arctan2(x_n[1], x_n[0]) - course_rad))))
        yaw_i = ATT.start + 2  # the heading error is about NED down
        if d * d <= self.gate1 * (self.P[yaw_i, yaw_i] + sigma_rad**2):
            return False
        _, _, yaw = euler_from_quat(self.q)
        self.set_heading(yaw - d, sigma_rad)  # a turn about NED down by -d
        self.counters.heading_resets += 1
        return True

    def _symmetrise(self) -> None:
        self.P = kernels.symmetrised(self.P)

    def check_covariance(self, where: str, full: bool = True) -> None:
        """Raise :class:`CovarianceError` unless P is finite, symmetric and positive definite.

        ``full=False`` is the per-block check: finite with a positive diagonal
        (P is symmetrised after every step). The full check adds symmetry and
        a Cholesky factorisation (positive definite); the pipeline runs it at
        every GPS fix and once a second.
        """
        p = self.P
        flaw = kernels.covariance_flaw(p)
        if flaw == 1:
            raise CovarianceError(f"covariance not finite after {where} at t = {self.t_s:.3f} s")
        if not full:
            if flaw == 2:
                raise CovarianceError(
                    f"covariance has a non-positive variance after {where} at t = {self.t_s:.3f} s"
                )
            return
        if np.abs(p - p.T).max() > 1e-9 * np.abs(p).max():
            raise CovarianceError(f"covariance not symmetric after {where} at t = {self.t_s:.3f} s")
        try:
            np.linalg.cholesky(p)
        except np.linalg.LinAlgError:
            ev = np.linalg.eigvalsh(p)
            raise CovarianceError(
                f"covariance not positive definite after {where} at t = {self.t_s:.3f} s "
                f"(smallest eigenvalue {ev[0]:.3e})"
            ) from None
