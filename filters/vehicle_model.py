"""The vehicle model's fixed parts: calm-air constraints on the body velocity.

An aircraft in calm air flies with no sideslip and at the angle of attack its lift
needs, so its velocity in the body frame (FRD) has no component along the lateral axis
and none along the wind-normal axis ``[-sin alpha, 0, cos alpha]``.
:class:`filters.ekf.NavFilter` measures both as zero (``update_sideslip``,
``update_angle_of_attack``) with the angle of attack from its lift law. This module holds
what those updates use that needs no filter state: the constraint axes, the second-order
remainder of their linearisation (its moments, and how many consecutive updates share
one value of it), the lift-off blend's spread beyond its linear term, and the record of
one update. Why each count has its value: docs/notes/filter-notes.md ("the sideslip remainder
is correlated", "the remainder counted longer in a coast").
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from ngnav.motion import min_jerk_step

#: Times the sideslip update counts the variance of its second-order remainder
#: (:meth:`filters.ekf.NavFilter.sideslip_second_order`). The remainder is a function of errors
#: that change over seconds, so consecutive 5 Hz updates see nearly the same value
#: (measured on ``uav-survey``, 6 runs: lag-1 correlation 0.97 in the outage, 0.8 while
#: GPS holds); as white noise the filter would average it down over many updates and
#: turn optimistic in the coast. Counting it 4 times treats one remainder in four
#: updates (0.8 s) as new: see docs/notes/filter-notes.md ("the sideslip remainder") for what 1, 4,
#: 10 and
#: 40 gave.
SIDESLIP_REMAINDER_UPDATES = 4.0
#: A fixed-wing's calm-air models' 1-sigma, deg: the ground velocity lies in the body's
#: x-z plane (no sideslip) and leaves the body x axis by the angle of attack alone. Calm
#: air makes both exact; this is a numerical floor, the models' second-order remainders
#: and the lift law's noise carry their real uncertainty in R.
CALM_AIR_SIGMA_DEG = 3e-6
#: A fixed-wing's zero-lift angle of attack before flight, deg, and its 1-sigma: a
#: cambered wing's few degrees either way; the flight learns it while GPS holds.
ZERO_LIFT_AOA_DEG = -1.5
ZERO_LIFT_AOA_SIGMA_DEG = 1.0
#: Times the body-velocity updates count the variance of the remainder's attitude-product
#: part (the ``dtheta^T A dtheta / 2`` of :meth:`filters.ekf.NavFilter.body_velocity_second_order`).
#: That part multiplies two attitude errors the constraint cannot see (for the sideslip
#: model: the rotation about the constraint axis, the pitch, times the roll about the
#: velocity), so no update shrinks it and it lasts as long as the tilt errors do: 40 is
#: the remainder's integrated autocorrelation measured on ``uav-survey``'s outage (38-41
#: updates, docs/notes/filter-notes.md "the sideslip remainder"; ``python -m studies.remainder``
#: measures it on any flight). Both counts are the defaults of ``filter.remainder_updates`` and
#: ``filter.attitude_remainder_updates``. Counted like the rest (4) it turned a hand-over's
#: 1 deg roll and pitch errors into a pitch and angle of attack 2-3 times surer than
#: their errors (``tactical``, 16 runs, 2-4 s: attitude NEES 7.3, angle of attack 6.1).
#: Since a hand-over counts as a coast's end (``NavFilter.handover_hold_s``) a flight
#: may count it as long as it lasts after the hand-over: ``tactical`` sets 7.
ATTITUDE_REMAINDER_UPDATES = 40.0
#: Times the body-velocity updates count the whole remainder in a coast: from
#: :data:`COAST_AFTER_S` without an accepted GPS position until ``coast_hold_s`` after
#: the last such update. Through a coast nothing renews the errors the remainder is made
#: of, and ``python -m studies.remainder`` measures its persistence there at 42 updates
#: (``uav-survey``, 8 runs, 300-330 s; 5-21 while GPS holds): counted 4 times the
#: coast's end read a joint NEES of 17.9 over 325-345 s (50 runs). The default of
#: ``filter.coast_remainder_updates``.
COAST_REMAINDER_UPDATES = 40.0
#: Time without an accepted GPS position after which the filter is coasting, s: five
#: fixes at 5 Hz, so one rejected fix (a glitch) is not a coast. The default of
#: ``filter.coast_after_s``.
COAST_AFTER_S = 1.0
#: ...or this many intervals of the fixes received, whichever is longer.
COAST_AFTER_FIXES = 5.0

#: The interval a body-velocity remainder (``NavFilter.body_velocity_error``) is taken
#: over before a model's first accepted update, s: the models' 5 Hz.
BODY_REMAINDER_INTERVAL_S = 0.2
#: ...and the longest it is taken over, s: after a pause (below the models' speed) the
#: errors at the update no longer describe the whole interval's, and the interval's
#: powers (up to its cube) would make the remainder the pause's length, not the errors'.
BODY_REMAINDER_MAX_INTERVAL_S = 1.0

#: Blocks by which the lift law's Jacobian load lags the load the angle is predicted
#: with. The angle's sensitivity to ``K`` is the load ``u``; taken from this block, its
#: noise is the noise in the predicted angle, and the update's gain times its innovation
#: then has a mean (``-K Var(u)`` along ``u``): errors in variables, which push the offset
#: and ``K`` apart along the direction a steady load cannot see (``uav-survey``, 12 runs:
#: +0.58 / -0.53 sigma at 540 s, -0.00 / +0.08 with the lag; docs/notes/filter-notes.md "the lift
#: law's
#: Jacobian takes the load two blocks back"). The pipeline's load is extrapolated from
#: this block and the last one, so two blocks back is the nearest load whose noise is
#: independent of it.
LIFT_JACOBIAN_LAG_BLOCKS = 2

#: FRD body axes of the vehicle-model pseudo-measurements: lateral (sideslip) and
#: vertical (angle of attack).
LATERAL = 1
VERTICAL = 2

#: Standard-normal grid (41 points over +-6 sigma) and its normalised Gaussian weights:
#: the lift-off blend's spread over a speed error (:func:`blend_spread_var`).
#: The blend is piecewise polynomial, which Gauss-Hermite rules integrate badly near its
#: ends (7 points: off by up to 100 %); this grid agrees with 4e6 sampled errors within
#: their standard error (scratch check, the blend's start, middle and end).
BLEND_Z = np.linspace(-6.0, 6.0, 41)
BLEND_W = np.exp(-0.5 * BLEND_Z**2) / np.exp(-0.5 * BLEND_Z**2).sum()


def constraint_axes(axis: int, aoa_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Constraint axis ``n_b`` and the wind x axis ``t_b`` (FRD) at angle of attack ``aoa_rad``.

    :data:`LATERAL`: ``n_b = e_y``; :data:`VERTICAL`: ``n_b = [-sin a, 0, cos a]``.
    ``t_b = [cos a, 0, sin a]`` either way (the body x axis at zero).
    """
    ca, sa = np.cos(aoa_rad), np.sin(aoa_rad)
    t_b = np.array([ca, 0.0, sa])
    if axis == LATERAL:
        return np.array([0.0, 1.0, 0.0]), t_b
    if axis == VERTICAL:
        return np.array([-sa, 0.0, ca]), t_b
    raise ValueError(f"axis must be LATERAL (1) or VERTICAL (2), got {axis}")


