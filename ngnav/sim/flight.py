"""Exact truth of simulated flights: attitude, rate, rate derivative, position, velocity.

A flight is described by four smooth profiles, bank ``phi``, flight-path
pitch ``theta``, airspeed ``V`` and angle of attack ``alpha``, each a sum of
minimum-jerk transitions (continuous up to the second derivative). The first
three define the wind frame W (x along the velocity, no sideslip: coordinated
flight in calm air), so ``v_n = C_nw [V, 0, 0]``; the body is the wind frame
pitched nose-up by ``alpha`` about their common y axis, ``C_nb = C_nw R_y(alpha)``,
so the body sees its velocity as ``V [cos alpha, 0, sin alpha]``. The heading
rate is that of a coordinated turn, ``psi_dot = g0 tan(phi) / V`` (zero below
``taxi_speed_mps``), unless a transition asks for an explicit yaw rate.

Everything the array and the filter see follows analytically from the profiles
and their derivatives:

- ``q_nw`` from the ZYX Euler angles ``(psi, theta, phi)``, ``q_nb = q_nw q_y(alpha)``;
- ``omega_w`` from the Euler-rate kinematics and ``omega_dot_w`` from their exact
  time derivative (never a finite difference of sampled attitude);
  ``omega_b = C_bw omega_w + [0, alpha_dot, 0]`` and
  ``omega_dot_b = C_bw omega_dot_w + (dC_bw/dt) omega_w + [0, alpha_ddot, 0]``;
- a spinning body is rolled further about its own x axis by the spin angle ``s``
  (the spin rate's integral): ``q_nb = q_nw q_y(alpha) q_x(s)``;
- ``a_w = [V_dot, omega_wz V, -omega_wy V]`` (the derivative of ``C_nw [V, 0, 0]``),
  ``f_b = C_bw (a_w - C_wn g_n)``.

``alpha`` is either a scheduled profile or, with a :class:`LiftLaw`, the angle
a real aircraft needs for the lift its flight path asks for:
``alpha = w(V) (alpha0 + K n_w / V^2)``, with ``n_w = V omega_wy + g cos(theta)
cos(phi)`` the exact wind-frame normal load (the pull-up's ``V theta_dot`` term
included) and ``w(V)`` the lift-off blend (0 on the wheels). Its first and second
derivatives, which the rate derivative needs, come from second-order jets of the
profiles (a minimum-jerk profile's third derivative is exact too; where it jumps, at a
ramp's start and end, a sample takes the mean of its one-sided limits: see
:meth:`Profile.jerk`).

Heading and position, the two integrals, come from three-point Gauss-Legendre
quadrature of the same analytic derivatives over every sample interval (and,
for the heading inside an interval, over the part of it up to each node):
error of order ``dt^7``, far below anything a filter can see.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.conventions import G0_MPS2, gravity_n_mps2
from ngnav.motion import min_jerk_step
from ngnav.records import FlightTruth
from ngnav.rotation import dcm_from_quat, quat_from_euler, quat_multiply


@dataclass(frozen=True)
class Transition:
    """One minimum-jerk change of a profile.

    Parameters
    ----------
    start_s : float
        Time the change starts, s.
    duration_s : float
        Length of the change, s (> 0).
    delta : float
        Change of the profile value (rad for angles, m/s for speed, rad/s for yaw rate).
    """

    start_s: float
    duration_s: float
    delta: float


#: Times within this of a ramp's start or end are on it, s (:meth:`Profile.jerk`): a
#: sample time and a ramp end computed by different sums may differ by rounding.
JUMP_TOLERANCE_S = 1e-9


def _min_jerk_jerk(tau: np.ndarray) -> np.ndarray:
    """Third derivative ``d3s/dtau3`` of :func:`~ngnav.motion.min_jerk_step` (0 outside [0, 1];
    it jumps to and from 60 at the ends, where :meth:`Profile.jerk` takes the mean)."""
    x = np.asarray(tau, dtype=float)
    inside = (x >= 0.0) & (x <= 1.0)
    return np.where(inside, 60.0 - 360.0 * x + 360.0 * x * x, 0.0)


@dataclass(frozen=True)
class Profile:
    """A scalar profile: ``initial + sum_i delta_i s((t - start_i) / duration_i)``."""

    initial: float
    transitions: tuple[Transition, ...] = ()

    def evaluate(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, first and second time derivative at the times (T,)."""
        t = np.asarray(t_s, dtype=float)
        v = np.full(t.shape, self.initial)
        dv = np.zeros(t.shape)
        ddv = np.zeros(t.shape)
        flat = t.ravel()
        if flat.size > 1 and not np.all(flat[1:] >= flat[:-1]):
            order = np.argsort(flat, kind="stable")
            vals = self.evaluate(flat[order])
            out = [np.empty_like(flat) for _ in range(3)]
            for o, val in zip(out, vals, strict=True):
                o[order] = val
            return tuple(o.reshape(t.shape) for o in out)  # type: ignore[return-value]
        vf, dvf, ddvf = v.ravel(), dv.ravel(), ddv.ravel()
        for tr in self.transitions:
            i0 = int(np.searchsorted(flat, tr.start_s, side="left"))
            i1 = int(np.searchsorted(flat, tr.start_s + tr.duration_s, side="right"))
            vf[i1:] += tr.delta
            s, ds, dds = min_jerk_step((flat[i0:i1] - tr.start_s) / tr.duration_s)
            vf[i0:i1] += tr.delta * s
            dvf[i0:i1] += tr.delta * ds / tr.duration_s
            ddvf[i0:i1] += tr.delta * dds / tr.duration_s**2
        return v, dv, ddv

    def jerk(self, t_s: np.ndarray) -> np.ndarray:
        """Third time derivative at the times (T,).

        A minimum-jerk ramp's jerk jumps where it starts and ends. At a time on such a
        jump (within :data:`JUMP_TOLERANCE_S`) the value is the mean of the two one-sided
        limits: what a symmetric (linear-phase) anti-alias filter reads at a step, and
        the value whose trapezoid integral over the two neighbouring sample intervals is
        exact. A one-sided value there makes the trapezoid of sampled values miss the
        integral by half a sample interval times the jump, with the same sign in every
        run, since the ramps of a flight start on the sample grid: the lift law's
        angle of attack puts this jerk into the pitch acceleration, and ``tactical``'s
        level-off (a 5 deg pitch ramp over 1 s) then left its pitch rate 1.14 mrad/s
        off in every run (docs/notes/filter-notes.md, "the pitch jerk's jumps on the sample
        grid").
        """
        t = np.asarray(t_s, dtype=float)
        out = np.zeros(t.shape)
        for tr in self.transitions:
            end = tr.start_s + tr.duration_s
            at_end = (np.abs(t - tr.start_s) <= JUMP_TOLERANCE_S) | (
                np.abs(t - end) <= JUMP_TOLERANCE_S
            )
            # on a jump: the mean of the one-sided limits 0 and 60
            jerk = np.where(at_end, 30.0, _min_jerk_jerk((t - tr.start_s) / tr.duration_s))
            out += tr.delta * jerk / tr.duration_s**3
        return out


