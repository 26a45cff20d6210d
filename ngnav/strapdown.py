"""Attitude from body rate: quaternion integration, no Euler-angle state.

The rotation over each sample interval is the rotation vector of a rate that
varies linearly between samples, ``phi = (w_k + w_{k+1}) dt / 2 +
(w_k x w_{k+1}) dt^2 / 12`` (second-order coning term), applied as
``q_{k+1} = q_k * exp(phi)``; ``q_nb`` maps body to NED.
"""

from __future__ import annotations

import numpy as np

from ngnav.records import check_time_axis
from ngnav.rotation import quat_from_rotvec, quat_multiply, quat_normalize


def integrate_rate(
    omega_b_rps: np.ndarray, t_s: np.ndarray, q0_nb: np.ndarray | None = None
) -> np.ndarray:
    """Integrate body rate (T, 3), rad/s, at times (T,), s, into ``q_nb`` (T, 4).

    Parameters
    ----------
    omega_b_rps : array (T, 3)
        Body angular rate, rad/s.
    t_s : array (T,)
        Sample times, strictly increasing, s.
    q0_nb : array (4,), optional
        Attitude at ``t_s[0]``; identity by default.
    """
    w = np.asarray(omega_b_rps, dtype=float)
    t = np.asarray(t_s, dtype=float)
    check_time_axis(t)
    if w.shape != (t.shape[0], 3):
        raise ValueError(f"omega_b_rps must have shape ({t.shape[0]}, 3), got {w.shape}")
    q0 = np.array([1.0, 0.0, 0.0, 0.0]) if q0_nb is None else quat_normalize(q0_nb)
    dt = np.diff(t)[:, None]
    phi = 0.5 * (w[:-1] + w[1:]) * dt + np.cross(w[:-1], w[1:]) * dt**2 / 12.0
    dq = quat_from_rotvec(phi)
    out = np.empty((t.shape[0], 4))
    out[0] = q0
    q = q0
    for k in range(dq.shape[0]):
        q = quat_multiply(q, dq[k])
        out[k + 1] = q
    return quat_normalize(out)


def rotation_angle_about(q_nb: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Signed rotation angle (rad) of ``q`` (..., 4) about a unit ``axis`` (3,).

    For a rotation about ``axis`` this is its exact angle; for a series of
    attitudes (T, 4) it is unwrapped along time, so turns beyond 180 deg read
    correctly.
    """
    q = np.asarray(q_nb, dtype=float)
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    angle = 2.0 * np.arctan2(q[..., 1:] @ axis, q[..., 0])
    if angle.ndim == 1:
        angle = np.unwrap(angle)
    return angle