def attitude_product_matrix(a_ned: np.ndarray, v_ned_mps: np.ndarray) -> np.ndarray:
    """``A = (a v^T + v a^T) / 2 - (a . v) I`` (3, 3), m/s per rad^2.

    The velocity along a constraint axis ``a`` (NED) of a body turned by the small
    NED rotation ``dtheta`` holds ``dtheta^T A dtheta / 2`` beyond its linear term
    (:meth:`filters.ekf.NavFilter.body_velocity_second_order`).
    """
    a = np.asarray(a_ned, dtype=float)
    v = np.asarray(v_ned_mps, dtype=float)
    return 0.5 * (np.outer(a, v) + np.outer(v, a)) - float(a @ v) * np.eye(3)


class Remainder(NamedTuple):
    """A body-velocity model's second-order remainder (m/s; variances m^2/s^2).

    ``mean_att`` and ``var_att`` are the mean and variance of its attitude-product
    part alone (``dtheta^T A dtheta / 2``), the part no update of the model shrinks.
    """

    mean: float
    var: float
    var_att: float
    mean_att: float = 0.0


class BodyVelocityRecord(NamedTuple):
    """One vehicle-model update as the filter made it (``NavFilter.body_velocity_log``).

    The nominal state it linearised at, the model's value and Jacobian there, and
    the second-order remainder the update assumed: what
    :mod:`studies.remainder` needs to measure the remainder actually left
    against a truth.

    Attributes
    ----------
    t_s : float
        Filter time, s.
    axis : int
        :data:`LATERAL` (the sideslip model) or :data:`VERTICAL` (the angle of attack's).
    q_nb : array (4,)
        Nominal attitude, body (FRD) to NED, Hamilton scalar first.
    vel_ned_mps : array (3,)
        Nominal velocity, NED, m/s.
    aoa_rad : float
        The nominal angle of attack the vertical axis was taken at (0 for the lateral), rad.
    v_axis_mps : float
        The model's velocity along its constraint axis at the nominal state, m/s.
    h_att, h_vel : arrays (3,)
        Its Jacobian on the NED attitude error (m/s per rad) and on the velocity error.
    dv_daoa_mps : float
        Its change per radian of angle of attack, ``-(C t_b) . v`` (0 for the lateral),
        m/s per rad.
    remainder : Remainder
        The second-order remainder's mean and variances at the update.
    r_m2ps2 : float
        The update's R: the sigma's variance plus the remainder as counted (and, for the
        angle-of-attack model, the load's noise and the lift-off blend's), m^2/s^2.
    accepted : bool
        Whether the update passed its gate.
    """

    t_s: float
    axis: int
    q_nb: np.ndarray
    vel_ned_mps: np.ndarray
    aoa_rad: float
    v_axis_mps: float
    h_att: np.ndarray
    h_vel: np.ndarray
    dv_daoa_mps: float
    remainder: Remainder
    r_m2ps2: float
    accepted: bool


