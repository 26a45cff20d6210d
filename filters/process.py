"""The process model: the error's transition F and process noise Q over one block."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import predict as kf_predict

from filters import kernels
from filters.algebra import BODY_FRAME_MAX_CURVATURE_MPS
from filters.state import ATT, RATE, VEL
from ngnav.rotation import (
    dcm_from_quat,
)


class ProcessMixin:
    """F and Q for a block, filterpy's predict, and the noise added beside the transition."""

    def _predict_covariance(
        self, phi: np.ndarray, q: np.ndarray, f_n: np.ndarray, t_s: float
    ) -> None:
        """filterpy's predict by the block's ``phi`` and ``q`` (over ``t_s`` s, mean NED
        force ``f_n``), then the force curvature's noise (:meth:`_add_curvature_noise`)
        and P symmetrised."""
        if self.lag is not None:
            self.lag.start(self.P, phi)
        self.x, p = kf_predict(self.x, self.P, phi, q)
        kernels.predicted_covariance(
            p,
            self._body_frame_allowed(),
            self.vel,
            BODY_FRAME_MAX_CURVATURE_MPS,
            self._curvature_sd_mps,
            self._curvature_sd_m,
            f_n,
            t_s,
        )
        self.P = p

    def force_for_jacobian(self, f_n: np.ndarray) -> np.ndarray:
        """The block's mean force (NED, m/s^2) as the transition's ``-[f_n]x`` reads it.

        The estimate's force is the truth's turned by the attitude error, ``dtheta x f``
        (variance ``diag([f]x P_att [f]x^T)``); each component is shrunk to its unbiased
        size (:func:`filters.algebra.shrink_to_size`, errors in variables, as the rate
        products' Jacobian). In a coast of a free vehicle the tilt error alone tilts the
        force: read as it is, a hover's force made a heading error move the horizontal
        velocity and a tilt error the vertical, and the returning fixes turned the heading
        the wrong way (`multirotor`: attitude inside its band on 86.4 % of epochs, 92.9 %
        so; docs/design.md, "Process model").
        """
        return kernels.shrunk_force(f_n, self.P[ATT, ATT])

    def _add_curvature_noise(self, t_s: float, f_n: np.ndarray) -> None:
        """The attitude error's second-order action on the force, as a random constant.

        The truth's force is ``R(dtheta) C f``; the transition keeps its first order and
        the nominal its mean, which leaves ``b = [dtheta]x^2 f / 2`` less its mean. In a
        long coast of a free vehicle (a multirotor's hover, a car in a tunnel) the tilt
        grows to ten degrees and the heading to tens, and ``b`` reaches 0.1-0.4 m/s^2;
        without it the vertical velocity, tied to the tilt only through the estimate's
        tilted force, was held to centimetres per second while it drifted by metres
        (docs/design.md, "Process model"). Its variance is
        :func:`filters.algebra.force_curvature_variance`. The tilt changes slowly, so
        ``b`` is carried as a constant: each NED axis's 1-sigma velocity error from it
        grows by ``sd(b_i) t`` a block, and the position error it makes with it, fully
        correlated (left out, `multirotor`'s coast read its position over-sure and its
        joint NEES pessimistic: position 92.9 % inside, joint 78.5; 100.0 and 82.1 with
        it), from zero at the last position or velocity measurement that passed its gate
        (a GPS fix or a vehicle model's; carried through `uav-survey`'s 30 s outage past
        its 5 Hz models it made the joint NEES pessimistic, 89.5 % inside).
        Not carried while the velocity error is in the body frame (the attitude is then
        known to a few degrees and ``b`` is negligible).
        """
        kernels.curvature_noise_step(
            self.P,
            self._body_frame_allowed(),
            self.vel,
            BODY_FRAME_MAX_CURVATURE_MPS,
            self._curvature_sd_mps,
            self._curvature_sd_m,
            f_n,
            t_s,
        )

    def _forget_curvature(self) -> None:
        """Start the curvature's constant again from zero: after a measurement of the
        position or the velocity (the constant's parts are not followed through the update),
        or a reset of them."""
        self._curvature_sd_mps[:] = 0.0
        self._curvature_sd_m[:] = 0.0

    def propagation_matrices(
        self,
        k: int,
        dt: float,
        c: np.ndarray,
        f_n: np.ndarray,
        sg: np.ndarray | None = None,
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
        sg : array (k, nd), optional
            Feature sensitivity to the geometry states (``DR``, ``CAL``; :meth:`geometry_sg`).
        """
        t = k * dt
        # a rate error reaches wdot and f through what the features hold of the rate
        # products (the forecast's S E_q q(w_hat), and with channels excluded the aided
        # A_m q(w_hat)); with sensor-position states the removed S G(w_hat) dr_hat is off
        # by its rate derivative times the rate error
        quad_into = self._quad_into_features
        geo = self._geometry_args(sg)
        return kernels.propagation_matrices(
            self._fc_base,
            f_n,
            c,
            self._bias_effect_f,
            self.layout.bias.start,
            kernels.ABSENT if quad_into is None else quad_into,
            self._quad6_d,
            self.w,
            *geo,
            t,
            self._q12_body(k, dt),
            self._q_walks(t),
            np.empty((self.layout.n, self.layout.n)),
            np.empty((self.layout.n, self.layout.n)),
        )

    def _q_walks(self, t: float) -> np.ndarray:
        """Process noise (n, n) of the random walks over ``t`` s: the biases' and the
        angle-of-attack offset's (the K error, if carried, is constant); cached per t."""
        q = self._q_walk_cache.get(t)
        if q is None:
            n = self.layout.n
            q = np.zeros((n, n))
            bs = self.layout.bias
            q[bs, bs] = (self.noise.bias_rw_cov + self.extra_bias_walk) * t
            if self.layout.n_aoa:
                ia = self.layout.aoa.start
                q[ia, ia] = self.aoa_rw_rad_rts**2 * t
            self._q_walk_cache[t] = q
        return q

    def _q12_body(self, k: int, dt: float) -> np.ndarray:
        """Navigation-block noise (12, 12) of ``k`` samples with ``C = I`` (cached per k).

        A feature-noise sample ``n = [n_w, n_f]`` at step ``j`` of ``k`` enters
        the rate as ``dt n_w``, the attitude as ``(k - j) dt^2 n_w``, the
        velocity as ``dt n_f`` and the position as ``(k - j) dt^2 n_f``; the
        sums over ``j`` of 1, ``(k - j)`` and ``(k - j)^2`` give the weights. With
        :attr:`rate_reset_each_block` the angular acceleration's noise is one block's
        own (``FilterNoise.block_wdot_cov``).
        """
        block = self.rate_reset_each_block
        key = (k, dt, block)
        qb = self._q12_cache.get(key)
        if qb is None:
            s0 = k * dt**2
            s1 = k * (k - 1) / 2.0 * dt**3
            s2 = (k - 1) * k * (2 * k - 1) / 6.0 * dt**4
            sff, sfw = self._sff, self._sfw
            sww = self._sww_block if block else self._sww
            qb = np.block(
                [
                    [s2 * sff, s1 * sff, s2 * sfw, s1 * sfw],
                    [s1 * sff, s0 * sff, s1 * sfw, s0 * sfw],
                    [s2 * sfw.T, s1 * sfw.T, s2 * sww, s1 * sww],
                    [s1 * sfw.T, s0 * sfw.T, s1 * sww, s0 * sww],
                ]
            )
            self._q12_cache[key] = qb
        return qb

    def add_forecast_noise(self, cov_b: np.ndarray, t_s: float) -> None:
        """Covariance of the compensation's forecast error over one block.

        ``cov_b`` (6, 6) is the covariance of the error the forecast left in the
        block's solved ``[wdot, f]`` (FRD; rad/s^2 and m/s^2), a constant over
        the block's ``t_s`` seconds: it adds ``cov t^2`` to the rate (body) and
        ``C cov C^T t^2`` to the velocity (NED), with their cross term, as
        :meth:`add_hold_noise` does for a held run; the next transition carries
        it into attitude and position.
        """
        ct = dcm_from_quat(self.q) * t_s
        t2 = t_s * t_s
        ww = cov_b[0:3, 0:3] * t2
        wf = cov_b[0:3, 3:6] @ ct.T * t_s
        ff = ct @ cov_b[3:6, 3:6] @ ct.T
        p = self.P
        p[RATE, RATE] += 0.5 * (ww + ww.T)  # exactly symmetric
        p[RATE, VEL] += wf
        p[VEL, RATE] += wf.T
        p[VEL, VEL] += 0.5 * (ff + ff.T)
        self.P = p

    def add_hold_noise(
        self, t_before_s: float, t_after_s: float, wdot_sigma_rps2: float, f_sigma_mps2: float
    ) -> None:
        """Covariance of the forecast that stood in for held (missing) samples.

        Over a run of held samples the filter propagates on the compensation's
        forecast, whose error is modelled as a random constant (1-sigma
        ``wdot_sigma_rps2``, ``f_sigma_mps2``) over the run: the rate error grows
        as ``sigma T`` and the velocity error as ``sigma_f T``. The run grew from
        ``t_before_s`` to ``t_after_s`` held seconds in this block; the increment
        of those variances is added (the transition carries them into attitude and
        position at the next block).
        """
        d = t_after_s * t_after_s - t_before_s * t_before_s
        if d <= 0.0:
            return
        p = self.P
        p[RATE, RATE] += np.eye(3) * (wdot_sigma_rps2 * wdot_sigma_rps2 * d)
        p[VEL, VEL] += np.eye(3) * (f_sigma_mps2 * f_sigma_mps2 * d)
        self.P = p

    def geometry_jacobian(self, wdot_b_rps2: np.ndarray, omega_b_rps: np.ndarray) -> np.ndarray:
        """Sensitivity (k, 3N) of the compensated features to the sensor positions.

        A sensor at ``r_i + dr_i`` reads ``theta_i . (wdot x dr_i + w x (w x dr_i))``
        more than at ``r_i``: row ``i`` of ``G`` is ``theta_i^T M`` with
        ``M = [wdot]x + [w]x^2``, and the solved features see ``S G``. With a forecast
        compensation (``noise.bias_effect`` ``T``) the forecast's history holds them
        (it takes out the bias estimates, not ``S G dr_hat``), so the loop returns them
        as it returns a bias and the compensated features see ``T S G``: this is what
        the nominal takes out (``T S G dr_hat``) and what the Jacobians carry. The raw
        ``S G`` left tactical's 27 position states' NEES at 37.6 by the end (24 runs,
        against 30.0 for their prior; 30.6 with ``T``).

        Parameters
        ----------
        wdot_b_rps2, omega_b_rps : arrays (3,)
            The block's angular acceleration and rate, FRD.
        """
        return kernels.geometry_jacobian(
            np.asarray(wdot_b_rps2, dtype=float),
            np.asarray(omega_b_rps, dtype=float),
            self.sensor_axes_b,
            self._solve_rep,
        )

    def geometry_rate_jacobian(self, omega_b_rps: np.ndarray) -> np.ndarray:
        """Sensitivity (k, 3) of ``T S G(w) dr_hat`` to the rate, at the estimated positions.

        ``d/dw [w x (w x dr)] = (w . dr) I + w dr^T - 2 dr w^T``; sensor ``i`` reads it
        along ``theta_i``. A rate error moves what the nominal removes for the positions by
        this times the error: at a projectile's spin (12 rad/s) and 0.5 mm positions, about
        0.1 rad/s^2 of angular acceleration per rad/s, which the transition and the rate
        measurement carry.
        """
        return kernels.geometry_rate_jacobian(
            np.asarray(omega_b_rps, dtype=float), self.dr, self.sensor_axes_b, self._solve_t
        )

    def calibration_jacobian(
        self,
        f_b_mps2: np.ndarray,
        wdot_b_rps2: np.ndarray,
        omega_b_rps: np.ndarray,
        through_loop: bool = True,
    ) -> np.ndarray:
        """Sensitivity (k, 3N) of the compensated features to the sensing-axis errors.

        A sensing axis off by ``dg_i`` reads ``dg_i . a_i`` more, ``a_i`` the specific
        force at the sensor (:func:`filters.kernels.load_jacobian`); through the solve and,
        as for the positions (:meth:`geometry_jacobian`), the forecast's loop: ``T S``
        (``through_loop`` False: ``S``, for a mean with no forecast, the static one).
        """
        rep = self._solve_rep if through_loop else np.repeat(self.solve_matrix, 3, axis=1)
        return kernels.load_jacobian(
            np.asarray(f_b_mps2, dtype=float),
            np.asarray(wdot_b_rps2, dtype=float),
            np.asarray(omega_b_rps, dtype=float),
            self.sensor_positions_b_m,
            np.ascontiguousarray(rep, dtype=float),
        )

    def geometry_sg(
        self, f_b_mps2: np.ndarray, wdot_b_rps2: np.ndarray, omega_b_rps: np.ndarray
    ) -> np.ndarray | None:
        """The features' sensitivity (k, nd) to the geometry states, in their order
        (positions, then sensing axes), at the block's motion; None without them."""
        lay = self.layout
        parts = []
        if lay.n_dr:
            parts.append(self.geometry_jacobian(wdot_b_rps2, omega_b_rps))
        if lay.n_cal:
            parts.append(self.calibration_jacobian(f_b_mps2, wdot_b_rps2, omega_b_rps))
        if not parts:
            return None
        return parts[0] if len(parts) == 1 else np.hstack(parts)

    def geometry_estimates(self) -> np.ndarray:
        """The geometry states' estimates (nd,): ``dr_hat`` then ``dg_hat``."""
        if not self.layout.n_cal:
            return self.dr
        return np.concatenate([self.dr, self.dg]) if self.layout.n_dr else self.dg

    def _geometry_args(self, sg: np.ndarray | None) -> tuple:
        """The kernels' geometry arguments: ``sg``, its first column, the estimates, and
        with positions the sensing axes and ``T S`` (their rate derivative)."""
        with_geo, dr0, axes, solve_t = self._geo_fixed
        return (
            sg if with_geo else kernels.ABSENT,
            dr0,
            self.geometry_estimates(),
            axes,
            solve_t,
        )

    # ------------------------------------------------------------- measurements
    def rate_noise_cross(
        self, k: int, dt: float, c: np.ndarray, held: np.ndarray | None = None
    ) -> np.ndarray | None:
        """``E[dx v^T]`` (n, nq): a block's propagation noise with its rate measurement's.

        The block's ``k`` samples (interval ``dt``, ``C_nb`` ``c`` at its start) drive
        the error state as :meth:`_q12_body` says (sample ``j`` enters the rate as
        ``-dt n_w``, the attitude as ``-(k - j) dt^2 C n_w``, the velocity and position
        likewise with ``n_f``; minus: errors are true - estimate), and their mean
        quadratic terms, noise ``v = mean n_q``, are the rate measurement. With
        ``X = noise.quad_cross_cov`` the cross-covariance is ``-dt X_w`` for the rate,
        ``-dt C X_f`` for the velocity, ``-dt^2 lag C X_w`` and ``-dt^2 lag C X_f`` for
        the attitude and position (``lag`` the mean of ``k - j`` over the samples
        measured; ``held`` (k,) marks held ones, which carry no sample noise). None
        without the cross-covariance or with no sample measured.
        """
        cq = self.noise.quad_cross_cov
        if cq is None or self.layout.nq == 0:
            return None
        held = np.zeros(0, dtype=bool) if held is None else np.asarray(held, dtype=bool)
        m = kernels.rate_noise_cross(cq, np.asarray(c, dtype=float), dt, k, held, self.layout.n)
        return m if m.shape[1] else None
