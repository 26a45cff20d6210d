"""The vehicle constraints' second-order remainder: its moments, and how many updates count it."""

from __future__ import annotations

import math

import numpy as np

from filters.algebra import (
    _DTHETA_DV,
    _DTHETA_DV_DW,
)
from filters.state import RATE, VEL
from filters.vehicle_model import (
    BODY_REMAINDER_INTERVAL_S,
    BODY_REMAINDER_MAX_INTERVAL_S,
    COAST_AFTER_FIXES,
    LATERAL,
    VERTICAL,
    Remainder,
    attitude_product_matrix,
    constraint_axes,
    remainder_moments,
)
from ngnav.rotation import (
    dcm_from_quat,
    skew,
)


class RemainderMixin:
    """The remainder's quadratic forms, and the counts of the hand-over and coasts."""

    def current_remainder_updates(self) -> float:
        """The count of the whole remainder a body-velocity update uses now.

        ``coast_remainder_updates`` while coasting (more than ``coast_after_s``, or
        five intervals of the GPS fixes received, whichever is longer, since the last
        accepted GPS position: a slow receiver's normal spacing is not a coast) and for
        ``coast_hold_s`` after it: the remainder built up in a coast lasts as long
        after it as in it. The same count, if not coasting, until ``handover_hold_s``
        after the first such call since :meth:`initialise`
        (``counters.handover_model_updates``). Otherwise ``remainder_updates``. Called
        once per update: a coasting call is counted (``counters.coast_model_updates``)
        and extends the hold; the first call after :meth:`initialise` starts the
        hand-over's.
        """
        if self._handover_pending:
            self._handover_pending = False
            # less a nanosecond: the update times are sums of sample intervals, and the
            # update a whole hold later ends it
            self._handover_until = self.t_s + self.handover_hold_s - 1e-9
        coasting = self._coasting()
        if coasting:
            self._coast_until = self.t_s + self.coast_hold_s
        if coasting or self.t_s < self._coast_until:
            self.counters.coast_model_updates += 1
            return self.coast_remainder_updates
        if self.t_s < self._handover_until:
            self.counters.handover_model_updates += 1
            return self.coast_remainder_updates
        return self.remainder_updates

    def _coasting(self) -> bool:
        """More than ``coast_after_s`` (or five fix intervals) since the last accepted position."""
        after = self.coast_after_s
        if not math.isnan(self.fix_interval_s):
            after = max(after, COAST_AFTER_FIXES * self.fix_interval_s)
        return self.t_s - self.t_last_position_fix > after

    def counts_as_coast(self) -> bool:
        """Whether a body-velocity update now would use ``coast_remainder_updates``.

        True while coasting, within ``coast_hold_s`` of the last coasting update, and
        from :meth:`initialise` until ``handover_hold_s`` after the models' first
        update since: what
        :meth:`current_remainder_updates` decides, without its counting (a query).
        The vehicle models run at ``filters.vehicle_model.SIDESLIP_RATE_HZ`` throughout.
        """
        return (
            self._coasting()
            or self._handover_pending
            or self.t_s < max(self._coast_until, self._handover_until)
        )

    def sideslip_second_order(self) -> Remainder:
        """:meth:`body_velocity_second_order` of the lateral axis (the sideslip model)."""
        return self.body_velocity_second_order(LATERAL)

    def body_velocity_second_order(self, axis: int = LATERAL) -> Remainder:
        """Mean and variance of a body-velocity model's second-order term (m/s, m^2/s^2).

        With ``a = C n_b`` (the constraint axis in NED; :meth:`body_velocity_model`),
        the velocity of the true state along it is ``a^T exp(-[dtheta]x) (v + dv)``;
        beyond the linear terms it holds
        ``q = dtheta^T [a]x dv + dtheta^T A dtheta / 2``
        with ``A = (a v^T + v a^T) / 2 - (a . v) I``. With the ``AOA`` state the
        vertical axis also turns, ``n_b(alpha + da) = n_b - da t_b - da^2 n_b / 2``
        (``b = C t_b``), which adds ``-da b^T ([v]x dtheta + dv) - da^2 (a . v) / 2``.
        The angle itself, ``w(V) (alpha_b + K n_w / V^2)`` with a lift law, is bilinear in
        the speed's error ``dV = v^T dv / V`` and the law's states beyond its Jacobian:
        ``da`` holds ``dV (w' d alpha_b + (w' u - 2 w u / V) dK)`` too, which moves the
        model by ``-b . v`` per radian. In the lift-off blend (``w'`` up to 0.5 per m/s,
        the law 1 deg uncertain) this term is far above the model's sigma.
        Written ``q = x^T M x / 2`` over ``x = (dtheta, dv[, da, AOA states])``, a
        Gaussian error gives ``E q = tr(M P) / 2`` and ``Var q = tr(M P M P) / 2``, the second-order
        filter's terms (as for the rate products). They are negligible while GPS
        holds velocity and attitude; at the end of a long coast (metres per second
        of velocity error, tenths of a degree of tilt) they exceed a tight sideslip
        sigma, and without them the filter trusted the linearised constraint too
        far (joint velocity-attitude NEES far above its 6 dof on ``uav-survey``).
        ``var_att`` is ``Var`` of the ``dtheta^T A dtheta / 2`` part alone.
        """
        return self._form_moments(*self.body_velocity_second_order_form(axis))

    def _form_moments(self, mq: np.ndarray, sel: np.ndarray, mean_shift: float) -> Remainder:
        """:func:`remainder_moments` of a form from :meth:`body_velocity_second_order_form`."""
        rem = remainder_moments(mq, self.P[np.ix_(sel, sel)])
        return rem._replace(mean=rem.mean - mean_shift)

    def body_velocity_second_order_form(
        self, axis: int = LATERAL
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """The remainder of :meth:`body_velocity_second_order` as a quadratic form.

        Returns
        -------
        mq : array (d, d)
            ``q = x^T mq x / 2`` over the error states ``x = dx[sel]`` (m/s per unit of
            each pair); the first three of ``sel`` are the attitude error.
        sel : array (d,) of int
            Their indices in the error state.
        mean_shift : float
            What the propagation already carries of ``E q`` (the body-frame velocity
            error's terms; 0 otherwise), m/s: the update's mean is ``E q - mean_shift``.
        """
        c = dcm_from_quat(self.q)
        n_b, t_b = constraint_axes(axis, self.aoa)
        a = c @ n_b
        v = self.vel
        with_aoa = axis == VERTICAL and self.layout.n_aoa > 0
        d = 7 if with_aoa else 6
        m = np.zeros((d, d))
        mb = None
        if self.in_body_frame():
            # n_b . v_b is linear in (dtheta, xi_v): the remainder is the body velocity's
            # own second order since the model's last update, over (dtheta, xi_v, dw)
            mb = self.body_velocity_remainder_matrix(n_b, self._model_interval(axis))
        else:
            m[0:3, 0:3] = attitude_product_matrix(a, v)
            sa = skew(a)
            m[0:3, 3:6] = sa
            m[3:6, 0:3] = sa.T
        idx = _DTHETA_DV
        if with_aoa:
            b = c @ t_b
            m[6, 0:3] = m[0:3, 6] = -(b @ skew(v))
            m[6, 3:6] = m[3:6, 6] = -b
            m[6, 6] = -float(a @ v)
        if mb is not None:
            # the propagation carries the means of its terms (propagate), so only their
            # variance is the update's
            p9 = self.P[np.ix_(_DTHETA_DV_DW, _DTHETA_DV_DW)]
            mb_mean = remainder_moments(mb, p9).mean
            if not with_aoa:
                return mb, _DTHETA_DV_DW, mb_mean
        elif not with_aoa:
            return m, idx, 0.0
        # x = (dtheta, dv, da, AOA states): the angle's linear error da (through the
        # law's states and, with a law, the speed) beside the states it is made of, for
        # the angle's own second-order terms
        ia = self.layout.aoa
        na = self.layout.n_aoa
        t = np.zeros((7 + na, 6 + na))
        t[:6, :6] = np.eye(6)
        j = self.aoa_jacobian(v)
        t[6, 3:6] = j[VEL]
        t[6, 6:] = j[ia]
        t[7:, 6:] = np.eye(na)
        mx = np.zeros((7 + na, 7 + na))
        mx[:7, :7] = m
        speed = self._speed()
        if speed > 1.0:
            # alpha = w(V) (alpha_b + K n_w / V^2) mixes the speed with the law's states:
            # d2 alpha / dV d alpha_b = w', d2 alpha / dV dK = w' u - 2 w u / V, with
            # dV = v^T dv / V. In the lift-off blend the first dwarfs the model's sigma
            # (w' up to 0.5 per m/s against a law 1 deg uncertain); without it the
            # blend's slope made the speed look measured.
            u = self._lift_u_jac
            w, dw = self._lift_w, self._lift_dw
            mix = np.array([dw, dw * u - 2.0 * w * u / speed])
            dv_da = -float(b @ v)
            v_hat = v / speed
            cross = dv_da * np.outer(v_hat, mix[:na])  # (3, na): m/s per unit^2
            mx[3:6, 7:] = cross
            mx[7:, 3:6] = cross.T
            # and the speed's own curvature: V(v + dv) bends across the velocity, and the
            # law's 1 / V^2 (with w' times it) along it; the blend's w'' is
            # blend_remainder_var's
            k_u = self.aoa_k * u
            lift = self._unblended_aoa()
            slope = dw * lift - 2.0 * w * k_u / speed  # d alpha / dV, rad s/m
            along = -4.0 * dw * k_u / speed + 6.0 * w * k_u / speed**2
            vv = np.outer(v_hat, v_hat)
            mx[3:6, 3:6] += dv_da * (slope * (np.eye(3) - vv) / speed + along * vv)
        sel = np.concatenate((idx, np.arange(ia.start, ia.stop)))
        if mb is None:
            return t.T @ mx @ t, sel, 0.0
        # x = (dtheta, xi_v, da, AOA states, dw): the angle's terms beside the body
        # velocity's
        nx = 7 + na
        sel = np.concatenate((sel, np.arange(RATE.start, RATE.stop)))
        t2 = np.zeros((nx + 3, 6 + na + 3))
        t2[:nx, : 6 + na] = t
        t2[nx:, 6 + na :] = np.eye(3)
        m3 = np.zeros((nx + 3, nx + 3))
        m3[:nx, :nx] = mx
        m3[0:6, 0:6] += mb[0:6, 0:6]
        m3[nx:, 0:6] = mb[6:9, 0:6]
        m3[0:6, nx:] = mb[0:6, 6:9]
        m3[nx:, nx:] = mb[6:9, 6:9]
        return t2.T @ m3 @ t2, sel, mb_mean

    def _model_interval(self, axis: int) -> float:
        """Time since the vehicle model's last accepted update on ``axis``, s.

        :data:`BODY_REMAINDER_INTERVAL_S` before the first, and never more than
        :data:`BODY_REMAINDER_MAX_INTERVAL_S` (a long pause below the model's speed).
        """
        last = self._model_last_t.get(axis)
        if last is None:
            return BODY_REMAINDER_INTERVAL_S
        return min(max(self.t_s - last, 0.0), BODY_REMAINDER_MAX_INTERVAL_S)

    def body_velocity_remainder_matrix(self, n_b: np.ndarray, t_s: float) -> np.ndarray:
        """The body velocity's second order along ``n_b`` over ``t_s`` s (9, 9).

        With :attr:`body_velocity_error` the models' constraint ``n_b . v_b`` is linear in
        the error state at the update; what the filter's linear propagation left out
        since the last update is the body velocity's own second order,
        ``d dv_b / dt = - dw x dv_b + C^T dtheta x (dtheta x g) / 2 + (linear)``, taken
        over the interval with the errors at the update (``dv_b`` drifting back by its
        linear rate ``L = - dw x v_b - w x dv_b + C^T (g x dtheta)``, ``dtheta`` by
        ``C dw``):

        ``q = T dw^T [n]x dv_b - T^2/2 dw^T A(n, v_b) dw + T^2/2 dw^T [n]x [w]x dv_b
        - T^2/2 dw^T [n]x C^T [g]x dtheta + T/2 dtheta^T A_g dtheta
        - T^2/2 dtheta^T A_g C dw + T^3/6 dw^T C^T A_g C dw``,

        ``A(a, v) = (a v^T + v a^T)/2 - (a . v) I``
        (:func:`filters.vehicle_model.attitude_product_matrix`), ``A_g = A(C n, g)``, and
        ``dv_b = C^T (xi_v + v x dtheta)``. Returned as ``M`` with ``q = x^T M x / 2``
        over ``x = (dtheta, xi_v, dw)`` (NED rad, NED m/s, FRD rad/s).
        """
        tt = float(t_s)
        c = dcm_from_quat(self.q)
        v = self.vel
        g = self._g
        a = c @ n_b
        d_xi = c.T  # dv_b per xi_v
        d_th = c.T @ skew(v)  # dv_b per dtheta
        sn = skew(n_b)
        ag = attitude_product_matrix(a, g)
        b_wv = tt * sn + 0.5 * tt * tt * sn @ skew(self.w)  # dw^T b_wv dv_b
        m_wx = b_wv @ d_xi
        m_wt = b_wv @ d_th - 0.5 * tt * tt * sn @ c.T @ skew(g) - 0.5 * tt * tt * (ag @ c).T
        m = np.zeros((9, 9))
        m[0:3, 0:3] = tt * ag
        m[6:9, 6:9] = -tt * tt * attitude_product_matrix(n_b, c.T @ v) + (tt**3 / 3.0) * (
            c.T @ ag @ c
        )
        m[6:9, 0:3] = m_wt
        m[0:3, 6:9] = m_wt.T
        m[6:9, 3:6] = m_wx
        m[3:6, 6:9] = m_wx.T
        return m
