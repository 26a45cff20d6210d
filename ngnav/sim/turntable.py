"""The indexing head's exact truth: a turn about a body- and space-fixed axis.

All analytic: the rate derivative is the derivative of the rate profile, never a
finite difference of sampled attitude.
"""

from __future__ import annotations

import numpy as np

from ngnav.conventions import gravity_n_mps2
from ngnav.motion import min_jerk_step
from ngnav.records import FlightTruth
from ngnav.rotation import dcm_from_quat, quat_from_axis_angle, quat_multiply, quat_normalize


def fixed_axis_turn(
    angle_rad: float,
    *,
    duration_s: float,
    rest_before_s: float,
    rest_after_s: float,
    rate_hz: float,
    axis_b: np.ndarray,
    pivot_b_m: np.ndarray,
    q0_nb: np.ndarray | None = None,
) -> FlightTruth:
    """A turn by ``angle_rad`` about a body- and space-fixed axis (an indexing head).

    The body rests, turns with a minimum-jerk profile, and rests again. The
    axis passes through ``pivot_b_m`` (body frame, from the body origin), so
    the origin, off the axis, feels tangential and centripetal acceleration.

    Parameters
    ----------
    angle_rad : float
        Turn angle, rad (right-hand about ``axis_b``).
    duration_s, rest_before_s, rest_after_s : float
        Durations of the turn and of the rests around it, s.
    rate_hz : float
        Sample rate, Hz.
    axis_b : array (3,)
        Turn axis, body frame (normalised here).
    pivot_b_m : array (3,)
        A point of the axis, body frame, m.
    q0_nb : array (4,), optional
        Attitude before the turn; identity (level, facing north) by default.

    Returns
    -------
    FlightTruth
        The pivot stays at the NED origin; the body origin circles it.
    """
    for name, v in (("duration_s", duration_s), ("rate_hz", rate_hz)):
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"{name} must be positive, got {v}")
    if rest_before_s < 0 or rest_after_s < 0:
        raise ValueError("rest durations must not be negative")
    k = np.asarray(axis_b, dtype=float)
    k = k / np.linalg.norm(k)
    n = round((rest_before_s + duration_s + rest_after_s) * rate_hz) + 1
    t = np.arange(n) / rate_hz
    s, ds, dds = min_jerk_step((t - rest_before_s) / duration_s)
    alpha = angle_rad * s
    rate = angle_rad * ds / duration_s
    acc = angle_rad * dds / duration_s**2
    w = rate[:, None] * k
    wd = acc[:, None] * k
    q0 = np.array([1.0, 0.0, 0.0, 0.0]) if q0_nb is None else quat_normalize(q0_nb)
    q = quat_normalize(quat_multiply(q0, quat_from_axis_angle(k, alpha)))
    d = -np.asarray(pivot_b_m, dtype=float)  # origin relative to the pivot, body frame
    a_b = np.cross(wd, d) + np.cross(w, np.cross(w, d))
    c = dcm_from_quat(q)
    g_b = np.einsum("tji,j->ti", c, gravity_n_mps2())
    # the origin about the pivot, which stays at the NED origin
    pos = np.einsum("tij,j->ti", c, d)
    vel = np.einsum("tij,tj->ti", c, np.cross(w, d))
    return FlightTruth(t, pos, vel, q, w, wd, a_b - g_b)
