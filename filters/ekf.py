"""Error-state (multiplicative) EKF: compensated nine-accelerometer array + GPS.

filterpy is the engine: every covariance step is ``filterpy.kalman.predict``
or ``filterpy.kalman.update`` (Joseph form) with the F, Q, H, R built here.
The nominal state (position, velocity, attitude quaternion, body rate,
feature biases) is propagated by the array's compensated samples:

- rate:      ``w_k = w_{k-1} + (wdot_k - b_wdot) dt``
- attitude:  ``q_k = q_{k-1} * exp((w_{k-1} + w_k) dt / 2)``
- velocity:  ``v += (C_nb (f - b_f) + g) dt``, position by the trapezoid.

Samples are processed in blocks (``filter_rate_hz``, 100 Hz by default; a
block also ends at every GPS fix time): the nominal state is propagated
sample by sample, the covariance once per block, and the block's mean
rate-quadratic terms update the rate (SPEC section 2; the information a
six-accelerometer layout lacks). The error state is injected into the nominal
state after every update and reset to zero.

Two second-order terms (SPEC section 7) are kept: the expected rotated
specific force ``E[C f] = (I + (P_att - tr(P_att) I) / 2) C f`` and the expected
products ``E[w_i w_j] = w_i w_j + P_ij``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update
from scipy.stats import chi2

from filters.state import ATT, B_F, B_WDOT, POS, RATE, VEL, StateLayout, b_quad
from ngnav.conventions import gravity_n_mps2
from ngnav.flight import quat_from_euler
from ngnav.rotation import (
    dcm_from_quat,
    euler_from_quat,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    skew,
)


class CovarianceError(RuntimeError):
    """The covariance stopped being symmetric positive definite."""


@dataclass(frozen=True)
class FilterNoise:
    """Noise model of the filter, in the solved-feature space.

    Attributes
    ----------
    feature_cov : array (k, k)
        Per-sample covariance of the solved features ``[wdot(3), f(3), quad(nq)]``.
    bias_prior_cov : array (k, k)
        Prior covariance of the feature biases (turn-on bias mapped through S).
    bias_rw_cov : array (k, k)
        Random-walk spectral density of the feature biases, per second.
    """

    feature_cov: np.ndarray
    bias_prior_cov: np.ndarray
    bias_rw_cov: np.ndarray


@dataclass
class Counters:
    """What the filter did, for the run summary."""

    blocks: int = 0
    samples: int = 0
    gps_used: int = 0
    gps_rejected_pos: int = 0
    gps_rejected_vel: int = 0
    gps_resets: int = 0
    rate_updates: int = 0
    rate_rejected: int = 0
    held_samples: int = 0


@dataclass
class GpsUpdateResult:
    """Innovation statistics of one fix: NIS of position and velocity, and acceptance."""

    nis_pos: float
    nis_vel: float
    pos_accepted: bool
    vel_accepted: bool


@dataclass
class NavFilter:
    """The GPS/array error-state EKF.

    Parameters
    ----------
    noise : FilterNoise
        Feature noise and bias model.
    quad_pairs : array (nq, 2) of int
        Body-rate component pairs ``(i, j)`` of the solved quadratic terms
        ``w_i w_j`` (e.g. products ``(1, 2), (0, 2), (0, 1)`` for the nine-cube).
    antenna_b_m : array (3,)
        GPS antenna position from the array's reference point, FRD, m.
    gate_probability : float
        Innovation gate: a fix whose NIS exceeds the chi-square quantile of
        this probability is rejected (counted). 0.9999 by default.
    rate_measurement : bool
        Use the rate-quadratic terms as a rate measurement.
    """

    noise: FilterNoise
    quad_pairs: np.ndarray
    antenna_b_m: np.ndarray
    gate_probability: float = 0.9999
    rate_measurement: bool = True
    counters: Counters = field(default_factory=Counters)

    def __post_init__(self) -> None:
        self.quad_pairs = np.asarray(self.quad_pairs, dtype=int).reshape(-1, 2)
        self.layout = StateLayout(self.quad_pairs.shape[0])
        n = self.layout.n
        k = 6 + self.layout.nq
        for name in ("feature_cov", "bias_prior_cov", "bias_rw_cov"):
            m = getattr(self.noise, name)
            if m.shape != (k, k):
                raise ValueError(f"noise.{name} must be ({k}, {k}), got {m.shape}")
        if not 0.5 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0.5, 1), got {self.gate_probability}")
        self.gate3 = float(chi2.ppf(self.gate_probability, 3))
        self.gate_q = float(chi2.ppf(self.gate_probability, max(self.layout.nq, 1)))
        self.x = np.zeros(n)
        self.P = np.eye(n)
        self.t_s = 0.0
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.w = np.zeros(3)
        self.bias = np.zeros(6 + self.layout.nq)
        self._eye = np.eye(n)
        self._g = gravity_n_mps2()
        self._sww = self.noise.feature_cov[0:3, 0:3]
        self._sff = self.noise.feature_cov[3:6, 3:6]
        self._sfw = self.noise.feature_cov[3:6, 0:3]
        self._sqq = self.noise.feature_cov[6:, 6:]
        self._consec_rejects = 0

    # ------------------------------------------------------------------ set-up
    def initialise(
        self,
        t_s: float,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        q_nb: np.ndarray,
        omega_b_rps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: np.ndarray,
        att_sigma_rad: np.ndarray,
        rate_sigma_rps: float,
    ) -> None:
        """Set the nominal state and a diagonal prior (biases from ``noise.bias_prior_cov``)."""
        self.t_s = float(t_s)
        self.pos = np.array(pos_ned_m, dtype=float)
        self.vel = np.array(vel_ned_mps, dtype=float)
        self.q = quat_normalize(np.asarray(q_nb, dtype=float))
        self.w = np.array(omega_b_rps, dtype=float)
        self.bias = np.zeros(6 + self.layout.nq)
        p = np.zeros((self.layout.n, self.layout.n))
        p[POS, POS] = np.diag(np.broadcast_to(pos_sigma_m, 3) ** 2)
        p[VEL, VEL] = np.diag(np.broadcast_to(vel_sigma_mps, 3) ** 2)
        p[ATT, ATT] = np.diag(np.broadcast_to(att_sigma_rad, 3) ** 2)
        p[RATE, RATE] = np.eye(3) * rate_sigma_rps**2
        bs = self.layout.bias
        p[bs, bs] = self.noise.bias_prior_cov
        self.P = p
        self.x = np.zeros(self.layout.n)
        self.check_covariance("initialisation")

    # ------------------------------------------------------------- propagation
    def propagate(
        self, wdot: np.ndarray, f: np.ndarray, dt: float, block_cov: np.ndarray | None = None
    ) -> np.ndarray:
        """Propagate through a block of K compensated samples.

        Parameters
        ----------
        wdot, f : arrays (K, 3)
            Angular acceleration (rad/s^2) and specific force (m/s^2), FRD.
        dt : float
            Sample interval, s.
        block_cov : array (6, 6), optional
            Covariance of an error of ``[wdot, f]`` common to all samples of
            the block (the unknown part of the geometry), added to Q.

        Returns
        -------
        omega_b_rps : array (K, 3)
            The nominal rate at each sample (for the rate measurement).
        """
        k = wdot.shape[0]
        bw, bf = self.bias[0:3], self.bias[3:6]
        w_prev = self.w
        w = w_prev + np.cumsum(wdot - bw, axis=0) * dt
        w_start = np.vstack([w_prev, w[:-1]])
        alpha = 0.5 * (w_start + w) * dt  # rotation vector of each sample interval
        # attitude at each sample's mid-interval relative to the block start (second order)
        cum = np.cumsum(alpha, axis=0) - 0.5 * alpha
        f_c = f - bf
        # rotate f_k by exp(cum_k) to the block-start body frame, to second order
        cf = np.cross(cum, f_c)
        f_b0 = f_c + cf + 0.5 * np.cross(cum, cf)
        c0 = dcm_from_quat(self.q)
        a_n = f_b0 @ c0.T
        pa = self.P[ATT, ATT]
        a_n = a_n + 0.5 * (a_n @ (pa - np.trace(pa) * np.eye(3)).T) + self._g
        v_steps = self.vel + np.cumsum(a_n, axis=0) * dt
        v_start = np.vstack([self.vel, v_steps[:-1]])
        self.pos = self.pos + 0.5 * np.sum(v_start + v_steps, axis=0) * dt
        # attitude: exact product of the sample rotations, with the coning term
        rot = np.sum(alpha, axis=0) + 0.5 * np.sum(
            np.cross(np.cumsum(alpha, axis=0) - alpha, alpha), axis=0
        )
        self.q = quat_normalize(quat_multiply(self.q, quat_from_rotvec(rot)))
        self.vel = v_steps[-1]
        self.w = w[-1]
        self.t_s += k * dt
        self._predict_covariance(k, dt, c0, np.mean(a_n, axis=0) - self._g, block_cov)
        self.counters.blocks += 1
        self.counters.samples += k
        return w

    def _predict_covariance(
        self, k: int, dt: float, c: np.ndarray, f_n: np.ndarray, block_cov: np.ndarray | None
    ) -> None:
        phi, q = self.propagation_matrices(k, dt, c, f_n, block_cov)
        self.x, self.P = kf_predict(self.x, self.P, phi, q)
        self._symmetrise()

    def propagation_matrices(
        self,
        k: int,
        dt: float,
        c: np.ndarray,
        f_n: np.ndarray,
        block_cov: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Transition F and process noise Q over a block of ``k`` samples.

        Parameters
        ----------
        k : int
            Samples in the block; ``dt`` their interval, s.
        c : array (3, 3)
            ``C_nb`` at the block start.
        f_n : array (3,)
            Mean specific force over the block, NED, m/s^2.
        """
        n = self.layout.n
        t = k * dt
        fc = np.zeros((n, n))
        fc[POS, VEL] = np.eye(3)
        fc[VEL, ATT] = -skew(f_n)
        fc[VEL, B_F] = -c
        fc[ATT, RATE] = c
        fc[RATE, B_WDOT] = -np.eye(3)
        ft = fc * t
        ft2 = ft @ ft
        phi = self._eye + ft + 0.5 * ft2 + ft2 @ ft / 6.0
        # noise of the k samples, summed exactly for constant C (see module docstring)
        s1 = k * (k - 1) / 2.0
        s2 = (k - 1) * k * (2 * k - 1) / 6.0
        cww = c @ self._sww
        cff = c @ self._sff @ c.T
        cfw = c @ self._sfw
        cfwc = cfw @ c.T
        q = np.zeros((n, n))
        q[RATE, RATE] = k * dt**2 * self._sww
        q[ATT, RATE] = s1 * dt**3 * cww
        q[ATT, ATT] = s2 * dt**4 * cww @ c.T
        q[VEL, VEL] = k * dt**2 * cff
        q[POS, VEL] = s1 * dt**3 * cff
        q[POS, POS] = s2 * dt**4 * cff
        q[VEL, RATE] = k * dt**2 * cfw
        q[VEL, ATT] = s1 * dt**3 * cfwc
        q[POS, RATE] = s1 * dt**3 * cfw
        q[POS, ATT] = s2 * dt**4 * cfwc
        bs = self.layout.bias
        q[bs, bs] = self.noise.bias_rw_cov * t
        q = np.triu(q) + np.triu(q, 1).T
        if block_cov is not None:
            gam = np.zeros((n, 6))
            gam[RATE, 0:3] = -t * np.eye(3)
            gam[ATT, 0:3] = -0.5 * t * t * c
            gam[VEL, 3:6] = -t * c
            gam[POS, 3:6] = -0.5 * t * t * c
            q = q + gam @ block_cov @ gam.T
        return phi, q

    # ------------------------------------------------------------- measurements
    def update_rate(
        self,
        quad_mean: np.ndarray,
        w_block: np.ndarray,
        k: int,
        extra_cov: np.ndarray | None = None,
    ) -> float | None:
        """Update with a block's mean solved rate-quadratic terms (nq,); returns the NIS.

        ``extra_cov`` (nq, nq) is added to the noise: an error common to the
        block's samples (the unknown part of the geometry).
        """
        nq = self.layout.nq
        if nq == 0 or not self.rate_measurement:
            return None
        pred, h = self.rate_model(w_block)
        pred = pred + self.P[RATE, RATE][self.quad_pairs[:, 0], self.quad_pairs[:, 1]]
        pred = pred + self.bias[6:]
        r = self._sqq / k if extra_cov is None else self._sqq / k + extra_cov
        y = quad_mean - pred
        s = h @ self.P @ h.T + r
        nis = float(y @ np.linalg.solve(s, y))
        if nis > self.gate_q:
            self.counters.rate_rejected += 1
            return nis
        self.x, self.P = kf_update(self.x, self.P, y, r, h)
        self._inject()
        self.counters.rate_updates += 1
        return nis

    def rate_model(self, w_block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Block-mean quadratic terms (nq,) of the rates (K, 3) and their Jacobian (nq, n).

        The rate error is the same at every sample of a block, so the Jacobian
        is the block mean of ``d(w_i w_j)/dw``; the bias block is the identity.
        """
        nq = self.layout.nq
        i, j = self.quad_pairs[:, 0], self.quad_pairs[:, 1]
        pred = np.mean(w_block[:, i] * w_block[:, j], axis=0)
        h = np.zeros((nq, self.layout.n))
        rows = np.arange(nq)
        h[rows, 9 + i] += np.mean(w_block[:, j], axis=0)
        h[rows, 9 + j] += np.mean(w_block[:, i], axis=0)
        h[:, b_quad(nq)] = np.eye(nq)
        return pred, h

    def gps_model(
        self, q_nb: np.ndarray, omega_b_rps: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Antenna offset (NED) and velocity (NED, from rotation) and their Jacobians.

        Returns ``C r``, ``C (w x r)``, ``H_pos`` (3, n), ``H_vel`` (3, n).
        """
        c = dcm_from_quat(q_nb)
        r = self.antenna_b_m
        cr = c @ r
        cwr = c @ np.cross(omega_b_rps, r)
        n = self.layout.n
        hp = np.zeros((3, n))
        hp[:, POS] = np.eye(3)
        hp[:, ATT] = -skew(cr)
        hv = np.zeros((3, n))
        hv[:, VEL] = np.eye(3)
        hv[:, ATT] = -skew(cwr)
        hv[:, RATE] = -c @ skew(r)
        return cr, cwr, hp, hv

    def update_gps(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
        dt_fix_s: float = 0.0,
    ) -> GpsUpdateResult:
        """Gate and apply one GPS fix (antenna position and velocity, NED).

        ``dt_fix_s`` is the fix time minus the filter time (|dt| below one
        array sample); the prediction is moved by ``v dt``.
        """
        cr, _, hp, _ = self.gps_model(self.q, self.w)
        rp = np.diag(np.broadcast_to(np.asarray(pos_sigma_m, dtype=float), 3) ** 2)
        yp = pos_ned_m - (self.pos + cr + self.vel * dt_fix_s)
        nis_p, ok_p = self._gated_update(yp, rp, hp)
        _, cwr, _, hv = self.gps_model(self.q, self.w)  # after the position update
        rv = np.eye(3) * float(vel_sigma_mps) ** 2
        yv = vel_ned_mps - (self.vel + cwr)
        nis_v, ok_v = self._gated_update(yv, rv, hv)
        self.counters.gps_used += int(ok_p or ok_v)
        self.counters.gps_rejected_pos += int(not ok_p)
        self.counters.gps_rejected_vel += int(not ok_v)
        self._consec_rejects = 0 if ok_p else self._consec_rejects + 1
        return GpsUpdateResult(nis_p, nis_v, ok_p, ok_v)

    def _gated_update(self, y: np.ndarray, r: np.ndarray, h: np.ndarray) -> tuple[float, bool]:
        s = h @ self.P @ h.T + r
        nis = float(y @ np.linalg.solve(s, y))
        if not np.isfinite(nis) or nis > self.gate3:
            return nis, False
        self.x, self.P = kf_update(self.x, self.P, y, r, h)
        self._inject()
        return nis, True

    @property
    def consecutive_position_rejects(self) -> int:
        """Fixes in a row whose position was rejected (a divergence sign)."""
        return self._consec_rejects

    def reset_to_fix(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
    ) -> None:
        """Documented fallback: put position and velocity on a fix after a run of rejections."""
        cr = dcm_from_quat(self.q) @ self.antenna_b_m
        self.pos = np.asarray(pos_ned_m, dtype=float) - cr
        self.vel = np.asarray(vel_ned_mps, dtype=float).copy()
        n = self.layout.n
        keep = np.ones(n, dtype=bool)
        keep[0:6] = False
        p = self.P.copy()
        p[~keep, :] = 0.0
        p[:, ~keep] = 0.0
        p[POS, POS] = np.diag(np.broadcast_to(np.asarray(pos_sigma_m, dtype=float), 3) ** 2)
        p[VEL, VEL] = np.eye(3) * float(vel_sigma_mps) ** 2
        self.P = p
        self._consec_rejects = 0
        self.counters.gps_resets += 1
        self.check_covariance("GPS reset")

    def set_heading(self, yaw_rad: float, sigma_rad: float) -> None:
        """Replace the heading (keeping roll and pitch); its variance becomes ``sigma^2``."""
        roll, pitch, _ = euler_from_quat(self.q)
        self.q = quat_from_euler(roll, pitch, yaw_rad)
        # the heading error is about NED down: decorrelate it and set its variance
        p = self.P.copy()
        p[8, :] = 0.0
        p[:, 8] = 0.0
        p[8, 8] = sigma_rad**2
        self.P = p
        self.check_covariance("heading alignment")

    # -------------------------------------------------------------- internals
    def _inject(self) -> None:
        dx = self.x
        self.pos = self.pos + dx[POS]
        self.vel = self.vel + dx[VEL]
        dth = dx[ATT]
        self.q = quat_normalize(quat_multiply(quat_from_rotvec(dth), self.q))
        self.w = self.w + dx[RATE]
        self.bias = self.bias + dx[self.layout.bias]
        # reset Jacobian of the attitude error (first order)
        g = self._eye.copy()
        g[ATT, ATT] -= 0.5 * skew(dth)
        self.P = g @ self.P @ g.T
        self.x = np.zeros_like(self.x)
        self._symmetrise()

    def _symmetrise(self) -> None:
        self.P = 0.5 * (self.P + self.P.T)

    def check_covariance(self, where: str) -> None:
        """Raise :class:`CovarianceError` unless P is finite, symmetric and positive definite."""
        p = self.P
        if not np.all(np.isfinite(p)):
            raise CovarianceError(f"covariance not finite after {where} at t = {self.t_s:.3f} s")
        if not np.allclose(p, p.T, rtol=1e-9, atol=1e-15):
            raise CovarianceError(f"covariance not symmetric after {where} at t = {self.t_s:.3f} s")
        try:
            np.linalg.cholesky(p)
        except np.linalg.LinAlgError:
            ev = np.linalg.eigvalsh(p)
            raise CovarianceError(
                f"covariance not positive definite after {where} at t = {self.t_s:.3f} s "
                f"(smallest eigenvalue {ev[0]:.3e})"
            ) from None