def remainder_variance(
    rem: Remainder,
    updates: float = SIDESLIP_REMAINDER_UPDATES,
    attitude_updates: float = ATTITUDE_REMAINDER_UPDATES,
) -> float:
    """What a body-velocity update adds to R for its remainder, m^2/s^2.

    The variance counted ``updates`` times (default :data:`SIDESLIP_REMAINDER_UPDATES`)
    and its attitude-product part ``attitude_updates`` times (default
    :data:`ATTITUDE_REMAINDER_UPDATES`), but never fewer times than the whole
    (``max(attitude_updates, updates)``: a coast's or hand-over's count covers the
    attitude part too): each count is the number of consecutive updates that share
    one value of that part.
    """
    return updates * rem.var + max(attitude_updates - updates, 0.0) * rem.var_att


def prior_weighted_count(count: float, r_counted: float, s_prior: float) -> float:
    """The remainder's count scaled by the weight its update keeps on the prior.

    Parameters
    ----------
    count : float
        The configured count (>= 1): consecutive updates that share one value of the
        remainder (:func:`remainder_variance`).
    r_counted : float
        The update's R with the configured count, m^2/s^2.
    s_prior : float
        The prior's variance along the constraint, ``h P h^T``, m^2/s^2.

    Returns
    -------
    float
        ``1 + (count - 1) w`` with ``w = R / (s + R) = 1 - h K``, the weight the
        posterior keeps on the prior along the constraint. A persistent remainder
        adds information it does not have only through what an update keeps of the
        earlier ones, which is that weight: where the prior along the constraint is
        fresh process noise (``s`` thousands of times R, GPS-held flight), the update
        replaces the constraint's combination by the measurement, the error left along
        it is the current remainder (counted once) and the gain is the same to
        ``(count - 1) R / s`` either way; where the prior is R's size or smaller
        (the update adds to what earlier ones left) the whole count applies.
        :class:`filters.ekf.NavFilter` applies it to the sideslip model only
        (``count_by_prior_weight``): the angle-of-attack model's prior along its
        constraint holds the lift law's states, which are not fresh noise.
    """
    w = r_counted / (s_prior + r_counted) if s_prior + r_counted > 0.0 else 1.0
    return 1.0 + (count - 1.0) * w