#: A second-order jet: value, first and second time derivative (arrays of one shape).
Jet = tuple[np.ndarray, np.ndarray, np.ndarray]


def _jmul(a: Jet, b: Jet) -> Jet:
    return (a[0] * b[0], a[1] * b[0] + a[0] * b[1], a[2] * b[0] + 2 * a[1] * b[1] + a[0] * b[2])


def _jcompose(f: np.ndarray, df: np.ndarray, ddf: np.ndarray, a: Jet) -> Jet:
    """The jet of ``f(a(t))`` from ``f, f', f''`` evaluated at ``a``."""
    return (f, df * a[1], ddf * a[1] ** 2 + df * a[2])


def _jaffine(a: Jet, scale: float, offset: float = 0.0) -> Jet:
    return (scale * a[0] + offset, scale * a[1], scale * a[2])


def _jcos(a: Jet) -> Jet:
    return _jcompose(np.cos(a[0]), -np.sin(a[0]), -np.cos(a[0]), a)


def _jsin(a: Jet) -> Jet:
    return _jcompose(np.sin(a[0]), np.cos(a[0]), -np.sin(a[0]), a)


def _jrecip(a: Jet, floor: float) -> Jet:
    """``1 / max(a, floor)`` (constant where ``a`` is below the floor)."""
    above = a[0] > floor
    x = np.maximum(a[0], floor)
    return (
        1.0 / x,
        np.where(above, -a[1] / x**2, 0.0),
        np.where(above, 2 * a[1] ** 2 / x**3 - a[2] / x**2, 0.0),
    )


