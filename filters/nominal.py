"""The nominal state's mechanisation, and the error's injection and resets (their Jacobians)."""

from __future__ import annotations

import numpy as np

from filters import kernels
from filters.algebra import (
    BODY_FRAME_MAX_CURVATURE_MPS,
    BODY_INJECTION_MAX_CURVATURE_MPS,
)
from filters.state import ATT, RATE
from ngnav.rotation import (
    dcm_from_quat,
    euler_from_quat,
    quat_from_euler,
)

_NO_RATES = np.zeros((0, 3))  # kernels.remove_feature_residual: no block rates


class NominalMixin:
    """Propagate the nominal state; inject corrections; reset it onto fixes."""

    # ------------------------------------------------------------- propagation
    def propagate(
        self, wdot: np.ndarray, f: np.ndarray, dt: float, sg: np.ndarray | None = None
    ) -> np.ndarray:
        """Propagate through a block of K compensated samples.

        Samples are instantaneous values at the sample times; the block runs
        from the previous sample (the last one propagated, kept by the filter;
        set by :meth:`set_last_sample` at the start) to the last sample of
        ``wdot``/``f``. Rate, velocity and position are integrated by the
        trapezoid rule, the attitude by the product of the sample rotations.

        Parameters
        ----------
        wdot, f : arrays (K, 3)
            Angular acceleration (rad/s^2) and specific force (m/s^2), FRD.
        dt : float
            Sample interval, s.
        sg : array (k, 3N), optional
            The block's sensitivity of the solved features to the sensor
            positions (:meth:`geometry_jacobian`); required with ``DR`` states.

        Returns
        -------
        omega_b_rps : array (K, 3)
            The nominal rate at each sample (for the rate measurement).
        """
        k = wdot.shape[0]
        mw, mw0, wts, wts1 = self._block_weights(k, dt)
        t = k * dt
        with_geo, dr0, axes, solve_t = self._geo_fixed
        if with_geo and sg is None:
            raise ValueError("a filter with geometry states needs the block's sg")
        quad_into = self._quad_into_features
        # rates, the attitude's rotation vector (second order, with the coning term
        # sum_s cum_s x alpha_s / 2) and the trapezoid's increments of a_n = m f_b0 + g
        # (f rotated to the block-start body frame by the running attitude), with the
        # force's and gravity's second-order means for the velocity error's frame (the
        # truth's-force sign, tried, was worse: docs/design.md, "Process model"); then
        # the block's F and Q (propagation_matrices, at force_for_jacobian's force)
        # filterpy's predict reads F and Q and keeps neither; C_nb at the block start is
        # this block's rate measurement's, the mean force its predict's: written in place
        phi, q, c0, f_n = self._fq_out
        w, self.q, self.pos, self.vel, self.w = kernels.propagate_block(
            self.q,
            self.pos,
            self.vel,
            self.w,
            self.P,
            self._g,
            self._body_frame_allowed(),
            BODY_FRAME_MAX_CURVATURE_MPS,
            self._last_wdot,
            wdot,
            self._last_f,
            f,
            self.bias,
            mw,
            mw0,
            wts,
            wts1,
            dt,
            self._fc_base,
            self._bias_effect_f,
            self.layout.bias.start,
            kernels.ABSENT if quad_into is None else quad_into,
            self._quad6_d,
            sg if with_geo else kernels.ABSENT,
            dr0,
            self.geometry_estimates(),
            axes,
            solve_t,
            self._q12_body(k, dt),
            self._q_walks(t),
            phi,
            q,
            c0,
            f_n,
        )  # and the block's last samples into _last_wdot and _last_f (its own arrays)
        self.t_s += t
        self._predict_covariance(phi, q, f_n, t)
        self._block = (k, dt, c0)  # for the rate measurement of this block
        self.counters.blocks += 1
        self.counters.samples += k
        return w

    def _block_weights(
        self, k: int, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The block integration as matrices over its K + 1 samples (cached per K, dt).

        With ``d`` (K + 1, 3) the angular accelerations at the block's sample
        times (the previous block's last one first) and ``w0`` the rate at the
        block start, the trapezoid rule gives the rates at the K sample times
        ``W d + w0``, the sample rotation vectors ``alpha_s = dt (w_s + w_s+1) / 2``
        and their running sums ``cum_s`` (s = 0..K) as rows of ``mw @ d + mw0 w0``
        (3K + 1 rows: rates, rotation vectors, running sums). ``wts`` (3, K + 1)
        turns accelerations ``a`` at the sample times into the block's velocity
        increment (trapezoid), its position increment beyond ``K dt v0``
        (trapezoid of the trapezoid) and its mean over the K new samples;
        ``wts1`` (3, 1) are their row sums (the weights of a constant).
        """
        key = (k, dt)
        got = self._weights_cache.get(key)
        if got is not None:
            return got
        h = 0.5 * dt
        tw = np.zeros((k + 1, k + 1))  # running trapezoid: value at s minus value at 0
        for s in range(1, k + 1):
            tw[s] = tw[s - 1]
            tw[s, s - 1] += h
            tw[s, s] += h
        avg = h * (np.eye(k, k + 1) + np.eye(k, k + 1, 1))  # interval mean times dt
        run = np.tril(np.ones((k + 1, k)), -1)  # running sum from 0
        mw = np.vstack([tw[1:], avg @ tw, run @ avg @ tw])
        ones = np.ones(k + 1)
        mw0 = np.concatenate([ones[1:], avg @ ones, run @ avg @ ones])[:, None]
        trap = np.full(k + 1, dt)
        trap[[0, -1]] = h
        mean = np.r_[0.0, np.full(k, 1.0 / k)]
        wts = np.vstack([tw[k], trap @ tw, mean])
        got = (mw, mw0, wts, wts.sum(axis=1)[:, None])
        self._weights_cache[key] = got
        return got

    def set_last_sample(self, wdot: np.ndarray, f: np.ndarray) -> None:
        """The compensated sample at the filter's current time (FRD; rad/s^2, m/s^2)."""
        self._last_wdot = np.array(wdot, dtype=float)
        self._last_f = np.array(f, dtype=float)

    def remove_feature_residual(
        self,
        r_b: np.ndarray,
        t_s: float,
        w_block: np.ndarray | None = None,
        dt: float = 0.0,
    ) -> np.ndarray | None:
        """Take a constant error in the last block's solved ``[wdot, f]`` out of the state.

        ``r_b`` (6,) is the error (FRD; rad/s^2 and m/s^2) the block's ``t_s``
        seconds were propagated with. It put ``r t`` into the rate,
        ``r t^2 / 2`` (body) into the attitude, ``C r t`` into the velocity and
        ``C r t^2 / 2`` into the position (``C`` the block-end attitude), for a
        residual the previous block's last sample carried too (the trapezoid's first
        interval starts there); this removes them from the nominal state. Left: the
        block's turn, the propagation's second-order attitude-covariance factor on
        ``C f`` and what an attitude residual does through gravity. The covariance is
        left as it is. With ``w_block`` (K, 3), the block's rates at its samples
        (interval ``dt``), takes the residual's ``r (s + 1) dt`` out of them in place and
        returns them.
        """
        w_blk = _NO_RATES if w_block is None else w_block
        self.w, self.q, self.vel, self.pos = kernels.remove_feature_residual(
            self.q, self.w, self.vel, self.pos, np.asarray(r_b, dtype=float), t_s, w_blk, dt
        )
        return w_block

    # -------------------------------------------------------------- internals
    def _inject(self) -> None:
        """Fold the error state into the nominal state and reset it to zero.

        Body-style (with the body-frame velocity error, and a correction small enough for
        its first-order reset), the body velocity takes the correction and the corrected
        attitude carries it. P takes the reset Jacobian ``G P G^T`` (first order): ``G = I``
        except the attitude rows (``algebra.attitude_reset_jacobian``) and, body-style, the
        velocity rows; a smoother's clone takes the same rows.
        """
        lay = self.layout
        g = self._g_rows
        (
            self.q,
            self.pos,
            self.vel,
            self.w,
            self.bias,
            self.dr,
            self.dg,
            self.aoa_b,
            self.aoa_k,
            body,
        ) = kernels.inject_error(
            self.x,
            self.P,
            self.q,
            self.pos,
            self.vel,
            self.w,
            self.bias,
            self.dr,
            self.dg,
            self.aoa_b,
            self.aoa_k,
            self._inject_offsets,
            self._body_frame_allowed(),
            BODY_FRAME_MAX_CURVATURE_MPS,
            BODY_INJECTION_MAX_CURVATURE_MPS,
            g,
        )
        if self.lag is not None:
            if body:
                self.lag.reset(g[0], g[1], g[2])
            else:
                self.lag.reset(g[0])
        self.x = np.zeros(lay.n)

    def reset_to_fix(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
    ) -> None:
        """Put position and velocity on a fix (antenna, NED): the documented fallback.

        Used after a run of rejected fixes and for the first fix after an outage (the
        caller counts which). The antenna lever arm is removed with the current attitude
        and rate; position and velocity get the fix's variances and lose their
        correlations with the other states, which keep theirs. A component the fix
        lacks (NaN) keeps its estimate and covariance (the whole velocity, while its
        error is taken in the body frame).
        """
        c = dcm_from_quat(self.q)
        pos = np.asarray(pos_ned_m, dtype=float) - c @ self.antenna_b_m
        vel = np.asarray(vel_ned_mps, dtype=float) - c @ np.cross(self.w, self.antenna_b_m)
        put = np.concatenate([np.isfinite(pos), np.isfinite(vel)])
        if not put[3:6].all() and self.in_body_frame():
            put[3:6] = False  # a body-frame velocity error has no NED component to put alone
        self.pos = np.where(put[0:3], pos, self.pos)
        self.vel = np.where(put[3:6], vel, self.vel)
        var = np.concatenate(
            [
                np.broadcast_to(np.asarray(pos_sigma_m, dtype=float), 3) ** 2,
                np.full(3, float(vel_sigma_mps) ** 2),
            ]
        )
        idx = np.flatnonzero(put)
        p = self.P.copy()
        p[idx, :] = 0.0
        p[:, idx] = 0.0
        p[idx, idx] = var[idx]
        self.P = p
        if self.lag is not None:
            self.lag.forget(idx.tolist())
        self._consec_rejects = 0
        self._consec_vel_rejects = 0
        self.t_last_position_fix = self.t_s
        self._forget_curvature()
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
        if self.lag is not None:
            self.lag.forget([8])
        self._consec_slip_rejects = 0
        self.check_covariance("heading alignment")

    def reopen_attitude(self, tilt_sigma_rad: float, rate_sigma_rps: float) -> None:
        """Documented fallback: add tilt and rate variance the filter has lost track of.

        A gyro-free array's tilt comes from integrating the rate, which comes
        from integrating the angular acceleration; when that goes wrong beyond
        its covariance (a long coast), the velocity it predicts soon fails every
        GPS gate and nothing can correct it. Adding ``tilt_sigma_rad^2`` to the
        two NED tilt variances and ``rate_sigma_rps^2`` to the three rate
        variances (heading and everything else keep theirs; adding to the
        diagonal keeps P positive definite) lets the next velocity fixes
        through to relearn them. Counted as ``attitude_reopens``.
        """
        p = self.P.copy()
        tilt = np.arange(ATT.start, ATT.start + 2)  # NED north and east tilt
        p[tilt, tilt] += tilt_sigma_rad**2
        rate = np.arange(RATE.start, RATE.stop)
        p[rate, rate] += rate_sigma_rps**2
        self.P = p
        self._consec_vel_rejects = 0
        self.counters.attitude_reopens += 1
        self.check_covariance("attitude reopened")