def remainder_moments(m: np.ndarray, px: np.ndarray) -> Remainder:
    """Moments of the remainder ``q = x^T M x / 2`` for a Gaussian error ``x ~ N(0, px)``.

    Parameters
    ----------
    m : array (d, d)
        The remainder's symmetric matrix over ``x = (dtheta, dv[, dalpha, AOA states])``:
        NED attitude error (rad), NED velocity error (m/s) and, for the angle-of-attack
        model with its state, the angle's linear error (rad) and the lift law's states
        (offset, rad; ``K``, m); m/s per unit of each pair.
    px : array (d, d)
        The covariance of ``x``, in the same order.

    Returns
    -------
    Remainder
        ``E q = tr(M P) / 2`` and ``Var q = tr(M P M P) / 2`` (m/s, m^2/s^2), the
        second-order filter's terms, and the same of the attitude-product part
        (``M`` and ``P`` restricted to the first three rows and columns).
    """
    mp = m @ px
    mpa = m[0:3, 0:3] @ px[0:3, 0:3]
    return Remainder(
        0.5 * float(np.trace(mp)),
        0.5 * float(np.sum(mp * mp.T)),
        0.5 * float(np.sum(mpa * mpa.T)),
        0.5 * float(np.trace(mpa)),
    )


def blend_spread_var(x0: float, sx: float) -> float:
    """Variance of the minimum-jerk step ``s`` beyond its linear term at ``x0``.

    ``Var[s(x0 + e) - s(x0) - s'(x0) e]`` for ``e ~ N(0, sx^2)``, on the 41-point grid
    :data:`BLEND_Z` (dimensionless: ``x0`` and ``sx`` in units of the step's width).
    The lift-off blend ``w(V)`` is this step over ``[0.8, 1]`` of the lift-off speed;
    :meth:`filters.ekf.NavFilter.blend_remainder_var` scales a speed error to it.
    """
    s0, ds0, _ = min_jerk_step(x0)
    s, _, _ = min_jerk_step(x0 + sx * BLEND_Z)
    r = s - s0 - ds0 * sx * BLEND_Z
    mean = float(BLEND_W @ r)
    return max(float(BLEND_W @ (r * r)) - mean * mean, 0.0)


#: Rate of the vehicle model's updates (sideslip and angle of attack, when configured)
#: over the hand-over and coasts (``NavFilter.counts_as_coast``), where the coast's count
#: is in updates at this rate; elsewhere too (the rate is fixed), Hz.
SIDESLIP_RATE_HZ = 5.0


@functools.lru_cache(maxsize=64)  # a run has one or two block sizes
def load_extrapolation_weights(k_now: int, k_prev: int) -> tuple[float, float]:
    """Weights ``(w_now, w_prev)`` that take two consecutive block means to the block end.

    A block of ``k_now`` samples ending at ``t_e`` (the filter's time) has its mean at
    ``t_e - (k_now - 1) dt / 2``; the block before, of ``k_prev`` samples, at
    ``t_e - k_now dt - (k_prev - 1) dt / 2``. The straight line through the two means,
    evaluated at ``t_e``, is ``w_now f_k + w_prev f_k-1`` with ``w_now = 1 + L``,
    ``w_prev = -L``, ``L = (k_now - 1) / (k_now + k_prev)``: 1.45 and -0.45 for
    ``tactical``'s blocks of 10 samples (1.5 / -0.5, the limit of long blocks, reaches
    half a sample past the block end: 0.5 ms, and at the level-off's load rate the
    angle of attack ran up to 0.6 sigma off the truth, the same way in every run;
    design notes, "the load's half-sample lead"). Exact for a load linear in time.

    Parameters
    ----------
    k_now, k_prev : int
        Samples in the current and the previous block (>= 1).

    Returns
    -------
    tuple of float
        ``(w_now, w_prev)``, summing to 1.
    """
    if k_now < 1 or k_prev < 1:
        raise ValueError(f"block sizes must be >= 1, got {k_now} and {k_prev}")
    lead = (k_now - 1) / (k_now + k_prev)
    return 1.0 + lead, -lead