def _jstep(a: Jet, start: float, width: float) -> Jet:
    """Minimum-jerk step of ``a`` from ``start`` over ``width``."""
    s, ds, dds = min_jerk_step((a[0] - start) / width)
    return _jcompose(s, ds / width, dds / width**2, a)


@dataclass(frozen=True)
class LiftLaw:
    """Angle of attack from the lift a flight needs (see the module docstring).

    ``alpha = w(V) (alpha0 + K n_w / V^2)``: steady lift ``n_w m = rho V^2 S C_La
    (alpha - alpha0) / 2`` gives ``K = 2 (m / S) / (rho C_La)``.

    Parameters
    ----------
    alpha0_rad : float
        Zero-lift angle of attack of the body x axis, rad.
    k_m : float
        ``K``, m (wing loading over density and lift slope).
    liftoff_speed_mps : float
        Below 0.8 times this speed the aircraft is on its wheels (``alpha`` = 0: the
        body x axis along the runway); ``w`` rises from 0 to 1 by a minimum-jerk step
        up to this speed.
    """

    alpha0_rad: float
    k_m: float
    liftoff_speed_mps: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.k_m) and self.k_m > 0):
            raise ValueError(f"lift k_m must be positive, got {self.k_m}")
        if not (np.isfinite(self.liftoff_speed_mps) and self.liftoff_speed_mps > 0):
            raise ValueError(f"liftoff_speed_mps must be positive, got {self.liftoff_speed_mps}")
        if not (np.isfinite(self.alpha0_rad) and abs(self.alpha0_rad) < 0.5):
            raise ValueError(f"alpha0 must be within +-0.5 rad, got {self.alpha0_rad}")

    def drawn(self, alpha0_sigma_rad: float, k_sigma_m: float, rng: np.random.Generator) -> LiftLaw:
        """One aircraft of this type: ``alpha0`` and ``K`` drawn around this law's values
        with the given 1-sigmas (rigging, payload, the day's density), the lift-off speed
        kept."""
        return LiftLaw(
            self.alpha0_rad + rng.normal(0.0, alpha0_sigma_rad),
            self.k_m + rng.normal(0.0, k_sigma_m),
            self.liftoff_speed_mps,
        )

    def weight(self, speed: Jet) -> Jet:
        """The lift-off blend ``w(V)`` as a jet."""
        v_lof = self.liftoff_speed_mps
        return _jstep(speed, 0.8 * v_lof, 0.2 * v_lof)


