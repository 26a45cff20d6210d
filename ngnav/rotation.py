"""Hamilton scalar-first quaternions (``[w, x, y, z]``), vectorised.

All functions accept arrays with any number of leading dimensions and a last
axis of 4 (quaternions) or 3 (vectors). ``q_nb`` rotates body vectors into
NED (see :mod:`ngnav.conventions`). Single quaternions and vectors take a
scalar fast path (the filter calls these once per block; numpy's generic
stacking costs more than the arithmetic there).
"""

from __future__ import annotations

import math

import numpy as np


def _mul4(p: list[float], q: list[float]) -> list[float]:
    """Hamilton product of two quaternions given as 4 floats each."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return [
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ]


def _unit4(q: list[float]) -> list[float]:
    """4 floats scaled to a unit quaternion with a non-negative scalar part."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    n = -n if w < 0.0 else n
    return [w / n, x / n, y / n, z / n]


def _exp3(x: float, y: float, z: float) -> list[float]:
    """Exponential map of one rotation vector (rad) as 4 floats."""
    a = math.sqrt(x * x + y * y + z * z)
    k1 = 0.5 - a * a / 48.0 if a < 1e-4 else math.sin(0.5 * a) / a
    return [math.cos(0.5 * a), k1 * x, k1 * y, k1 * z]


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p * q``, shapes (..., 4)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    if p.ndim == 1 and q.ndim == 1:
        return np.array(_mul4(p.tolist(), q.tolist()))
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion), shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with a non-negative scalar part, shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        return np.array(_unit4(q.tolist()))
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Exponential map: rotation vector (..., 3), rad -> unit quaternion (..., 4).

    Accurate for small angles (uses the series of sin(x)/x below 1e-4 rad).
    """
    rotvec = np.asarray(rotvec, dtype=float)
    if rotvec.ndim == 1:
        return np.array(_exp3(*rotvec.tolist()))
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < 1e-4
    # sin(half)/angle; series 1/2 - angle^2/48 for small angles
    safe = np.where(small, 1.0, angle)
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([np.cos(half), k * rotvec], axis=-1)


def quat_rotate_by_rotvec(
    q: np.ndarray, rotvec: np.ndarray | list[float], *, left: bool
) -> np.ndarray:
    """One unit quaternion (4,) turned by one rotation vector (3,), rad, renormalised.

    ``left=False``: ``q * exp(rotvec)`` (a body-frame increment, as in strapdown
    integration); ``left=True``: ``exp(rotvec) * q`` (a NED-frame correction, the
    error-state reset). Equal to :func:`quat_normalize` of :func:`quat_multiply`
    and :func:`quat_from_rotvec`, without their array overhead.
    """
    e = _exp3(*np.asarray(rotvec, dtype=float).tolist())
    qf = np.asarray(q, dtype=float).tolist()
    return np.array(_unit4(_mul4(e, qf) if left else _mul4(qf, e)))


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Logarithm map: unit quaternion (..., 4) -> rotation vector (..., 3), rad.

    Returns the shortest rotation (angle in [0, pi]).
    """
    q = quat_normalize(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    small = s < 1e-12
    scale = np.where(small, 2.0 / np.where(small, q[..., :1], 1.0), angle / np.where(small, 1.0, s))
    return scale * v


def quat_from_axis_angle(axis: np.ndarray, angle_rad: np.ndarray | float) -> np.ndarray:
    """Quaternion for a rotation by ``angle_rad`` about unit ``axis`` (3,)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    angle = np.asarray(angle_rad, dtype=float)[..., None]
    return np.concatenate([np.cos(0.5 * angle), np.sin(0.5 * angle) * axis], axis=-1)


def dcm_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``C_nb`` (..., 3, 3) from ``q_nb`` (..., 4): ``v_n = C_nb @ v_b``."""
    q = quat_normalize(q)
    if q.ndim == 1:
        w, x, y, z = q.tolist()
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate body vectors into NED: ``v_n = q_nb * v_b * conj(q_nb)``; shapes (...,4), (...,3)."""
    return np.einsum("...ij,...j->...i", dcm_from_quat(q), np.asarray(v, dtype=float))


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (ZYX, rad) from ``q_nb``, shape (..., 3). For display only."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        # one quaternion (the live output's path): the same formulas without array overhead
        w, x, y, z = q.tolist()
        n = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / n, x / n, y / n, z / n
        return np.array(
            [
                math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                math.asin(min(1.0, max(-1.0, 2 * (w * y - z * x)))),
                math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
            ]
        )
    q = quat_normalize(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """Skew matrix ``[v]x`` (..., 3, 3) with ``skew(v) @ n == cross(v, n)``."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        x, y, z = v.tolist()
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    x, y, z = np.moveaxis(v, -1, 0)
    o = np.zeros_like(x)
    return np.stack(
        [np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], axis=-2
    )


_YZX = np.array([1, 2, 0])
_ZXY = np.array([2, 0, 1])


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` of two 3-vectors: ``np.cross``'s value without its axis handling."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (K, 3) arrays (``np.cross`` without its axis handling)."""
    # np.take on a small axis costs less than fancy indexing
    return a.take(_YZX, axis=1) * b.take(_ZXY, axis=1) - a.take(_ZXY, axis=1) * b.take(_YZX, axis=1)


def quat_from_euler(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """``q_nb`` (..., 4) of ZYX Euler angles (rad): yaw about z, then pitch, then roll."""
    r, p, y = (np.asarray(a, dtype=float) / 2 for a in (roll, pitch, yaw))
    z = np.zeros_like(r + p + y)
    qz = np.stack([np.cos(y) + z, z, z, np.sin(y) + z], -1)
    qy = np.stack([np.cos(p) + z, z, np.sin(p) + z, z], -1)
    qx = np.stack([np.cos(r) + z, np.sin(r) + z, z, z], -1)
    return quat_multiply(quat_multiply(qz, qy), qx)
