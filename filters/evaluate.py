"""Errors against truth, NEES and NIS, chi-square bounds, and summary tables.

Error conventions (truth minus estimate) follow :mod:`filters.state`; the
attitude error is the NED rotation vector of ``q_true * conj(q_est)``. NEES of
a block is ``e^T P^-1 e`` with the filter's covariance of that block; over R
Monte Carlo runs its average at an epoch, times R, is chi-square with
``R * dim`` degrees of freedom when the filter is consistent, so the two-sided
95 % bounds are ``chi2.ppf([0.025, 0.975], R * dim) / R``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from filters.state import NEES_BLOCKS
from ngnav.records import Estimates, FlightTruth
from ngnav.rotation import (
    dcm_from_quat,
    euler_from_quat,
    quat_conjugate,
    quat_multiply,
    quat_to_rotvec,
)


@dataclass(frozen=True)
class RunErrors:
    """Errors at each estimate epoch (E,): truth minus estimate."""

    t_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    att_ned_rad: np.ndarray
    rpy_deg: np.ndarray
    rate_b_rps: np.ndarray

    def stacked(self) -> np.ndarray:
        """The 12 navigation errors (E, 12) in the state layout's order."""
        return np.hstack([self.pos_ned_m, self.vel_ned_mps, self.att_ned_rad, self.rate_b_rps])


def truth_indices(truth: FlightTruth, t_s: np.ndarray) -> np.ndarray:
    """Indices of the truth samples at the times ``t_s`` (which must be sample times)."""
    dt = float(np.median(np.diff(truth.t_s)))
    idx = np.rint((t_s - truth.t_s[0]) / dt).astype(int)
    if np.any(idx < 0) or np.any(idx >= truth.t_s.shape[0]):
        raise ValueError("estimate times fall outside the truth")
    if not np.allclose(truth.t_s[idx], t_s, atol=dt * 1e-3):
        raise ValueError("estimate times are not truth sample times")
    return idx


def run_errors(est: Estimates, truth: FlightTruth) -> RunErrors:
    """Errors of an estimate sequence against the truth."""
    i = truth_indices(truth, est.t_s)
    q_t = truth.q_nb[i]
    att = quat_to_rotvec(quat_multiply(q_t, quat_conjugate(est.q_nb)))
    rpy = np.rad2deg(euler_from_quat(q_t) - euler_from_quat(est.q_nb))
    rpy = (rpy + 180.0) % 360.0 - 180.0
    return RunErrors(
        est.t_s,
        truth.pos_ned_m[i] - est.pos_ned_m,
        truth.vel_ned_mps[i] - est.vel_ned_mps,
        att,
        rpy,
        truth.omega_b_rps[i] - est.omega_b_rps,
    )


#: The issue's consistency target: each block's run-averaged statistic inside its 95 %
#: bounds on at least this share of epochs.
TARGET_SHARE = 0.9

#: Below this speed the truth's angle of attack is not defined (m/s).
AOA_MIN_SPEED_MPS = 5.0


def truth_aoa_rad(truth: FlightTruth, idx: np.ndarray) -> np.ndarray:
    """The truth's angle of attack (rad) at sample indices ``idx``: the body x-z angle
    of its velocity, ``atan2(v_bz, v_bx)``; NaN below :data:`AOA_MIN_SPEED_MPS`."""
    v = truth.vel_ned_mps[idx]
    v_b = np.einsum("eji,ej->ei", dcm_from_quat(truth.q_nb[idx]), v)
    a = np.arctan2(v_b[:, 2], v_b[:, 0])
    return np.where(np.linalg.norm(v, axis=1) >= AOA_MIN_SPEED_MPS, a, np.nan)


def aoa_nees(est: Estimates, truth: FlightTruth) -> np.ndarray | None:
    """Angle-of-attack NEES per epoch (E,), 1 dof (NaN where the truth has none or
    the filter's sigma is 0, on the wheels), or None when the filter does not carry
    the state."""
    if est.aoa_rad is None:
        return None
    e = truth_aoa_rad(truth, truth_indices(truth, est.t_s)) - est.aoa_rad
    sd = est.aoa_sigma_rad
    # on the wheels (lift-off blend 0) the angle is known to be 0: no statistic there
    return np.where(sd > 0, (e / np.where(sd > 0, sd, 1.0)) ** 2, np.nan)


def nees(errors: RunErrors, cov_nav: np.ndarray) -> dict[str, np.ndarray]:
    """NEES per epoch (E,) for each block of :data:`filters.state.NEES_BLOCKS` and ``all``.

    NaN where the block's covariance is not finite or not positive definite: the epochs of
    a lost track, and the few a failing filter records between its covariance checks (the
    full check runs at every fix and once a second) before it stops.
    """
    e = errors.stacked()
    out = {}
    for name, sl in {**NEES_BLOCKS, "all": slice(0, 12)}.items():
        ee, cc = e[:, sl], cov_nav[:, sl, sl]
        sd = np.sqrt(np.abs(np.einsum("eii->ei", cc)))
        ok = np.all(np.isfinite(cc), axis=(1, 2)) & np.all(np.isfinite(ee), axis=1)
        ok &= np.all(sd > 0.0, axis=1)
        # on the correlations (the units drop out): positive definite to double precision
        s_ok = sd[ok]
        lam, vec = np.linalg.eigh(cc[ok] / s_ok[:, :, None] / s_ok[:, None, :])
        pd = lam[:, 0] > 1e-12
        z2 = np.einsum("eij,ei->ej", vec, ee[ok] / s_ok) ** 2 / np.where(pd[:, None], lam, 1.0)
        val = np.full(e.shape[0], np.nan)
        val[np.flatnonzero(ok)[pd]] = z2[pd].sum(axis=1)
        out[name] = val
    return out