@dataclass(frozen=True)
class FlightPlan:
    """Profiles of a flight and its start.

    Attributes
    ----------
    duration_s : float
        Length of the flight, s.
    bank, pitch, speed : Profile
        Roll angle (rad) and pitch angle (rad) of the wind frame (the pitch is the
        flight-path angle), and airspeed (m/s).
    yaw_rate : Profile
        Extra heading rate (rad/s) on top of the coordinated-turn rate;
        used to turn on the ground.
    heading0_rad : float
        Initial heading (course), rad from north.
    taxi_speed_mps : float
        Below this speed the coordinated-turn heading rate is switched off
        (it tends to infinity as V -> 0); the switch is smooth (a min-jerk
        blend over the speed band ``[0.5, 1] * taxi_speed_mps``).
    aoa : Profile
        Angle of attack (rad): the body's nose-up pitch from the velocity, about
        body y. Zero by default (the body flies along its x axis).
    lift : LiftLaw, optional
        Angle of attack from the lift law instead (``aoa`` must then stay zero).
    spin_rate : Profile
        Roll rate of the body about its own x axis on top of the flight's (rad/s): a
        spinning projectile. Zero by default.
    """

    duration_s: float
    bank: Profile
    pitch: Profile
    speed: Profile
    yaw_rate: Profile = Profile(0.0)
    heading0_rad: float = 0.0
    taxi_speed_mps: float = 2.0
    aoa: Profile = Profile(0.0)
    lift: LiftLaw | None = None
    spin_rate: Profile = Profile(0.0)

    def __post_init__(self) -> None:
        if self.lift is not None and (self.aoa.initial != 0.0 or self.aoa.transitions):
            raise ValueError("give an angle-of-attack profile or a lift law, not both")

    def angle_of_attack(self, t_s: np.ndarray) -> Jet:
        """Angle of attack (rad) and its first and second derivatives at the times (T,)."""
        if self.lift is None:
            return self.aoa.evaluate(t_s)
        t = np.asarray(t_s, dtype=float)
        lift = self.lift
        phi = self.bank.evaluate(t)
        th = self.pitch.evaluate(t)
        dth = (th[1], th[2], self.pitch.jerk(t))
        v = self.speed.evaluate(t)
        vt = self.taxi_speed_mps
        inv_v = _jrecip(v, 0.25 * vt)  # the blend below is 0 where the floor acts
        tan, sec2 = np.tan(phi[0]), 1 / np.cos(phi[0]) ** 2
        tan_phi = _jcompose(tan, sec2, 2 * sec2 * tan, phi)
        coord = _jaffine(_jmul(tan_phi, inv_v), G0_MPS2)
        dpsi = _jmul(_jstep(v, 0.5 * vt, 0.5 * vt), coord)
        r = self.yaw_rate.evaluate(t)
        dpsi = (dpsi[0] + r[0], dpsi[1] + r[1], dpsi[2] + r[2])
        cphi, sphi, cth = _jcos(phi), _jsin(phi), _jcos(th)
        w_y = _jmul(dth, cphi)
        w_y2 = _jmul(_jmul(dpsi, sphi), cth)
        w_y = (w_y[0] + w_y2[0], w_y[1] + w_y2[1], w_y[2] + w_y2[2])
        n_w = _jmul(v, w_y)
        grav = _jaffine(_jmul(cth, cphi), G0_MPS2)
        n_w = (n_w[0] + grav[0], n_w[1] + grav[1], n_w[2] + grav[2])
        alpha = _jaffine(_jmul(n_w, _jmul(inv_v, inv_v)), lift.k_m, lift.alpha0_rad)
        return _jmul(lift.weight(v), alpha)

    def heading_rate(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Heading rate (rad/s) and its derivative (rad/s^2) at the times (T,)."""
        phi, dphi, _ = self.bank.evaluate(t_s)
        v, dv, _ = self.speed.evaluate(t_s)
        r, dr, _ = self.yaw_rate.evaluate(t_s)
        vt = self.taxi_speed_mps
        blend, dblend_dv, _ = min_jerk_step((v - 0.5 * vt) / (0.5 * vt))
        dblend = dblend_dv / (0.5 * vt) * dv
        vs = np.maximum(v, 0.25 * vt)  # blend is 0 there anyway; avoids 1/0
        tan, sec2 = np.tan(phi), 1.0 / np.cos(phi) ** 2
        coord = G0_MPS2 * tan / vs
        dcoord = np.where(v > 0.25 * vt, G0_MPS2 * (sec2 * dphi * vs - tan * dv) / vs**2, 0.0)
        return blend * coord + r, dblend * coord + blend * dcoord + dr


def euler_rates_to_body(
    euler: tuple[np.ndarray, np.ndarray, np.ndarray],
    rates: tuple[np.ndarray, np.ndarray, np.ndarray],
    accels: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Body rate and its exact derivative from ZYX Euler angles and their derivatives.

    Parameters
    ----------
    euler, rates, accels : tuples (phi, theta, psi) of arrays (T,)
        Angles (rad), rates (rad/s) and accelerations (rad/s^2).

    Returns
    -------
    omega_b_rps, omega_dot_b_rps2 : arrays (T, 3)
    """
    phi, th, _ = euler
    dphi, dth, dpsi = rates
    ddphi, ddth, ddpsi = accels
    sf, cf, st, ct = np.sin(phi), np.cos(phi), np.sin(th), np.cos(th)
    w = np.stack([dphi - dpsi * st, dth * cf + dpsi * sf * ct, -dth * sf + dpsi * cf * ct], axis=-1)
    wd = np.stack(
        [
            ddphi - ddpsi * st - dpsi * dth * ct,
            ddth * cf
            - dth * dphi * sf
            + ddpsi * sf * ct
            + dpsi * dphi * cf * ct
            - dpsi * dth * sf * st,
            -ddth * sf
            - dth * dphi * cf
            + ddpsi * cf * ct
            - dpsi * dphi * sf * ct
            - dpsi * dth * cf * st,
        ],
        axis=-1,
    )
    return w, wd


_GL_X = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GL_W = np.array([5.0, 8.0, 5.0]) / 9.0


def _integrate_heading_and_position(
    plan: FlightPlan, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Heading (T,) and NED position (T, 3) by Gauss-Legendre quadrature per interval."""
    h = np.diff(t)  # (T-1,)
    frac = 0.5 * (1.0 + _GL_X)  # node positions in an interval, as fractions
    nodes = t[:-1, None] + h[:, None] * frac  # (T-1, 3)
    dpsi_nodes = plan.heading_rate(nodes.ravel())[0].reshape(nodes.shape)
    psi = plan.heading0_rad + np.concatenate([[0.0], np.cumsum(0.5 * h * (dpsi_nodes @ _GL_W))])
    # heading at each node: psi(t_k) + integral from t_k to the node (GL on the sub-interval)
    sub = t[:-1, None, None] + (h[:, None] * frac)[:, :, None] * frac[None, None, :]
    dpsi_sub = plan.heading_rate(sub.ravel())[0].reshape(sub.shape)
    psi_nodes = psi[:-1, None] + 0.5 * (h[:, None] * frac) * (dpsi_sub @ _GL_W)
    th = plan.pitch.evaluate(nodes.ravel())[0].reshape(nodes.shape)
    v = plan.speed.evaluate(nodes.ravel())[0].reshape(nodes.shape)
    vel = np.stack(
        [v * np.cos(th) * np.cos(psi_nodes), v * np.cos(th) * np.sin(psi_nodes), -v * np.sin(th)],
        axis=-1,
    )  # (T-1, 3 nodes, 3)
    steps = 0.5 * h[:, None] * np.einsum("knc,n->kc", vel, _GL_W)
    pos = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    return psi, pos


def _spin_angle(plan: FlightPlan, t: np.ndarray) -> np.ndarray:
    """Spin angle (T,), rad: the spin rate's integral by Gauss-Legendre per interval
    (exact for the quintic minimum-jerk ramps)."""
    h = np.diff(t)
    nodes = t[:-1, None] + h[:, None] * 0.5 * (1.0 + _GL_X)
    rate = plan.spin_rate.evaluate(nodes.ravel())[0].reshape(nodes.shape)
    return np.concatenate([[0.0], np.cumsum(0.5 * h * (rate @ _GL_W))])


def _add_spin(
    plan: FlightPlan, t: np.ndarray, w: np.ndarray, wd: np.ndarray, f: np.ndarray, q: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Roll the body by the spin angle about its x axis: ``q_nb = q_nb' q_x(s)``, with
    ``omega_b = C_bb' omega_b' + [s_dot, 0, 0]`` and its exact derivative."""
    s = _spin_angle(plan, t)
    p, dp, _ = plan.spin_rate.evaluate(t)
    cs, ss = np.cos(s), np.sin(s)
    zero, one = np.zeros_like(s), np.ones_like(s)
    c = np.stack(
        [
            np.stack([one, zero, zero], -1),
            np.stack([zero, cs, ss], -1),
            np.stack([zero, -ss, cs], -1),
        ],
        axis=-2,
    )  # (T, 3, 3): rows are the spun body's axes in the unspun body
    dc = p[:, None, None] * np.stack(
        [
            np.stack([zero, zero, zero], -1),
            np.stack([zero, -ss, cs], -1),
            np.stack([zero, -cs, -ss], -1),
        ],
        axis=-2,
    )
    e_x = np.array([1.0, 0.0, 0.0])
    w_s = np.einsum("tij,tj->ti", c, w) + p[:, None] * e_x
    wd_s = np.einsum("tij,tj->ti", c, wd) + np.einsum("tij,tj->ti", dc, w) + dp[:, None] * e_x
    q_x = np.stack([np.cos(s / 2), np.sin(s / 2), zero, zero], -1)
    return w_s, wd_s, np.einsum("tij,tj->ti", c, f), quat_multiply(q, q_x)


def fly(plan: FlightPlan, rate_hz: float) -> FlightTruth:
    """Sample the exact truth of ``plan`` at ``rate_hz`` from t = 0 to its duration.

    Raises
    ------
    ValueError
        If the rate or duration is not positive, or the pitch reaches +-90 deg
        (the Euler description is singular there).
    """
    if not np.isfinite(rate_hz) or rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    if not np.isfinite(plan.duration_s) or plan.duration_s <= 0:
        raise ValueError(f"duration_s must be positive, got {plan.duration_s}")
    n = round(plan.duration_s * rate_hz) + 1
    t = np.arange(n) / rate_hz

    psi, pos = _integrate_heading_and_position(plan, t)
    phi, dphi, ddphi = plan.bank.evaluate(t)
    th, dth, ddth = plan.pitch.evaluate(t)
    if np.any(np.abs(th) >= np.deg2rad(89.0)):
        raise ValueError("pitch reaches +-89 deg: the Euler-angle flight description is singular")
    v, dv, _ = plan.speed.evaluate(t)
    dpsi, ddpsi = plan.heading_rate(t)
    w_w, wd_w = euler_rates_to_body((phi, th, psi), (dphi, dth, dpsi), (ddphi, ddth, ddpsi))
    q_nw = quat_from_euler(phi, th, psi)
    c_nw = dcm_from_quat(q_nw)
    vel = v[:, None] * c_nw[:, :, 0]
    a_w = np.stack([dv, w_w[:, 2] * v, -w_w[:, 1] * v], axis=-1)
    f_w = a_w - np.einsum("tji,j->ti", c_nw, gravity_n_mps2())
    # the body: the wind frame pitched nose-up by alpha about the common y axis
    al, dal, ddal = plan.angle_of_attack(t)
    ca, sa = np.cos(al), np.sin(al)
    zero, one = np.zeros_like(al), np.ones_like(al)
    c_bw = np.stack(
        [
            np.stack([ca, zero, -sa], -1),
            np.stack([zero, one, zero], -1),
            np.stack([sa, zero, ca], -1),
        ],
        axis=-2,
    )  # (T, 3, 3), rows: body axes in the wind frame
    dc_bw = dal[:, None, None] * np.stack(
        [
            np.stack([-sa, zero, -ca], -1),
            np.stack([zero, zero, zero], -1),
            np.stack([ca, zero, -sa], -1),
        ],
        axis=-2,
    )
    e_y = np.array([0.0, 1.0, 0.0])
    w = np.einsum("tij,tj->ti", c_bw, w_w) + dal[:, None] * e_y
    wd = (
        np.einsum("tij,tj->ti", c_bw, wd_w)
        + np.einsum("tij,tj->ti", dc_bw, w_w)
        + ddal[:, None] * e_y
    )
    q_y = np.stack([np.cos(al / 2), zero, np.sin(al / 2), zero], -1)
    q = quat_multiply(q_nw, q_y)
    f_b = np.einsum("tij,tj->ti", c_bw, f_w)
    if plan.spin_rate.initial != 0.0 or plan.spin_rate.transitions:
        w, wd, f_b, q = _add_spin(plan, t, w, wd, f_b, q)
    return FlightTruth(t, pos, vel, q, w, wd, f_b)
