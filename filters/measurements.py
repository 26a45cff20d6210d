"""The array's and the GPS's measurement models: each gives (z, H, R) for filterpy's update."""

from __future__ import annotations

import numpy as np

from filters import kernels
from filters.state import ATT, RATE
from filters.supervision import GAP_RESET_AFTER_REJECTS
from filters.updates import Measurement, quadratic_form
from ngnav.records import GpsUpdateResult
from ngnav.rotation import dcm_from_quat

_NO_VAR = np.zeros(0)  # kernels.rate_model: the rate not shrunk
_NO_HELD = np.zeros(0, dtype=bool)  # kernels.rate_update: no sample held


class MeasurementsMixin:
    """Rate products, zero rate at rest, static biases, GPS position and velocity."""

    def rate_model(
        self,
        w_block: np.ndarray,
        sg: np.ndarray | None = None,
        rate_var: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Block-mean quadratic terms (nq,) of the rates (K, 3) and their Jacobian (nq, n).

        The rate error is the same at every sample of a block, so the Jacobian
        is the block mean of ``d(w_i w_j)/dw``; the bias block is the identity,
        the ``DR`` block the quadratic rows of ``sg``.

        ``rate_var`` (3,), the variances of the rate estimate, shrinks each
        rate in the Jacobian to ``sign(w) sqrt(max(0, w^2 - var))``, the
        unbiased estimate of its size. A product ``w_i w_j`` tells about
        ``w_j`` only as much as the *true* ``w_i`` is large; near zero rate an
        estimate ``w_i`` made of its own error would claim information that
        the measurement does not hold (a straight flight's yaw rate would
        look measured and the heading would turn overconfident).

        With ``quad_feedback`` the rate columns also carry the forecast
        compensation's return of the rate error, ``E_q J6(w)``.
        """
        return kernels.rate_model(
            np.asarray(w_block, dtype=float),
            self.quad_pairs,
            _NO_VAR if rate_var is None else np.asarray(rate_var, dtype=float),
            *self._rate_jacobian_parts(sg),
        )

    def _rate_jacobian_parts(self, sg: np.ndarray | None) -> tuple:
        """What the rate products' Jacobian is built from (``kernels.rate_model``'s
        arguments after the shrink): its constant part, the products' derivatives, the
        aided products' and, with geometry states, theirs (``sg``)."""
        sg, dr0, geo, axes, solve_t = self._geometry_args(sg)
        return (*self._rate_fixed, sg, geo, axes, solve_t, dr0)

    def measure_rate(
        self,
        quad_mean: np.ndarray,
        w_block: np.ndarray,
        k: int,
        sg: np.ndarray | None = None,
        block: tuple | None = None,
        held: np.ndarray | None = None,
    ) -> tuple[Measurement, np.ndarray, float]:
        """A block's mean solved rate-quadratic terms (nq,) as a measurement.

        The prediction is :meth:`rate_model`'s plus the rate error's second-order mean
        ``P_ij`` and the biases (and ``S G dr_hat`` with ``DR`` states); R is the block
        mean's noise plus the spread of ``d_i d_j`` about ``P_ij``. ``sg`` is the
        block's :meth:`geometry_jacobian` (with ``DR`` states). ``block`` is the
        propagation that made ``w_block`` (:meth:`propagate`'s ``(k, dt, C)``), whose
        noise the measurement's is correlated with (:meth:`rate_noise_cross`;
        ``held`` (K,) marks its held samples); None: independent. Products an excluded
        channel leaves unsolved are the rate's own (aided) and left out
        (:attr:`rate_rows`).

        Returns the measurement, its innovation covariance ``S`` and its NIS.
        """
        # rate_model's at the shrunk rate, with the second order: the mean P_ij of d_i d_j
        # and its spread about it
        cq = self.noise.quad_cross_cov
        if block is None or cq is None:
            cq, k_block, dt, c = kernels.ABSENT, 0, 0.0, kernels.ABSENT
        else:
            k_block, dt, c = block
        z, h, r, m, s, nis = kernels.rate_update(
            np.asarray(quad_mean, dtype=float),
            np.asarray(w_block, dtype=float),
            self.quad_pairs,
            *self._rate_jacobian_parts(sg),
            self.P,
            self.bias[6:],
            self._sqq,
            k,
            cq,
            c,
            dt,
            k_block,
            _NO_HELD if held is None else held,
            self.rate_rows,
        )
        if not m.shape[1]:
            m = None
        elif self.rate_dof < self.layout.nq:
            # laid out as numpy's column selection m[:, rows] lays it (Fortran order):
            # filterpy's BLAS products round by the layout
            m = np.asfortranarray(m)
        return Measurement(z, h, r, m), s, nis

    def update_rate(
        self,
        quad_mean: np.ndarray,
        w_block: np.ndarray,
        k: int,
        sg: np.ndarray | None = None,
        held: np.ndarray | None = None,
    ) -> float | None:
        """Update with a block's mean solved rate-quadratic terms (nq,); returns the NIS.

        Right after :meth:`propagate` over the same block the measurement carries its
        correlation with that block's propagation noise (:meth:`measure_rate`).
        """
        block, self._block = self._block, None
        if self.layout.nq == 0 or not self.rate_measurement:
            return None
        meas, s, nis = self.measure_rate(quad_mean, w_block, k, sg, block, held)
        self.last_rate_innovation = meas.z
        self.last_rate_innovation_cov = s
        ok = self._fuse_if_passes(meas, nis, self.gate_q)
        self.counters.rate_updates += int(ok)
        self.counters.rate_rejected += int(not ok)
        return nis

    def rate_at_rest_model(self) -> np.ndarray:
        """The zero-rate update's Jacobian (3, n): it reads the body rate states."""
        h = np.zeros((3, self.layout.n))
        h[:, RATE] = np.eye(3)
        return h

    def update_zero_rate(self, sigma_rps: float) -> tuple[float, bool]:
        """Zero-rate update at detected rest: the body rate (FRD, rad/s) is measured as zero.

        A vehicle standing still does not turn in the filter's NED frame (which leaves the
        Earth's rotation out), so ``omega_b = 0`` with 1-sigma ``sigma_rps`` per axis:
        its rocking on its mounts, or a numerical floor where the rest is exact. It is
        what holds the yaw rate at rest, where a gyro-free array has nothing else: the
        rate products vanish with the rates, and without a horizontal acceleration GPS
        does not see the heading. It also makes the angular-acceleration biases
        observable (the rate stays zero while their error would integrate into it).
        Gated on the 3-dof chi-square threshold (a rejection says the vehicle turns:
        :class:`filters.rest.RestDetector` ends the rest).

        Returns ``(nis, accepted)``.
        """
        if not (np.isfinite(sigma_rps) and sigma_rps > 0.0):
            raise ValueError(f"sigma_rps must be finite and > 0, got {sigma_rps}")
        meas = Measurement(-self.w, self.rate_at_rest_model(), np.eye(3) * (sigma_rps * sigma_rps))
        nis, ok = self._gated_update(meas)
        self.counters.zero_rate_used += int(ok)
        self.counters.zero_rate_rejected += int(not ok)
        return nis, ok

    def heading_model(self) -> tuple[float, np.ndarray]:
        """The heading (ZYX yaw, rad) and its Jacobian (n,) in the NED attitude error.

        With ``C_t = exp([dtheta]x) C``, ``yaw = atan2(C_10, C_00)`` moves by
        ``(C_00 dC_10 - C_10 dC_00) / (C_00^2 + C_10^2)`` for ``dC = [dtheta]x C``:
        ``-(C_00 C_20, C_10 C_20, -(C_00^2 + C_10^2)) / (C_00^2 + C_10^2)`` on the
        attitude (pure heading at level, the tilt's share growing with the pitch).
        """
        c = dcm_from_quat(self.q)
        c00, c10, c20 = c[0, 0], c[1, 0], c[2, 0]
        h2 = c00 * c00 + c10 * c10
        h = np.zeros(self.layout.n)
        h[ATT] = np.array([-c00 * c20, -c10 * c20, h2]) / h2
        return float(np.arctan2(c10, c00)), h

    def update_heading(self, yaw_rad: float, sigma_rad: float) -> tuple[float, bool]:
        """The heading measured as ``yaw_rad`` (ZYX yaw, rad) with 1-sigma ``sigma_rad``:
        a GPS course for a vehicle that moves along its body axis. Gated on the 1-dof
        chi-square threshold. Returns ``(nis, accepted)``."""
        if not (np.isfinite(sigma_rad) and sigma_rad > 0.0):
            raise ValueError(f"sigma_rad must be finite and > 0, got {sigma_rad}")
        yaw, h = self.heading_model()
        z = np.array([np.angle(np.exp(1j * (yaw_rad - yaw)))])
        meas = Measurement(z, h[None, :], np.array([[sigma_rad * sigma_rad]]))
        nis, ok = self._gated_update(meas, self.gate1)
        self.counters.course_updates += int(ok)
        return nis, ok

    def measure_static_biases(
        self,
        mean_features: np.ndarray,
        n_samples: int,
        effect: np.ndarray | None = None,
        sample_cov: np.ndarray | None = None,
        walk_s: float = 0.0,
        cal_effect: np.ndarray | None = None,
    ) -> Measurement:
        """The static alignment's measurement of the biases (:meth:`update_static_biases`).

        At rest ``wdot = 0`` and ``w = 0``, so the mean solved
        angular acceleration and rate products over ``n_samples`` samples measure
        their biases directly (noise ``feature_cov / n``). Through the channel-bias
        correlation this also informs the force bias. Without it a gyro-free
        array leaves the static alignment with its yaw-acceleration bias at the
        turn-on prior, and a single-axis yaw rate is invisible to the products.

        ``effect`` (k, k), optional, is what the bias states leave in
        ``mean_features`` (the identity by default; the pipeline's static mean has the
        mounting term at rest taken out with the biased force, which leaves
        ``M = I - E_f (I + E_ff)^-1`` of the force bias in the other features).

        ``sample_cov`` (k, k), optional, is the per-sample covariance of the raw solved
        features the mean was taken of (default: ``noise.feature_cov``). The static
        mean has no forecast loop, so its noise is the raw solve's, through ``effect``
        as the biases are: ``M cov M^T / n``. ``noise.feature_cov`` is the
        propagation's, mapped through the loop (``T``), about 13 % smaller in variance
        on the angular acceleration with ``uav-survey``'s 6 mm outward offset.

        ``cal_effect`` (k, 3N), with ``CAL`` states: what the sensing-axis errors leave in
        ``mean_features`` at rest (their sensitivity at the rest's force, through
        ``effect``).

        ``walk_s`` (s, >= 0, default 0) weights the biases' random walk: the states
        are the biases at the mean's last sample, which differ from their mean over
        the span by a walk of covariance ``noise.bias_rw_cov * walk_s``, read through
        ``effect`` as the noise is (:func:`static_mean_walk_s`: about a third of the
        span; 13 % of the white noise's variance over ``uav-survey``'s 5 s).
        """
        if not (np.isfinite(walk_s) and walk_s >= 0.0):
            raise ValueError(f"walk_s must be finite and >= 0, got {walk_s}")
        nq = self.layout.nq
        k = 6 + nq
        idx = np.r_[0:3, 6 : 6 + nq]
        m = np.eye(k) if effect is None else np.asarray(effect, dtype=float)
        if m.shape != (k, k):
            raise ValueError(f"effect must be ({k}, {k}), got {m.shape}")
        h = np.zeros((idx.size, self.layout.n))
        h[:, self.layout.bias] = m[idx]
        if cal_effect is not None:
            h[:, self.layout.cal] = np.asarray(cal_effect, dtype=float)[idx]
        if sample_cov is None:
            r = self.noise.feature_cov[np.ix_(idx, idx)] / max(int(n_samples), 1)
        else:
            mi = m[idx]
            r = mi @ np.asarray(sample_cov, dtype=float) @ mi.T / max(int(n_samples), 1)
        if walk_s > 0.0:
            r = r + m[idx] @ self.noise.bias_rw_cov @ m[idx].T * walk_s
        z = mean_features[idx] - m[idx] @ self.bias
        if cal_effect is not None:
            z = z - np.asarray(cal_effect, dtype=float)[idx] @ self.dg
        return Measurement(z, h, r)

    def update_static_biases(
        self,
        mean_features: np.ndarray,
        n_samples: int,
        effect: np.ndarray | None = None,
        sample_cov: np.ndarray | None = None,
        walk_s: float = 0.0,
        cal_effect: np.ndarray | None = None,
    ) -> None:
        """Static alignment: fuse :meth:`measure_static_biases` (ungated: the rest is known)."""
        self._apply(
            self.measure_static_biases(
                mean_features, n_samples, effect, sample_cov, walk_s, cal_effect
            )
        )

    def gps_model(
        self, q_nb: np.ndarray, omega_b_rps: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Antenna offset (NED) and velocity (NED, from rotation) and their Jacobians.

        Returns ``C r``, ``C (w x r)``, ``H_pos`` (3, n), ``H_vel`` (3, n).
        """
        return kernels.gps_model(
            np.asarray(q_nb, dtype=float),
            np.asarray(omega_b_rps, dtype=float),
            self.antenna_b_m,
            self.layout.n,
        )

    def measure_gps_position(
        self, pos_ned_m: np.ndarray, pos_sigma_m: np.ndarray | float, dt_fix_s: float = 0.0
    ) -> Measurement:
        """A fix's antenna position (NED, m; 1-sigma per axis) as a measurement.

        The prediction is the array's position plus the antenna's lever arm, moved by
        ``v dt_fix_s`` to the fix's time (``dt_fix_s``: fix time minus filter time).
        """
        cr, _, hp, _ = self.gps_model(self.q, self.w)
        rp = np.diag(np.broadcast_to(np.asarray(pos_sigma_m, dtype=float), 3) ** 2)
        return Measurement(pos_ned_m - (self.pos + cr + self.vel * dt_fix_s), hp, rp)

    def measure_gps_velocity(self, vel_ned_mps: np.ndarray, vel_sigma_mps: float) -> Measurement:
        """A fix's antenna velocity (NED, m/s; 1-sigma per axis) as a measurement.

        The prediction is the array's velocity plus the lever arm's ``C (w x r)``; with
        the body-frame velocity error (:meth:`in_body_frame`) also the second-order
        part's mean, whose covariance R carries (:meth:`velocity_curvature`).
        """
        _, cwr, _, hv = self.gps_model(self.q, self.w)
        rv = self._eye3 * float(vel_sigma_mps) ** 2
        yv = vel_ned_mps - (self.vel + cwr)
        if self.in_body_frame():
            mc, cc = self.velocity_curvature()
            yv = yv - mc
            rv = rv + cc
        return Measurement(yv, hv, rv)

    def update_gps(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
        dt_fix_s: float = 0.0,
        reset: bool = False,
    ) -> GpsUpdateResult:
        """Gate and apply one GPS fix (antenna position and velocity, NED).

        ``dt_fix_s`` is the fix time minus the filter time (|dt| below one
        array sample); the prediction is moved by ``v dt``. With ``reset``
        (the first fix after an outage) a fix that passes the position gate
        is not fused: :meth:`reset_to_fix` puts position and velocity on it; so
        does the :data:`GAP_RESET_AFTER_REJECTS`-th fix in a row that fails it.

        A component the receiver did not give (NaN: the altitude of a fix whose
        altitude is flagged ignored, the vertical velocity GPS_RAW_INT lacks) is left
        out: the rest is gated on its own dimension and fused. A fix with no velocity
        leaves the velocity untouched and is not counted as rejected; the 3-dof
        ``nis_pos`` and ``nis_vel`` of a partial fix are NaN (the statistics a 3-dof
        chi-square judges), ``nis_pos_h`` is there whenever the horizontal is.
        """
        t_fix = self.t_s + dt_fix_s
        if np.isfinite(self._t_prev_fix) and t_fix > self._t_prev_fix:
            self.fix_interval_s = t_fix - self._t_prev_fix
        self._t_prev_fix = t_fix
        pos_rows = np.isfinite(pos_ned_m)
        vel_rows = np.isfinite(vel_ned_mps)
        mp = self.measure_gps_position(np.nan_to_num(pos_ned_m), pos_sigma_m, dt_fix_s)
        yp, sp = mp.z, mp.innovation_cov(self.P)
        nis_h = quadratic_form(yp[0:2], sp[0:2, 0:2]) if pos_rows[0:2].all() else np.nan
        nis_vt = np.nan
        if pos_rows[2]:
            nis_vt = float(yp[2] ** 2 / sp[2, 2]) if sp[2, 2] > 0 else np.inf
        if not pos_rows.all():
            mp = mp.take(pos_rows)
            sp = mp.innovation_cov(self.P)
        if reset:
            nis_p = quadratic_form(mp.z, sp)
            passed = np.isfinite(nis_p) and nis_p <= self._gate(mp)
            if passed or self._consec_rejects + 1 >= GAP_RESET_AFTER_REJECTS:
                mv = self._gps_velocity(vel_ned_mps, vel_sigma_mps, vel_rows)
                nis_v = np.nan if mv is None else quadratic_form(mv.z, mv.innovation_cov(self.P))
                self.reset_to_fix(
                    pos_ned_m - self.vel * dt_fix_s, vel_ned_mps, pos_sigma_m, vel_sigma_mps
                )
                self.counters.gps_gap_resets += 1
                self.counters.gps_used += 1
                return GpsUpdateResult(
                    _full(nis_p, pos_rows),
                    _full(nis_v, vel_rows),
                    True,
                    mv is not None,
                    nis_h,
                    nis_vt,
                )
            self.counters.gps_rejected_pos += 1
            self.counters.gps_rejected_vel += int(vel_rows.any())
            self._consec_rejects += 1
            return GpsUpdateResult(_full(nis_p, pos_rows), np.nan, False, False, nis_h, nis_vt)
        nis_p, ok_p = self._gated_update(mp, self._gate(mp), sp)
        # the velocity at the state the position update left
        mv = self._gps_velocity(vel_ned_mps, vel_sigma_mps, vel_rows)
        nis_v, ok_v = (np.nan, False) if mv is None else self._gated_update(mv, self._gate(mv))
        self.counters.gps_used += int(ok_p or ok_v)
        self.counters.gps_rejected_pos += int(not ok_p)
        self.counters.gps_rejected_vel += int(mv is not None and not ok_v)
        self._consec_rejects = 0 if ok_p else self._consec_rejects + 1
        if mv is not None:
            self._consec_vel_rejects = 0 if ok_v else self._consec_vel_rejects + 1
        if ok_p:
            self.t_last_position_fix = self.t_s
        if ok_p or ok_v:
            self._forget_curvature()
        return GpsUpdateResult(
            _full(nis_p, pos_rows), _full(nis_v, vel_rows), ok_p, ok_v, nis_h, nis_vt
        )

    def _gps_velocity(
        self, vel_ned_mps: np.ndarray, vel_sigma_mps: float, rows: np.ndarray
    ) -> Measurement | None:
        """The fix's velocity measurement on the components it has, or None (none)."""
        if not rows.any():
            return None
        mv = self.measure_gps_velocity(np.nan_to_num(vel_ned_mps), vel_sigma_mps)
        return mv if rows.all() else mv.take(rows)

    def _gate(self, meas: Measurement) -> float:
        """The chi-square gate of a 1-, 2- or 3-row measurement."""
        return (self.gate1, self.gate2, self.gate3)[meas.z.shape[0] - 1]


def _full(nis: float, rows: np.ndarray) -> float:
    """A NIS as the 3-dof statistic: NaN unless all three components were measured."""
    return float(nis) if rows.all() else float("nan")
