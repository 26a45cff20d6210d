"""A fixed-wing's vehicle constraints (calm-air sideslip and angle of attack) as measurements."""

from __future__ import annotations

import math

import numpy as np

from filters import kernels
from filters.algebra import (
    BODY_FRAME_MAX_CURVATURE_MPS,
    ned_velocity_curvature,
)
from filters.state import ATT, VEL
from filters.updates import Measurement
from filters.vehicle_model import (
    LATERAL,
    LIFT_JACOBIAN_LAG_BLOCKS,
    VERTICAL,
    BodyVelocityRecord,
    blend_spread_var,
    constraint_axes,
    prior_weighted_count,
    remainder_variance,
)
from ngnav.motion import min_jerk_step
from ngnav.rotation import (
    dcm_from_quat,
    skew,
)


class ConstraintsMixin:
    """The body-velocity models, the angle-of-attack state and its lift law, their updates."""

    @property
    def aoa(self) -> float:
        """The nominal angle of attack, rad: ``w (alpha_b + K u)`` (``alpha_b`` without a law)."""
        return self._lift_w * self._unblended_aoa()

    def _unblended_aoa(self) -> float:
        """The lift law before the lift-off blend, ``alpha_b + K u``, rad."""
        return self.aoa_b + self.aoa_k * self._lift_u

    def _aoa_gradient(self) -> np.ndarray:
        """d alpha / d(AOA states): ``w [1, u]`` (or ``[w]`` with the offset alone)."""
        return self._lift_w * np.array([1.0, self._lift_u_jac])[: self.layout.n_aoa]

    def aoa_jacobian(self, vel_ned_mps: np.ndarray) -> np.ndarray:
        """``d alpha / d(error state)`` (n,) at the velocity ``vel_ned_mps`` (NED, m/s).

        ``w [1, u]`` for the law's offset and ``K``; through ``u = n_w / V^2``
        (:meth:`set_load`), ``-2 w K u v^T / V^2`` for the velocity and
        ``-w K [sin a, 0, -cos a] T_f / V^2`` for the biases (``T_f`` the force rows of
        ``noise.bias_effect``) and likewise, with the load's ``S G`` force rows for
        ``T_f`` (:meth:`set_load`'s ``sg_f``), for the sensor positions; through the
        lift-off blend ``w(V)``, ``w'(V) (alpha_b + K u) v^T / V``. Zero without the
        ``AOA`` state. The ``u`` here is the load :data:`LIFT_JACOBIAN_LAG_BLOCKS`
        blocks back, whose noise is independent of the predicted angle's (equal to the
        current one under a steady load).
        """
        return kernels.aoa_jacobian(*self._aoa_jacobian_args(vel_ned_mps))

    def _aoa_jacobian_args(self, vel_ned_mps: np.ndarray) -> tuple:
        """:func:`filters.kernels.aoa_jacobian`'s arguments at the velocity ``vel_ned_mps``."""
        lay = self.layout
        geo = lay.n_dr or lay.n_cal
        sg_f = self._lift_sg_f if geo and self._lift_sg_f is not None else kernels.ABSENT
        return (
            lay.n,
            lay.aoa.start,
            lay.n_aoa,
            self._lift_w,
            self._lift_u_jac,
            np.asarray(vel_ned_mps, dtype=float),
            self._lift_dw,
            self._unblended_aoa(),
            self.aoa_k,
            self._lift_axis,
            self._bias_effect_f,
            lay.bias.start,
            sg_f,
            lay.geometry.start,
        )

    @property
    def aoa_sigma(self) -> float:
        """1-sigma of :attr:`aoa`, rad: :meth:`aoa_jacobian`'s linear part, the lift-off
        blend's beyond it (:meth:`blend_remainder_var`) and the load's noise
        (:meth:`set_load`); 0 without the state."""
        return self.aoa_sigma_from(
            kernels.aoa_linear_var(self.P, *self._aoa_jacobian_args(self.vel))
        )

    def aoa_sigma_from(self, linear_var: float) -> float:
        """:attr:`aoa_sigma` (rad) from its linear part's variance ``linear_var``, rad^2
        (:func:`filters.kernels.aoa_linear_var` at :meth:`_aoa_jacobian_args`, which the
        epoch's record computes with the rest of it)."""
        lift = self._unblended_aoa()
        var = linear_var + lift * lift * self.blend_remainder_var() + self._load_angle_var()
        return math.sqrt(var) if var >= 0.0 else math.nan

    def _load_angle_var(self) -> float:
        """Variance of the angle of attack from the load's noise, ``(w K)^2 Var(u)``, rad^2."""
        wk = self._lift_w * self.aoa_k
        return wk * wk * self._lift_u_var

    def load_noise_var(self, q_nb: np.ndarray, vel_ned_mps: np.ndarray, aoa_rad: float) -> float:
        """The angle-of-attack model's variance from the load's noise at a given state,
        ``(dv/dalpha)^2 (w K)^2 Var(u)`` (m^2/s^2), ``dv/dalpha = -(C t_b) . v``: what its R
        adds (:meth:`set_load`); 0 without a load covariance."""
        _, t_b = constraint_axes(VERTICAL, aoa_rad)
        dv_da = -float((dcm_from_quat(q_nb) @ t_b) @ vel_ned_mps)
        return dv_da * dv_da * self._load_angle_var()

    def _speed(self) -> float:
        """``|v|`` of the nominal velocity, m/s (on floats: it runs every block)."""
        vx, vy, vz = self.vel.tolist()
        return math.sqrt(vx * vx + vy * vy + vz * vz)

    def blend_remainder_var(self) -> float:
        """Variance of the lift-off blend ``w(V)`` beyond its linear term (dimensionless).

        The blend is the minimum-jerk step over ``[0.8, 1] liftoff_speed_mps``, whose
        first and second derivatives vanish where it starts and ends: there a speed
        error ``dV`` moves ``w`` by ``10 (dV / width)^3`` and more, which the
        Jacobian's ``w'(V) dV`` cannot carry (the filter's angle-of-attack sigma
        went to 1e-8 deg at the blend's start while the truth, blended on its own
        speed, was 1e-4 deg off). This is ``Var[w(V + dV) - w(V) - w'(V) dV]`` for
        ``dV ~ N(0, u^T P_vel u)`` (``u`` the velocity's direction), on a 41-point
        grid over +-6 sigma; 0 where the blend is flat over +-6 sigma of speed,
        without the ``AOA`` state, or without a blend.
        """
        v_lof = self.liftoff_speed_mps
        if not self.layout.n_aoa or v_lof <= 0.0:
            return 0.0
        speed = self._speed()
        if speed <= 1.0:
            return 0.0
        width = 0.2 * v_lof
        x0 = (speed - 0.8 * v_lof) / width
        # the per-block path: the trace bounds the speed's variance from above
        p, iv = self.P, VEL.start
        s_max = 6.0 * math.sqrt(max(float(p[iv, iv] + p[iv + 1, iv + 1] + p[iv + 2, iv + 2]), 0.0))
        s_max /= width
        if x0 + s_max <= 0.0 or x0 - s_max >= 1.0:
            return 0.0
        u = self.vel / speed
        sx = float(np.sqrt(max(u @ self.P[VEL, VEL] @ u, 0.0))) / width
        if x0 + 6.0 * sx <= 0.0 or x0 - 6.0 * sx >= 1.0:
            return 0.0
        return blend_spread_var(x0, sx)

    def set_load(
        self,
        f_b_mps2: np.ndarray,
        load_cov: np.ndarray | None = None,
        sg_f: np.ndarray | None = None,
    ) -> None:
        """Feed the lift law the block's specific force (FRD, m/s^2, biases removed).

        ``u = n_w / V^2`` with the wind-frame normal load ``n_w = sin(a) f_x - cos(a) f_z``
        at the current angle of attack and ``V = |v|`` (calm air), and the lift-off blend
        ``w(V)``. The angle of attack so depends on the velocity and force-bias states
        too; :meth:`body_velocity_model` carries both in its Jacobian, which takes ``u``
        from :data:`LIFT_JACOBIAN_LAG_BLOCKS` calls back (errors in variables).

        ``load_cov`` (3, 3), (m/s^2)^2, FRD, is the covariance of the noise in
        ``f_b_mps2`` (the pipeline's: the block means' ``feature_cov / k``, weighted as its
        extrapolation weights them). The angle carries it, ``Var(u) = a^T load_cov a / V^4``
        along the lift axis ``a``: the angle-of-attack model's R and :attr:`aoa_sigma`
        add it. None: a noise-free load.

        ``sg_f`` (3, nd), with geometry states: the force rows of the load's sensitivity
        to them (:meth:`geometry_sg`'s, weighted as the load's blocks are), whose share of
        the estimates (``S G dr_hat``, ...) the caller has taken out of ``f_b_mps2`` as the
        propagation does; the angle of attack's Jacobian carries their errors as it
        carries the biases'. None: the load does not depend on them.
        """
        self._lift_sg_f = None if sg_f is None else np.asarray(sg_f, dtype=float)
        speed = self._speed()
        a = self.aoa  # the angle n_w is taken at: the last block's
        v_lof = self.liftoff_speed_mps
        if v_lof > 0.0:
            s, ds, _ = min_jerk_step((speed - 0.8 * v_lof) / (0.2 * v_lof))
            self._lift_w, self._lift_dw = float(s), float(ds) / (0.2 * v_lof)
        if self.aoa_k > 0.0 and speed > 1.0:
            self._lift_u, self._lift_u_var = kernels.lift_load(
                np.asarray(f_b_mps2, dtype=float),
                kernels.ABSENT if load_cov is None else np.asarray(load_cov, dtype=float),
                math.sin(a),
                math.cos(a),
                speed,
                self._lift_axis,  # written: the axis at this angle
            )  # n_w = _lift_axis . f
            recent = self._lift_u_recent
            recent.append(self._lift_u)
            if len(recent) > LIFT_JACOBIAN_LAG_BLOCKS + 1:
                del recent[0]
            self._lift_u_jac = recent[0]

    def body_velocity_model(
        self, q_nb: np.ndarray, vel_ned_mps: np.ndarray, axis: int = LATERAL, aoa_rad: float = 0.0
    ) -> tuple[float, np.ndarray]:
        """Velocity along a body constraint axis, ``n_b . C^T v`` (m/s), and its Jacobian (1, n).

        ``axis`` is :data:`LATERAL` (``n_b = e_y``: the sideslip model) or
        :data:`VERTICAL` (``n_b = [-sin alpha, 0, cos alpha]``, the wind-normal axis at
        angle of attack ``aoa_rad``: the angle-of-attack model; ``e_z`` at zero). With
        the ``AOA`` state the vertical model's Jacobian includes
        ``d/dalpha = -t_b . C^T v``, ``t_b = [cos alpha, 0, sin alpha]`` (the wind x axis),
        times :meth:`aoa_jacobian`.
        """
        c = dcm_from_quat(q_nb)
        n_b, t_b = constraint_axes(axis, aoa_rad)
        row = c @ n_b  # n_b^T C^T as a NED row
        h = np.zeros((1, self.layout.n))
        h[0, VEL] = row
        h[0, ATT] = row @ skew(vel_ned_mps)
        if axis == VERTICAL and self.layout.n_aoa:
            h[0] += -float((c @ t_b) @ vel_ned_mps) * self.aoa_jacobian(vel_ned_mps)
        return float(row @ vel_ned_mps), h

    def sideslip_model(self, q_nb: np.ndarray, vel_ned_mps: np.ndarray) -> tuple[float, np.ndarray]:
        """Body-lateral velocity ``e_y . C^T v`` (m/s) and its Jacobian (1, n)."""
        return self.body_velocity_model(q_nb, vel_ned_mps, LATERAL)

    def update_sideslip(self, sigma_rad: float, min_speed_mps: float) -> float | None:
        """Zero-sideslip pseudo-measurement (a fixed-wing's, ``vehicle.kind``).

        R is the sigma's lateral velocity squared (at the horizontal speed) plus the
        second-order remainder's variance as :func:`remainder_variance` counts it (it
        is correlated from one update to the next); the remainder's mean is added to
        the prediction.

        Returns the NIS, or None below ``min_speed_mps`` horizontal speed (no update).
        """
        speed = float(np.hypot(self.vel[0], self.vel[1]))
        if speed < min_speed_mps:
            return None
        nis, ok = self._body_velocity_update(LATERAL, speed * np.tan(sigma_rad))
        self.counters.sideslip_used += int(ok)
        self.counters.sideslip_rejected += int(not ok)
        self._consec_slip_rejects = 0 if ok else self._consec_slip_rejects + 1
        return nis

    def update_angle_of_attack(self, sigma_rad: float, min_speed_mps: float) -> float | None:
        """Angle-of-attack pseudo-measurement (a fixed-wing's).

        The velocity along the wind-normal axis ``[-sin alpha, 0, cos alpha]`` (FRD;
        ``alpha`` the ``AOA`` state, or zero without it: the body z axis) is measured
        as zero with a 1-sigma of ``|v| tan(sigma_rad)``, and the same second-order
        terms as :meth:`update_sideslip`. Returns the NIS, or None below
        ``min_speed_mps`` horizontal speed (no update).
        """
        if float(np.hypot(self.vel[0], self.vel[1])) < min_speed_mps:
            return None
        sigma_v = float(np.linalg.norm(self.vel)) * np.tan(sigma_rad)
        nis, ok = self._body_velocity_update(VERTICAL, sigma_v)
        self.counters.aoa_used += int(ok)
        self.counters.aoa_rejected += int(not ok)
        return nis

    def measure_body_velocity(
        self, axis: int, sigma_v_mps: float
    ) -> tuple[Measurement, BodyVelocityRecord]:
        """A vehicle model (``axis``: :data:`LATERAL` or :data:`VERTICAL`) as a measurement.

        The velocity along the constraint axis is measured as zero with 1-sigma
        ``sigma_v_mps``; the prediction adds the second-order remainder's mean, R its
        variance as counted (:func:`remainder_variance`) and, for the vertical model,
        the angle of attack's load noise and lift-off blend. Also returns the terms it
        was built from (``accepted`` False until an update says otherwise).
        """
        v_axis, h = self.body_velocity_model(self.q, self.vel, axis, self.aoa)
        mq, sel, mean_shift = self.body_velocity_second_order_form(axis)
        rem = self._form_moments(mq, sel, mean_shift)
        load_var = blend_var = 0.0  # R's angle-of-attack terms, m^2/s^2
        dv_da = 0.0  # the model's change per radian of angle of attack: -(C t_b . v)
        if axis == VERTICAL:
            _, t_b = constraint_axes(VERTICAL, self.aoa)
            dv_da = -float((dcm_from_quat(self.q) @ t_b) @ self.vel)
            # the predicted angle carries the load's noise: w K du
            load_var = dv_da * dv_da * self._load_angle_var()
            # the blend beyond its linear term moves the angle, and the velocity with it
            lift = self._unblended_aoa()
            blend_var = dv_da * dv_da * lift * lift * self.blend_remainder_var()
        n_upd = self.current_remainder_updates()
        counted = remainder_variance(rem, n_upd, self.attitude_remainder_updates)
        if self.count_by_prior_weight and axis == LATERAL and not self.counts_as_coast():
            # outside the hand-over and coasts (whose count stands for more than the
            # remainder's persistence): the count as far as the update keeps the prior;
            # the sideslip model only, whose prior along the constraint is fresh noise
            r_c = sigma_v_mps**2 + counted  # the sideslip's R: no load or blend terms
            s_prior = float(h[0] @ self.P @ h[0])
            counted = remainder_variance(
                rem,
                prior_weighted_count(n_upd, r_c, s_prior),
                prior_weighted_count(self.attitude_remainder_updates, r_c, s_prior),
            )
        var = sigma_v_mps**2 + counted
        if axis == VERTICAL:
            var += load_var
            if blend_var > 0.0:
                var += blend_var
        aoa = self.aoa if axis == VERTICAL else 0.0
        rec = BodyVelocityRecord(
            self.t_s, axis, self.q.copy(), self.vel.copy(), aoa, v_axis, h[0, ATT].copy(),
            h[0, VEL].copy(), dv_da, rem, float(var), False,
        )  # fmt: skip
        return Measurement(np.array([-(v_axis + rem.mean)]), h, np.array([[var]])), rec

    def _body_velocity_update(self, axis: int, sigma_v_mps: float) -> tuple[float, bool]:
        meas, rec = self.measure_body_velocity(axis, sigma_v_mps)
        nis, ok = self._gated_update(meas, self.gate1)
        if ok:
            self._model_last_t[axis] = self.t_s
            self._forget_curvature()  # the velocity was measured
        self._model_last_ok[axis] = ok
        if self.body_velocity_log is not None:
            self.body_velocity_log.append(rec._replace(accepted=ok))
        return nis, ok

    def in_body_frame(self) -> bool:
        """Whether the velocity error is taken in the body frame now.

        With :attr:`body_velocity_error`, while the attitude's uncertainty curves the NED
        velocity by at most :data:`BODY_FRAME_MAX_CURVATURE_MPS`
        (``|v| tr(P_att) / 2``, the size of ``dtheta x (dtheta x v) / 2``); otherwise the
        NED error's updates, remainder and injection. The two errors agree to first order,
        so P means the same either way and the filter may change from one to the other
        between steps; what differs is second order, which is what this bounds. Also the
        NED error while the last GPS velocity or either vehicle model's last update failed
        its gate: the body-frame error trusts P's attitude, and a hand-over told 1 deg while
        15 deg off otherwise fused GPS velocities through it for a second longer and
        relearned its tilt twice as badly (docs/notes/filter-notes.md).
        """
        return self._body_frame_allowed() and kernels.body_frame_curvature_ok(
            self.P, self.vel, BODY_FRAME_MAX_CURVATURE_MPS
        )

    def _body_frame_allowed(self) -> bool:
        """:meth:`in_body_frame` but for its curvature bound: the setting is on and the last
        GPS velocity and vehicle-model updates passed their gates."""
        if not self.body_velocity_error:
            return False
        # a GPS velocity or a vehicle model just failed its gate: P's attitude is in doubt,
        # and the body-frame error would fuse through it
        return self._consec_vel_rejects == 0 and all(self._model_last_ok.values())

    def velocity_curvature(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (3,) and covariance (3, 3) of the NED velocity's second-order part, m/s
        (:func:`filters.algebra.ned_velocity_curvature`); zeros with the NED error (the
        velocity error is then exactly additive)."""
        if not self.in_body_frame():
            return np.zeros(3), np.zeros((3, 3))
        return ned_velocity_curvature(self.vel, self.P)