def chi2_bounds(dim: int, runs: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds of the average of ``runs`` chi-square(dim) values."""
    a = (1.0 - level) / 2.0
    return (float(chi2.ppf(a, runs * dim) / runs), float(chi2.ppf(1 - a, runs * dim) / runs))


def share_inside(avg: np.ndarray, dim: int, runs: int) -> float:
    """Share of epochs whose run-averaged statistic lies inside the 95 % bounds."""
    lo, hi = chi2_bounds(dim, runs)
    ok = np.isfinite(avg)
    return float(np.mean((avg[ok] >= lo) & (avg[ok] <= hi)))


@dataclass(frozen=True)
class ErrorSummary:
    """RMS and worst of the headline errors of one run (units in the names)."""

    horiz_rms_m: float
    horiz_max_m: float
    vert_rms_m: float
    vert_max_m: float
    vel_rms_mps: float
    vel_max_mps: float
    roll_rms_deg: float
    roll_max_deg: float
    pitch_rms_deg: float
    pitch_max_deg: float
    yaw_rms_deg: float
    yaw_max_deg: float
    rate_rms_dps: float
    rate_max_dps: float


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(x**2))) if np.any(np.isfinite(x)) else float("nan")


def _max(x: np.ndarray) -> float:
    return float(np.nanmax(np.abs(x))) if np.any(np.isfinite(x)) else float("nan")


def summarise(errors: RunErrors, mask: np.ndarray | None = None) -> ErrorSummary:
    """Summary over the epochs in ``mask`` (all by default)."""
    m = np.ones(errors.t_s.shape, dtype=bool) if mask is None else mask
    h = np.hypot(errors.pos_ned_m[m, 0], errors.pos_ned_m[m, 1])
    v = np.linalg.norm(errors.vel_ned_mps[m], axis=1)
    r = np.rad2deg(np.linalg.norm(errors.rate_b_rps[m], axis=1))
    rpy = errors.rpy_deg[m]
    return ErrorSummary(
        _rms(h),
        _max(h),
        _rms(errors.pos_ned_m[m, 2]),
        _max(errors.pos_ned_m[m, 2]),
        _rms(v),
        _max(v),
        _rms(rpy[:, 0]),
        _max(rpy[:, 0]),
        _rms(rpy[:, 1]),
        _max(rpy[:, 1]),
        _rms(rpy[:, 2]),
        _max(rpy[:, 2]),
        _rms(r),
        _max(r),
    )


def euler_variances(q_nb: np.ndarray, p_att: np.ndarray) -> np.ndarray:
    """Variances (E, 3) of roll, pitch and yaw (ZYX Euler, rad^2) from the NED attitude
    error's covariance ``p_att`` (E, 3, 3) at the attitudes ``q_nb`` (E, 4).

    ``dtheta_ned = M [droll, dpitch, dyaw]`` with ``M = [Rz Ry e1, Rz e2, e3]`` (the
    NED directions the three Euler angles turn about), so the angles' covariance is
    ``M^-1 P M^-T``. Roll and pitch are the north and east errors only when the yaw is
    zero: flying east, roll is the east error.
    """
    _, pitch, yaw = euler_from_quat(q_nb).T
    cp, sp, cy, sy = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    m = np.zeros((q_nb.shape[0], 3, 3))
    m[:, 0, 0], m[:, 1, 0], m[:, 2, 0] = cy * cp, sy * cp, -sp
    m[:, 0, 1], m[:, 1, 1] = -sy, cy
    m[:, 2, 2] = 1.0
    m_inv = np.linalg.inv(m)
    return np.einsum("eij,ejk,eik->ei", m_inv, p_att, m_inv)


def bound_summary(
    cov: np.ndarray, mask: np.ndarray | None = None, q_nb: np.ndarray | None = None
) -> dict[str, float]:
    """RMS that a covariance sequence (E, 12, 12) predicts, in the summary's units.

    With the attitudes ``q_nb`` (E, 4) the roll/pitch/yaw bounds are the Euler angles'
    (:func:`euler_variances`); without, the NED attitude variances (north, east, down),
    which are roll, pitch and yaw only while the yaw is near zero.
    """
    m = np.ones(cov.shape[0], dtype=bool) if mask is None else mask
    d = np.einsum("eii->ei", cov[m])
    att_rms_deg = float(np.rad2deg(np.sqrt(np.mean(d[:, 6:9].sum(axis=1)))))  # the NED error
    if q_nb is not None:
        d = d.copy()
        d[:, 6:9] = euler_variances(q_nb[m], cov[m][:, 6:9, 6:9])
    return {
        "horiz_rms_m": float(np.sqrt(np.mean(d[:, 0] + d[:, 1]))),
        "vert_rms_m": float(np.sqrt(np.mean(d[:, 2]))),
        "vel_rms_mps": float(np.sqrt(np.mean(d[:, 3:6].sum(axis=1)))),
        "roll_rms_deg": float(np.rad2deg(np.sqrt(np.mean(d[:, 6])))),
        "pitch_rms_deg": float(np.rad2deg(np.sqrt(np.mean(d[:, 7])))),
        "yaw_rms_deg": float(np.rad2deg(np.sqrt(np.mean(d[:, 8])))),
        "rate_rms_dps": float(np.rad2deg(np.sqrt(np.mean(d[:, 9:12].sum(axis=1))))),
        "att_rms_deg": att_rms_deg,
    }
