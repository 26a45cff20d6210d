"""Compiled inner loops of a filter step (numba): its arithmetic outside filterpy.

Each kernel is the one implementation of its formula (the ``NavFilter`` methods and
:mod:`filters.algebra` call it, and say why the formula is what it is). A block's step
was some 400 small numpy calls around filterpy's predict and update, ten times the
cost of filterpy alone (``ngnav bench-filter``); the call overhead, not the
arithmetic, was the cost. Compiled on first use and cached on disk (``cache=True``:
the next process loads it).

One file on purpose, grouped by the model it serves (nominal and process, measurements,
channel health): numba drops a cached kernel when its own file changes, not when a
kernel it calls in another file does, so a split would leave stale compiled callers
after an edit to a shared helper.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from filters.state import ATT, N_NAV, POS, RATE, VEL

#: An array argument that is not there (a kernel tests its size).
ABSENT = np.zeros((0, 0))
#: An absent vector argument.
NO_VECTOR = np.zeros(0)
# the navigation blocks' first rows (numba reads them as compile-time constants)
_POS, _VEL, _ATT, _RATE = POS.start, VEL.start, ATT.start, RATE.start


# -------- rotations and small helpers


@njit(cache=True)
def dcm(q: np.ndarray) -> np.ndarray:
    """``C_nb`` (3, 3) of a quaternion (4,), normalised with a non-negative scalar part."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    w, x, y, z = w / n, x / n, y / n, z / n
    c = np.empty((3, 3))
    c[0, 0] = 1 - 2 * (y * y + z * z)
    c[0, 1] = 2 * (x * y - w * z)
    c[0, 2] = 2 * (x * z + w * y)
    c[1, 0] = 2 * (x * y + w * z)
    c[1, 1] = 1 - 2 * (x * x + z * z)
    c[1, 2] = 2 * (y * z - w * x)
    c[2, 0] = 2 * (x * z - w * y)
    c[2, 1] = 2 * (y * z + w * x)
    c[2, 2] = 1 - 2 * (x * x + y * y)
    return c


@njit(cache=True)
def rotate_right(q: np.ndarray, rx: float, ry: float, rz: float) -> np.ndarray:
    """``q * exp(r)`` (4,), renormalised (:func:`ngnav.rotation.quat_rotate_by_rotvec`)."""
    return _unit_product(q, _exp(rx, ry, rz))


@njit(cache=True)
def _unit_product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The Hamilton product ``p * q`` (4,) scaled to unit norm, scalar part non-negative."""
    pw, px, py, pz = p[0], p[1], p[2], p[3]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    w = pw * qw - px * qx - py * qy - pz * qz
    x = pw * qx + px * qw + py * qz - pz * qy
    y = pw * qy - px * qz + py * qw + pz * qx
    z = pw * qz + px * qy - py * qx + pz * qw
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0.0:
        n = -n
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = w / n, x / n, y / n, z / n
    return out


@njit(cache=True)
def _exp(rx: float, ry: float, rz: float) -> np.ndarray:
    """The quaternion (4,) of a rotation vector (rad), the series of sin(x)/x below 1e-4."""
    a = math.sqrt(rx * rx + ry * ry + rz * rz)
    k1 = 0.5 - a * a / 48.0 if a < 1e-4 else math.sin(0.5 * a) / a
    e = np.empty(4)
    e[0], e[1], e[2], e[3] = math.cos(0.5 * a), k1 * rx, k1 * ry, k1 * rz
    return e


@njit(cache=True)
def _skew(v: np.ndarray) -> np.ndarray:
    s = np.zeros((3, 3))
    s[0, 1], s[0, 2] = -v[2], v[1]
    s[1, 0], s[1, 2] = v[2], -v[0]
    s[2, 0], s[2, 1] = -v[1], v[0]
    return s


@njit(cache=True)
def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty_like(a)
    for s in range(a.shape[0]):
        out[s, 0] = a[s, 1] * b[s, 2] - a[s, 2] * b[s, 1]
        out[s, 1] = a[s, 2] * b[s, 0] - a[s, 0] * b[s, 2]
        out[s, 2] = a[s, 0] * b[s, 1] - a[s, 1] * b[s, 0]
    return out


@njit(cache=True)
def shrink(x: np.ndarray, var: np.ndarray, clear2: float = 0.0) -> np.ndarray:
    """``sign(x) sqrt(x^2 - var)`` per component, zero where ``x^2 - var <= clear2 var``
    (``algebra.shrink_to_size``; ``clear2`` its ``clear_sigmas`` squared)."""
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        xi = x[i]
        d = xi * xi - var[i]
        out[i] = math.copysign(math.sqrt(d), xi) if d > clear2 * var[i] else 0.0  # var >= 0
    return out


@njit(cache=True)
def _dot_last(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``d @ w`` (m, 3) for ``d`` (m, 3, 3): products' derivatives at the rate ``w`` (3,)."""
    out = np.empty((d.shape[0], 3))
    for r in range(d.shape[0]):
        for c in range(3):
            out[r, c] = d[r, c, 0] * w[0] + d[r, c, 1] * w[1] + d[r, c, 2] * w[2]
    return out


# -------- the nominal state: mechanisation, injection, resets


@njit(cache=True)
def mechanise(
    last_wdot: np.ndarray,
    wdot: np.ndarray,
    bw: np.ndarray,
    last_f: np.ndarray,
    f: np.ndarray,
    bf: np.ndarray,
    mw: np.ndarray,
    mw0: np.ndarray,
    wts: np.ndarray,
    wts1: np.ndarray,
    w0: np.ndarray,
    m: np.ndarray,
    g_n: np.ndarray,
):
    """One block's rates, attitude increment and force integrals (``NavFilter.propagate``).

    ``wdot``, ``f`` (K, 3) the block's compensated samples, ``last_*`` (3,) the previous
    block's last; ``bw``, ``bf`` (3,) what the nominal removes from them; ``mw``, ``mw0``,
    ``wts`` the block's integration weights (``NavFilter._block_weights``); ``w0`` (3,)
    the rate at the block start; ``m`` (3, 3) the map of the block-start body force to
    NED; ``g_n`` (3,) gravity. Returns the rates at the K samples (K, 3), the velocity
    increment, the position increment beyond ``K dt v0`` and the mean of ``m f + g``
    (rows of (3, 3)), and the block's rotation vector with its coning term (3,).
    """
    k = wdot.shape[0]
    wd = np.empty((k + 1, 3))
    f_c = np.empty((k + 1, 3))
    for a in range(3):
        wd[0, a] = last_wdot[a] - bw[a]
        f_c[0, a] = last_f[a] - bf[a]
    for s in range(k):
        for a in range(3):
            wd[s + 1, a] = wdot[s, a] - bw[a]
            f_c[s + 1, a] = f[s, a] - bf[a]
    lin = mw @ wd
    for r in range(lin.shape[0]):
        for a in range(3):
            lin[r, a] += mw0[r, 0] * w0[a]
    w = lin[:k].copy()
    alpha = lin[k : 2 * k]
    cum = lin[2 * k :]
    cf = _cross_rows(cum, f_c)
    ccf = _cross_rows(cum, cf)
    f_b0 = f_c + cf + 0.5 * ccf
    y = (wts @ f_b0) @ m.T
    for r in range(3):
        for a in range(3):
            y[r, a] += wts1[r, 0] * g_n[a]
    mm = np.zeros((3, 3))  # sum_s cum_s alpha_s^T over the block's samples
    for s in range(k):
        for a in range(3):
            for b in range(3):
                mm[a, b] += cum[s, a] * alpha[s, b]
    rot = np.empty(3)
    rot[0] = cum[k, 0] + 0.5 * (mm[1, 2] - mm[2, 1])
    rot[1] = cum[k, 1] + 0.5 * (mm[2, 0] - mm[0, 2])
    rot[2] = cum[k, 2] + 0.5 * (mm[0, 1] - mm[1, 0])
    return w, y, rot


@njit(cache=True)
def body_frame_gravity(
    g: np.ndarray, p: np.ndarray, c: np.ndarray, vel: np.ndarray, att0: int, vel0: int, rate0: int
) -> np.ndarray:
    """Gravity (3,) as the body-frame velocity error's mean propagation reads it
    (``NavFilter.propagate``): ``g + (P_att - tr(P_att) I) g / 2`` less
    ``C axial(E[dw dv_b^T])``, ``E[dw dv_b^T] = P_wv C - P_wtheta [v]x C``."""
    pa = np.ascontiguousarray(p[att0 : att0 + 3, att0 : att0 + 3])
    tr = pa[0, 0] + pa[1, 1] + pa[2, 2]
    g_n = g + 0.5 * (pa @ g - tr * g)
    pwv = np.ascontiguousarray(p[rate0 : rate0 + 3, vel0 : vel0 + 3])
    pwt = np.ascontiguousarray(p[rate0 : rate0 + 3, att0 : att0 + 3])
    x = pwv @ c - pwt @ _skew(vel) @ c
    ax = np.empty(3)
    ax[0] = x[1, 2] - x[2, 1]
    ax[1] = x[2, 0] - x[0, 2]
    ax[2] = x[0, 1] - x[1, 0]
    return g_n - c @ ax


@njit(cache=True)
def propagate_nominal(
    q: np.ndarray,
    pos: np.ndarray,
    vel: np.ndarray,
    w0: np.ndarray,
    p: np.ndarray,
    g: np.ndarray,
    body: bool,
    last_wdot: np.ndarray,
    wdot: np.ndarray,
    bw: np.ndarray,
    last_f: np.ndarray,
    f: np.ndarray,
    bf: np.ndarray,
    mw: np.ndarray,
    mw0: np.ndarray,
    wts: np.ndarray,
    wts1: np.ndarray,
    dt: float,
):
    """The nominal state through one block (``NavFilter.propagate``, which says why):
    the force map and gravity for the velocity error's frame (``body``), then
    :func:`mechanise`. Returns the rates at the K samples (K, 3), the new ``q``, ``pos``,
    ``vel``, ``C_nb`` at the block start and the block's mean NED force (3,)."""
    c0 = dcm(q)
    if body:
        # the truth's body velocity moves by f - w x v_b + C_true^T g: its mean holds
        # gravity's attitude curvature and the rate-velocity product's -E[dw x dv_b]
        m = c0
        g_n = body_frame_gravity(g, p, c0, vel, _ATT, _VEL, _RATE)
    else:
        # E[C f] = (I + (P_att - tr(P_att) I) / 2) C f  (second order in the attitude error,
        # about the estimate: the transition's -[f_n]x is built on this force)
        pa = np.ascontiguousarray(p[_ATT : _ATT + 3, _ATT : _ATT + 3])
        m = pa @ c0
        m *= 0.5
        m += (1.0 - 0.5 * (pa[0, 0] + pa[1, 1] + pa[2, 2])) * c0
        g_n = g
    w, y, rot = mechanise(last_wdot, wdot, bw, last_f, f, bf, mw, mw0, wts, wts1, w0, m, g_n)
    k = wdot.shape[0]
    pos_new = pos + (k * dt) * vel + y[1]
    vel_new = vel + y[0]
    q_new = rotate_right(q, rot[0], rot[1], rot[2])
    return w, q_new, pos_new, vel_new, c0, y[2] - g_n


@njit(cache=True)
def remove_feature_residual(
    q: np.ndarray,
    w: np.ndarray,
    vel: np.ndarray,
    pos: np.ndarray,
    r: np.ndarray,
    t_s: float,
    w_blk: np.ndarray,
    dt: float,
):
    """A constant error ``r`` (6,) in a block's solved ``[wdot, f]`` out of the nominal
    state propagated with it for ``t_s`` s (``NavFilter.remove_feature_residual``) and,
    in place, out of the block's rates ``w_blk`` (K, 3) at its samples (interval ``dt``).
    Returns the new rate, attitude, velocity and position."""
    t2 = 0.5 * t_s * t_s
    c = dcm(q)
    w_new = w - t_s * r[0:3]
    q_new = rotate_right(q, -t2 * r[0], -t2 * r[1], -t2 * r[2])
    dv = c @ np.ascontiguousarray(r[3:6])
    vel_new = vel - t_s * dv
    pos_new = pos - t2 * dv
    for s in range(w_blk.shape[0]):
        for a in range(3):
            w_blk[s, a] = w_blk[s, a] - ((s + 1) * dt) * r[a]
    return w_new, q_new, vel_new, pos_new


@njit(cache=True)
def inject(q: np.ndarray, v_old: np.ndarray, dth: np.ndarray, dv: np.ndarray, body: bool):
    """A correction's attitude and velocity and its reset Jacobian's rows
    (``NavFilter._inject``).

    ``q`` (4,) ``q_nb``; ``v_old`` (3,) the NED velocity; ``dth`` (3,) the NED attitude
    correction; ``dv`` (3,) the velocity correction, body-style when ``body`` (the body
    velocity takes it and the corrected attitude carries it), else NED. Returns the new
    ``q`` (4,) and velocity (3,), the attitude rows ``ga`` (3, 3)
    (``algebra.attitude_reset_jacobian``) and, body-style, the velocity rows ``gvv``,
    ``gvt`` (3, 3) (``algebra.body_velocity_reset_jacobian``; (0, 0) otherwise).
    """
    e = _exp(dth[0], dth[1], dth[2])
    if body:
        u = v_old + dv
        u[0] += v_old[1] * dth[2] - v_old[2] * dth[1]
        u[1] += v_old[2] * dth[0] - v_old[0] * dth[2]
        u[2] += v_old[0] * dth[1] - v_old[1] * dth[0]
        v_new = dcm(e) @ u
    else:
        v_new = v_old + dv
    q_new = _unit_product(e, q)  # exp(dth) * q
    ga = attitude_reset_rows(dth)
    if not body:
        return q_new, v_new, ga, np.zeros((0, 0)), np.zeros((0, 0))
    gvv, gvt = body_velocity_reset_rows(dth, dv, v_old)
    return q_new, v_new, ga, gvv, gvt


@njit(cache=True)
def inject_error(
    dx: np.ndarray,
    p: np.ndarray,
    q: np.ndarray,
    pos: np.ndarray,
    vel: np.ndarray,
    w: np.ndarray,
    bias: np.ndarray,
    dr: np.ndarray,
    dg: np.ndarray,
    aoa_b: float,
    aoa_k: float,
    offsets: tuple,
    body_allowed: bool,
    max_frame_mps: float,
    max_inject_mps: float,
    g_rows: np.ndarray,
):
    """The error state ``dx`` (n,) folded into the nominal state, and P's reset
    (``NavFilter._inject``, which says why).

    ``offsets`` holds the first columns of the biases, the sensor positions, the sensing
    axes and the angle-of-attack states and how many of the last there are. The correction
    is body-style (:func:`inject`) when ``body_allowed`` (the velocity error may be in the
    body frame), the attitude's curvature of the velocity is at most ``max_frame_mps``
    (:func:`body_frame_curvature_ok`) and the correction's, ``|v| |dtheta|^2 / 2``, at most
    ``max_inject_mps``. P becomes ``G P G^T`` in place (:func:`reset_rows_in_place`: the
    caller's P is filterpy's new posterior, which nothing else holds). Returns the new
    ``q``, ``pos``, ``vel``, ``w``, ``bias``, ``dr``, ``dg`` (new arrays), the AOA estimates
    and whether body-style; writes the Jacobian's rows ``ga``, ``gvv``, ``gvt`` (3, 3) into
    ``g_rows`` (3, 3, 3) (the last two only body-style).
    """
    bias0, dr0, cal0, aoa0, n_aoa = offsets
    dth = dx[_ATT : _ATT + 3].copy()
    body = False
    if body_allowed and body_frame_curvature_ok(p, vel, max_frame_mps):
        speed = math.sqrt(vel[0] * vel[0] + vel[1] * vel[1] + vel[2] * vel[2])
        th2 = dth[0] * dth[0] + dth[1] * dth[1] + dth[2] * dth[2]
        body = 0.5 * speed * th2 <= max_inject_mps
    q_new, v_new, ga, gvv, gvt = inject(q, vel, dth, dx[_VEL : _VEL + 3].copy(), body)
    g_rows[0] = ga
    if body:
        g_rows[1] = gvv
        g_rows[2] = gvt
    reset_rows_in_place(p, ga, gvv, gvt, _ATT, _VEL)
    pos_new = pos + dx[_POS : _POS + 3]
    w_new = w + dx[_RATE : _RATE + 3]
    bias_new = bias + dx[bias0 : bias0 + bias.shape[0]]
    dr_new = dr + dx[dr0 : dr0 + dr.shape[0]]
    dg_new = dg + dx[cal0 : cal0 + dg.shape[0]]
    if n_aoa:
        aoa_b += dx[aoa0]
        if n_aoa == 2:
            aoa_k += dx[aoa0 + 1]
    return q_new, pos_new, v_new, w_new, bias_new, dr_new, dg_new, aoa_b, aoa_k, body


@njit(cache=True)
def attitude_curvature(p: np.ndarray, v: np.ndarray) -> float:
    """``|v| tr(P_att) / 2`` (m/s): the size of the NED velocity's second-order part under
    the attitude's uncertainty (``NavFilter.in_body_frame``)."""
    speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return 0.5 * speed * (p[_ATT, _ATT] + p[_ATT + 1, _ATT + 1] + p[_ATT + 2, _ATT + 2])


@njit(cache=True)
def body_frame_curvature_ok(p: np.ndarray, v: np.ndarray, max_mps: float) -> bool:
    """Whether :func:`attitude_curvature` is at most ``max_mps``: the body-frame velocity
    error's bound (``NavFilter.in_body_frame``)."""
    return attitude_curvature(p, v) <= max_mps


@njit(cache=True)
def symmetrised(p: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2`` (n, n), a new array."""
    out = p.copy()
    symmetrise(out)
    return out


@njit(cache=True)
def symmetrise(p: np.ndarray) -> None:
    """``P`` (n, n) made ``(P + P^T) / 2`` in place (each pair read before it is written)."""
    n = p.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            s = 0.5 * (p[i, j] + p[j, i])
            p[i, j] = s
            p[j, i] = s


@njit(cache=True)
def attitude_reset_rows(dth: np.ndarray) -> np.ndarray:
    """``I + [dth]x / 2`` with its heading column held at ``e_z`` (3, 3)
    (``algebra.attitude_reset_jacobian``, which says why)."""
    hx, hy, hz = 0.5 * dth[0], 0.5 * dth[1], 0.5 * dth[2]
    ga = np.eye(3)
    ga[0, 1], ga[1, 0], ga[2, 0], ga[2, 1] = -hz, hz, -hy, hx
    return ga


@njit(cache=True)
def body_velocity_reset_rows(dth: np.ndarray, dv: np.ndarray, v: np.ndarray):
    """``(G_vv, G_vtheta)`` (3, 3) each (``algebra.body_velocity_reset_jacobian``)."""
    st = _skew(dth)
    sv = _skew(v)
    gvv = np.eye(3) + st
    gvt = st @ sv - _skew(dv) - 0.5 * sv @ st
    return gvv, gvt


@njit(cache=True)
def reset_rows(
    p: np.ndarray, ga: np.ndarray, gvv: np.ndarray, gvt: np.ndarray, att0: int, vel0: int
) -> np.ndarray:
    """``G P G^T`` (n, n), symmetrised, for ``G`` the identity but its attitude rows ``ga``
    (3, 3) and, unless ``gvv`` is (0, 0), its velocity rows ``[gvv, gvt]`` on the
    velocity and attitude columns (``algebra.apply_reset_jacobian``)."""
    out = p.copy()
    reset_rows_in_place(out, ga, gvv, gvt, att0, vel0)
    return out


@njit(cache=True)
def reset_rows_in_place(
    p: np.ndarray, ga: np.ndarray, gvv: np.ndarray, gvt: np.ndarray, att0: int, vel0: int
) -> None:
    """:func:`reset_rows` written into ``p`` (each column's three or six entries are read
    before they are written, so the result is the same to the bit)."""
    n = p.shape[0]
    body = gvv.shape[0] > 0
    # G's rows, then its columns, on three rows/columns each: loops (a BLAS call costs more
    # than these 3 x 3 x n products)
    for j in range(n):
        t0, t1, t2 = p[att0, j], p[att0 + 1, j], p[att0 + 2, j]
        if body:
            v0, v1, v2 = p[vel0, j], p[vel0 + 1, j], p[vel0 + 2, j]
            for i in range(3):
                p[vel0 + i, j] = (gvv[i, 0] * v0 + gvv[i, 1] * v1 + gvv[i, 2] * v2) + (
                    gvt[i, 0] * t0 + gvt[i, 1] * t1 + gvt[i, 2] * t2
                )
        for i in range(3):
            p[att0 + i, j] = ga[i, 0] * t0 + ga[i, 1] * t1 + ga[i, 2] * t2
    for j in range(n):
        t0, t1, t2 = p[j, att0], p[j, att0 + 1], p[j, att0 + 2]
        if body:
            v0, v1, v2 = p[j, vel0], p[j, vel0 + 1], p[j, vel0 + 2]
            for i in range(3):
                p[j, vel0 + i] = (v0 * gvv[i, 0] + v1 * gvv[i, 1] + v2 * gvv[i, 2]) + (
                    t0 * gvt[i, 0] + t1 * gvt[i, 1] + t2 * gvt[i, 2]
                )
        for i in range(3):
            p[j, att0 + i] = t0 * ga[i, 0] + t1 * ga[i, 1] + t2 * ga[i, 2]
    symmetrise(p)


@njit(cache=True)
def ned_velocity_curvature(v: np.ndarray, p_full: np.ndarray):
    """Mean (3,) and covariance (3, 3) of the NED velocity's second-order part under the
    body-frame velocity error (``algebra.ned_velocity_curvature``): ``v`` (3,) the NED
    velocity, ``p_full`` (n, n) the error covariance (its ``(dtheta, xi_v)`` block read)."""
    idx = (_ATT, _ATT + 1, _ATT + 2, _VEL, _VEL + 1, _VEL + 2)
    p6 = np.empty((6, 6))
    for a in range(6):
        for b in range(6):
            p6[a, b] = p_full[idx[a], idx[b]]
    m = np.zeros((3, 6, 6))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3  # eps_ijk = 1, eps_ikj = -1
        m[i, j, 3 + k] = 1.0
        m[i, k, 3 + j] = -1.0
        m[i, 3 + k, j] = 1.0
        m[i, 3 + j, k] = -1.0
        for a in range(3):
            m[i, i, a] -= 0.5 * v[a]
            m[i, a, i] -= 0.5 * v[a]
            m[i, a, a] += v[i]
    mp = np.empty((3, 6, 6))
    for i in range(3):
        mp[i] = m[i] @ p6
    mean = np.empty(3)
    for i in range(3):
        mean[i] = 0.5 * np.trace(mp[i])
    cov = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            s = 0.0
            for a in range(6):
                for b in range(6):
                    s += mp[i, a, b] * mp[j, b, a]
            cov[i, j] = 0.5 * s
    return mean, cov


@njit(cache=True)
def epoch_record(
    p: np.ndarray,
    vel: np.ndarray,
    body_allowed: bool,
    max_frame_mps: float,
    pos: np.ndarray,
    q: np.ndarray,
    w: np.ndarray,
    bias: np.ndarray,
    nav: np.ndarray,
    cov: np.ndarray,
    e: int,
    p_out: np.ndarray,
    aoa_args: tuple,
) -> float:
    """An epoch's record (``Pipeline._record``, :class:`filters.epochs.EpochStore`): its
    covariance (n, n) written into ``p_out``, and into row ``e`` of ``nav`` (E, 13 + nb)
    ``pos`` (3,), the NED velocity (3,), ``q`` (4,), ``w`` (3,), ``bias`` (nb,) and of
    ``cov`` (E, 12, 12) the covariance's navigation block. With the body-frame velocity
    error (``body_allowed`` and :func:`body_frame_curvature_ok`) the NED velocity's
    second-order part's mean and covariance are added to ``vel`` and P
    (:func:`ned_velocity_curvature`: the NED velocity a user reads). Returns
    :func:`aoa_linear_var` of P (not ``p_out``) at ``aoa_args``, its arguments after
    ``p`` (0 for ``n_aoa`` 0): the epoch's angle-of-attack variance, in the same call."""
    aoa_var = aoa_linear_var(p, *aoa_args)
    p_out[:] = p
    v = vel.copy()
    if body_allowed and body_frame_curvature_ok(p, vel, max_frame_mps):
        mc, cc = ned_velocity_curvature(vel, p)
        for i in range(3):
            v[i] = vel[i] + mc[i]
            for j in range(3):
                p_out[_VEL + i, _VEL + j] += cc[i, j]
    row = nav[e]
    row[0:3] = pos
    row[3:6] = v
    row[6:10] = q
    row[10:13] = w
    row[13:] = bias
    cov[e] = p_out[:N_NAV, :N_NAV]
    return aoa_var


# -------- the process model: F, Q and the force curvature


@njit(cache=True)
def shrunk_force(f_n: np.ndarray, p_att: np.ndarray) -> np.ndarray:
    """``f_n`` shrunk per component by ``diag([f]x P_att [f]x^T)`` (``force_for_jacobian``)."""
    sf = np.zeros((3, 3))
    sf[0, 1], sf[0, 2] = -f_n[2], f_n[1]
    sf[1, 0], sf[1, 2] = f_n[2], -f_n[0]
    sf[2, 0], sf[2, 1] = -f_n[1], f_n[0]
    var = np.zeros(3)
    for i in range(3):
        for a in range(3):
            for b in range(3):
                var[i] += sf[i, a] * p_att[a, b] * sf[i, b]
    return shrink(f_n, var)


@njit(cache=True)
def force_curvature_variance(f_n: np.ndarray, p_att: np.ndarray) -> np.ndarray:
    """Variance (3,) of each NED axis of ``[dtheta]x^2 f / 2`` for ``dtheta ~ N(0, P_att)``.

    See :func:`filters.algebra.force_curvature_variance` (the formula and its reason).
    """
    u = np.zeros(3)
    for i in range(3):
        for j in range(3):
            u[i] += p_att[i, j] * f_n[j]
    pu = np.zeros(3)
    for i in range(3):
        for j in range(3):
            pu[i] += p_att[i, j] * u[j]
    fu = f_n[0] * u[0] + f_n[1] * u[1] + f_n[2] * u[2]
    frob = 0.0
    for i in range(3):
        for j in range(3):
            frob += p_att[i, j] * p_att[i, j]
    out = np.empty(3)
    for i in range(3):
        out[i] = 0.25 * (u[i] * u[i] + fu * p_att[i, i]) + f_n[i] * (0.5 * frob * f_n[i] - pu[i])
    return out


@njit(cache=True)
def add_curvature_noise(
    p: np.ndarray,
    acc: np.ndarray,
    pos: np.ndarray,
    f_n: np.ndarray,
    t_s: float,
    att0: int,
    vel0: int,
    pos0: int,
) -> None:
    """Grow the force curvature's random constant over ``t_s`` s, in place
    (``NavFilter._add_curvature_noise``): ``acc`` (3,) and ``pos`` (3,) each NED axis's
    1-sigma velocity and position errors from it, m/s and m. The velocity part grows by
    ``sd(b) t_s``, the position part (moved by the transition's ``v t_s`` already) by half
    that times ``t_s``; P's variances and their covariance grow by the change of these
    fully correlated parts."""
    var_b = force_curvature_variance(f_n, np.ascontiguousarray(p[att0 : att0 + 3, att0 : att0 + 3]))
    for i in range(3):
        d = math.sqrt(max(var_b[i], 0.0)) * t_s
        a = acc[i]
        s = pos[i] + a * t_s
        a_new = a + d
        s_new = s + 0.5 * d * t_s
        v, q = vel0 + i, pos0 + i
        p[v, v] += a_new * a_new - a * a
        p[q, q] += s_new * s_new - s * s
        c = s_new * a_new - s * a
        p[q, v] += c
        p[v, q] += c
        acc[i] = a_new
        pos[i] = s_new


@njit(cache=True)
def error_dynamics(
    fc_base: np.ndarray,
    f_n: np.ndarray,
    c: np.ndarray,
    bias_effect_f: np.ndarray,
    bias0: int,
    quad_into: np.ndarray,
    quad6_d: np.ndarray,
    w: np.ndarray,
    sg: np.ndarray,
    dr0: int,
    dr: np.ndarray,
    axes: np.ndarray,
    solve_t: np.ndarray,
) -> np.ndarray:
    """The error dynamics' navigation rows ``F`` (12, n) over a block
    (``NavFilter.propagation_matrices``).

    ``fc_base`` (12, n) its constant part; ``f_n`` (3,) the force the transition reads;
    ``c`` (3, 3) ``C_nb``; ``bias_effect_f`` (3, nb) what the biases (from column
    ``bias0``) leave in the force; ``quad_into`` (6, 6) what the rate products' error
    reaches ``[wdot, f]`` through (``quad6_d`` (6, 3, 3) their derivative, ``w`` (3,) the
    rate), or (0, 0); ``sg`` (k, nd) the features' sensitivity to the geometry states
    (sensor positions, then sensing axes; from column ``dr0``), or (0, 0) without, and
    with positions (``axes`` (N, 3), else (0, 0)) the rate derivative of what the nominal
    removes for them (``dr`` (nd,) the geometry estimates, positions first, ``solve_t``
    (k, N): :func:`geometry_rate_jacobian`).
    """
    fc = fc_base.copy()
    v, a, r = _VEL, _ATT, _RATE
    fc[v, a + 1] = f_n[2]
    fc[v, a + 2] = -f_n[1]
    fc[v + 1, a] = -f_n[2]
    fc[v + 1, a + 2] = f_n[0]
    fc[v + 2, a] = f_n[1]
    fc[v + 2, a + 1] = -f_n[0]
    nb = bias_effect_f.shape[1]
    fc[v : v + 3, bias0 : bias0 + nb] = -(c @ np.ascontiguousarray(bias_effect_f))
    fc[a : a + 3, r : r + 3] = c
    if quad_into.shape[0]:
        aj = quad_into @ _dot_last(quad6_d, w)
        fc[r : r + 3, r : r + 3] = -aj[0:3]
        fc[v : v + 3, r : r + 3] = -(c @ np.ascontiguousarray(aj[3:6]))
    if sg.shape[0]:
        nd = sg.shape[1]
        fc[r : r + 3, dr0 : dr0 + nd] = -sg[0:3]
        fc[v : v + 3, dr0 : dr0 + nd] = -(c @ np.ascontiguousarray(sg[3:6]))
        if axes.shape[0]:
            gw = geometry_rate_jacobian(w, dr, axes, solve_t)
            fc[r : r + 3, r : r + 3] -= gw[0:3]
            fc[v : v + 3, r : r + 3] -= c @ np.ascontiguousarray(gw[3:6])
    return fc


@njit(cache=True)
def transition(fc: np.ndarray, t: float, phi: np.ndarray) -> np.ndarray:
    """``I + F t + (F t)^2 / 2 + (F t)^3 / 6`` (n, n) from ``F``'s navigation rows (12, n),
    written into ``phi`` (n, n) and returned.

    ``F t = [[A, B], [0, 0]]``, so ``(F t)^m = A^(m-1) [A, B]`` and the series needs only
    the navigation rows, in Horner form ``(I + A (I + A / 3) / 2) [A, B]``.
    """
    ft = fc * t
    n = ft.shape[1]
    a = np.ascontiguousarray(ft[:, :N_NAV])
    b = a * (1.0 / 3.0)
    for i in range(N_NAV):
        b[i, i] += 1.0
    b = a @ b
    b *= 0.5
    for i in range(N_NAV):
        b[i, i] += 1.0
    phi[:] = 0.0
    for i in range(n):
        phi[i, i] = 1.0
    phi[:N_NAV] += b @ ft
    return phi


@njit(cache=True)
def rotated_nav_noise(
    c: np.ndarray, q12_body: np.ndarray, q_walks: np.ndarray, q: np.ndarray
) -> np.ndarray:
    """Process noise (n, n), written into ``q`` (n, n) and returned: ``q_walks`` with the
    navigation block ``T q12_body T^T``, ``T`` block-diagonal ``(C, C, C, I)`` (body-frame
    noise blocks rotated to NED)."""
    t12 = np.eye(N_NAV)
    for b in range(3):
        t12[3 * b : 3 * b + 3, 3 * b : 3 * b + 3] = c
    q[:] = q_walks
    q[:N_NAV, :N_NAV] = t12 @ q12_body @ t12.T
    return q


@njit(cache=True)
def propagation_matrices(
    fc_base: np.ndarray,
    f_n: np.ndarray,
    c: np.ndarray,
    bias_effect_f: np.ndarray,
    bias0: int,
    quad_into: np.ndarray,
    quad6_d: np.ndarray,
    w: np.ndarray,
    sg: np.ndarray,
    dr0: int,
    dr: np.ndarray,
    axes: np.ndarray,
    solve_t: np.ndarray,
    t: float,
    q12_body: np.ndarray,
    q_walks: np.ndarray,
    phi: np.ndarray,
    q: np.ndarray,
):
    """A block's transition and process noise ``(F, Q)`` (n, n) each, written into ``phi``
    and ``q`` and returned (``NavFilter.propagation_matrices``): :func:`error_dynamics`
    through :func:`transition` over ``t`` s, and :func:`rotated_nav_noise`."""
    fc = error_dynamics(
        fc_base, f_n, c, bias_effect_f, bias0, quad_into, quad6_d, w, sg, dr0, dr, axes, solve_t
    )
    return transition(fc, t, phi), rotated_nav_noise(c, q12_body, q_walks, q)


@njit(cache=True)
def feature_offset(bias: np.ndarray, sg: np.ndarray, geo: np.ndarray):
    """What the nominal removes from ``wdot`` and ``f`` (3,) each: the biases ``bias``
    (k,) plus, with geometry states (``sg`` (k, nd), else (0, 0)), ``sg``'s share of their
    estimates ``geo`` (nd,) (``T S G dr_hat`` and ``T S diag(a^T) dg_hat``)."""
    bw = bias[0:3].copy()
    bf = bias[3:6].copy()
    if sg.shape[0]:
        off = np.ascontiguousarray(sg[0:6]) @ geo
        bw += off[0:3]
        bf += off[3:6]
    return bw, bf


@njit(cache=True)
def propagate_block(
    q: np.ndarray,
    pos: np.ndarray,
    vel: np.ndarray,
    w0: np.ndarray,
    p: np.ndarray,
    g: np.ndarray,
    body_allowed: bool,
    max_frame_mps: float,
    last_wdot: np.ndarray,
    wdot: np.ndarray,
    last_f: np.ndarray,
    f: np.ndarray,
    bias: np.ndarray,
    mw: np.ndarray,
    mw0: np.ndarray,
    wts: np.ndarray,
    wts1: np.ndarray,
    dt: float,
    fc_base: np.ndarray,
    bias_effect_f: np.ndarray,
    bias0: int,
    quad_into: np.ndarray,
    quad6_d: np.ndarray,
    sg: np.ndarray,
    dr0: int,
    geo: np.ndarray,
    axes: np.ndarray,
    solve_t: np.ndarray,
    q12_body: np.ndarray,
    q_walks: np.ndarray,
    phi: np.ndarray,
    qn: np.ndarray,
    c0_out: np.ndarray,
    f_n_out: np.ndarray,
):
    """One block's nominal propagation and its transition and noise, before filterpy's
    predict (``NavFilter.propagate``).

    :func:`propagate_nominal` of the samples less :func:`feature_offset`, with the
    body-frame velocity error when ``body_allowed`` and :func:`body_frame_curvature_ok`;
    then :func:`propagation_matrices` at the block-start ``C``, the block's mean force
    shrunk by the attitude's uncertainty (:func:`shrunk_force`) and the block-end rate.
    Returns the rates at the K samples (K, 3) and the new ``q``, ``pos``, ``vel`` and
    rate (3,); writes F and Q (n, n) into ``phi`` and ``qn``, ``C_nb`` at the block start
    (3, 3) into ``c0_out``, the block's mean NED force (3,) into ``f_n_out``, and the
    block's last samples ``wdot[-1]``, ``f[-1]`` (3,) into ``last_wdot``, ``last_f`` (the
    next block's first interval starts there). Outputs into the caller's arrays, not new
    ones: each array a kernel returns costs its boxing (about 0.4 us).
    """
    bw, bf = feature_offset(bias, sg, geo)
    body = body_allowed and body_frame_curvature_ok(p, vel, max_frame_mps)
    w, q_new, pos_new, vel_new, c0, f_n = propagate_nominal(
        q, pos, vel, w0, p, g, body, last_wdot, wdot, bw, last_f, f, bf, mw, mw0, wts, wts1, dt
    )
    k = wdot.shape[0]
    w_end = w[k - 1].copy()
    f_j = shrunk_force(f_n, p[_ATT : _ATT + 3, _ATT : _ATT + 3])
    propagation_matrices(
        fc_base, f_j, c0, bias_effect_f, bias0, quad_into, quad6_d, w_end, sg, dr0, geo, axes,
        solve_t, k * dt, q12_body, q_walks, phi, qn,
    )  # fmt: skip
    c0_out[:] = c0
    f_n_out[:] = f_n
    last_wdot[:] = wdot[k - 1]  # read by propagate_nominal above, no longer needed
    last_f[:] = f[k - 1]
    return w, q_new, pos_new, vel_new, w_end


@njit(cache=True)
def curvature_noise_step(
    p: np.ndarray,
    body_allowed: bool,
    vel: np.ndarray,
    max_frame_mps: float,
    acc: np.ndarray,
    pos: np.ndarray,
    f_n: np.ndarray,
    t_s: float,
) -> None:
    """The force curvature's noise over ``t_s`` s, in place (``NavFilter._add_curvature_noise``,
    which says why): with the NED velocity error (not ``body_allowed`` or not
    :func:`body_frame_curvature_ok` at ``vel``) :func:`add_curvature_noise` (``acc``, ``pos``
    its 1-sigma parts, ``f_n`` the block's mean force); with the body-frame error its parts
    started again from zero."""
    if body_allowed and body_frame_curvature_ok(p, vel, max_frame_mps):
        acc[:] = 0.0
        pos[:] = 0.0
    else:
        add_curvature_noise(p, acc, pos, f_n, t_s, _ATT, _VEL, _POS)


@njit(cache=True)
def predicted_covariance(
    p: np.ndarray,
    body_allowed: bool,
    vel: np.ndarray,
    max_frame_mps: float,
    acc: np.ndarray,
    pos: np.ndarray,
    f_n: np.ndarray,
    t_s: float,
) -> None:
    """P (n, n) after filterpy's predict over a block of ``t_s`` s, in place (filterpy's new
    array, which nothing else holds): :func:`curvature_noise_step` (its arguments), then
    symmetrised."""
    curvature_noise_step(p, body_allowed, vel, max_frame_mps, acc, pos, f_n, t_s)
    symmetrise(p)


@njit(cache=True)
def geometry_jacobian(
    wdot: np.ndarray, w: np.ndarray, axes: np.ndarray, solve_rep: np.ndarray
) -> np.ndarray:
    """The features' sensitivity (k, 3N) to the sensor positions, ``T S G``
    (``NavFilter.geometry_jacobian``): row ``i`` of ``G`` is ``theta_i^T ([wdot]x + [w]x^2)``."""
    ax, ay, az = wdot[0], wdot[1], wdot[2]
    x, y, z = w[0], w[1], w[2]
    n2 = x * x + y * y + z * z
    m = np.empty((3, 3))
    m[0, 0], m[0, 1], m[0, 2] = x * x - n2, x * y - az, x * z + ay
    m[1, 0], m[1, 1], m[1, 2] = y * x + az, y * y - n2, y * z - ax
    m[2, 0], m[2, 1], m[2, 2] = z * x - ay, z * y + ax, z * z - n2
    tm = (np.ascontiguousarray(axes) @ m).ravel()
    out = np.empty_like(solve_rep)
    for r in range(solve_rep.shape[0]):
        for c in range(solve_rep.shape[1]):
            out[r, c] = solve_rep[r, c] * tm[c]
    return out


@njit(cache=True)
def load_jacobian(
    f: np.ndarray, wdot: np.ndarray, w: np.ndarray, positions: np.ndarray, solve_rep: np.ndarray
) -> np.ndarray:
    """The features' sensitivity (k, 3N) to the sensing-axis errors, ``T S diag(a_i^T)``
    (``NavFilter.calibration_jacobian``): ``a_i = f + wdot x r_i + w x (w x r_i)`` is the
    specific force at sensor ``i`` (``positions`` (N, 3))."""
    n = positions.shape[0]
    load = np.empty(3 * n)
    for i in range(n):
        rx, ry, rz = positions[i, 0], positions[i, 1], positions[i, 2]
        # w x r, then w x (w x r) and wdot x r
        ux = w[1] * rz - w[2] * ry
        uy = w[2] * rx - w[0] * rz
        uz = w[0] * ry - w[1] * rx
        load[3 * i] = f[0] + wdot[1] * rz - wdot[2] * ry + w[1] * uz - w[2] * uy
        load[3 * i + 1] = f[1] + wdot[2] * rx - wdot[0] * rz + w[2] * ux - w[0] * uz
        load[3 * i + 2] = f[2] + wdot[0] * ry - wdot[1] * rx + w[0] * uy - w[1] * ux
    out = np.empty_like(solve_rep)
    for r in range(solve_rep.shape[0]):
        for c in range(solve_rep.shape[1]):
            out[r, c] = solve_rep[r, c] * load[c]
    return out


@njit(cache=True)
def position_sensitivity(
    wdot: np.ndarray,
    wdot_var: np.ndarray,
    inv_k: float,
    clear2: float,
    w: np.ndarray,
    t_half: float,
    axes: np.ndarray,
    solve_rep: np.ndarray,
) -> np.ndarray:
    """The features' sensitivity (k, 3N) to the sensor positions over a block
    (``StepMixin._block``, which says why): :func:`geometry_jacobian` at the angular
    acceleration ``wdot`` (3,) shrunk by its noise ``wdot_var * inv_k`` (3,)
    (:func:`shrink`, ``clear2``) and at the rate ``w + t_half wdot`` (the block's middle)."""
    var = wdot_var * inv_k
    wd = shrink(wdot, var, clear2)
    return geometry_jacobian(wd, w + t_half * wd, axes, solve_rep)


@njit(cache=True)
def history_row(
    h: np.ndarray,
    w: np.ndarray,
    mean: np.ndarray,
    bias: np.ndarray,
    wd_smooth: np.ndarray,
    gain: float,
) -> np.ndarray:
    """A block's row of the forecast's history, in place (``StepMixin._block``): ``h``
    (9,) takes the rate ``w`` (3,) and the block's ``[wdot, f]`` less the biases (the first
    six of ``mean`` and ``bias``), which is returned (6,); the smoothed angular
    acceleration ``wd_smooth`` (3,) moves towards it by ``gain``."""
    mean6 = np.empty(6)
    for i in range(6):
        mean6[i] = mean[i] - bias[i]
    for i in range(3):
        h[i] = w[i]
    for i in range(6):
        h[3 + i] = mean6[i]
    for i in range(3):
        wd_smooth[i] += gain * (mean6[i] - wd_smooth[i])
    return mean6


@njit(cache=True)
def geometry_rate_jacobian(
    w: np.ndarray, dr: np.ndarray, axes: np.ndarray, solve_t: np.ndarray
) -> np.ndarray:
    """``T S`` times the rows ``(w . dr_i) theta_i + (theta_i . w) dr_i - 2 (theta_i . dr_i) w``
    (k, 3): the rate derivative of what the nominal removes for the sensor positions
    (``NavFilter.geometry_rate_jacobian``); ``dr`` (3N,), ``axes`` (N, 3)."""
    n = axes.shape[0]
    rows = np.empty((n, 3))
    for i in range(n):
        dx, dy, dz = dr[3 * i], dr[3 * i + 1], dr[3 * i + 2]
        tx, ty, tz = axes[i, 0], axes[i, 1], axes[i, 2]
        wd = dx * w[0] + dy * w[1] + dz * w[2]
        tw = tx * w[0] + ty * w[1] + tz * w[2]
        td = tx * dx + ty * dy + tz * dz
        rows[i, 0] = wd * tx + tw * dx - 2.0 * td * w[0]
        rows[i, 1] = wd * ty + tw * dy - 2.0 * td * w[1]
        rows[i, 2] = wd * tz + tw * dz - 2.0 * td * w[2]
    return np.ascontiguousarray(solve_t) @ rows


# -------- the measurement models


@njit(cache=True)
def compensate(xs: np.ndarray, x_hat: np.ndarray, se: np.ndarray, phi_hat: np.ndarray) -> None:
    """The forecast's compensation of a block's features, in place (``StepMixin._block``).

    ``x_hat`` (9,) the forecast ``[w, wdot, f]``; writes ``phi_hat`` (12,) ``[wdot, f]``
    and the rate products ``(wx^2, wy^2, wz^2, wy wz, wx wz, wx wy)``, and takes
    ``se @ phi_hat`` (``se`` (k, 12) the compensation matrix) from every row of ``xs``
    (K, k).
    """
    wx, wy, wz = x_hat[0], x_hat[1], x_hat[2]
    for i in range(6):
        phi_hat[i] = x_hat[3 + i]
    phi_hat[6], phi_hat[7], phi_hat[8] = wx * wx, wy * wy, wz * wz
    phi_hat[9], phi_hat[10], phi_hat[11] = wy * wz, wx * wz, wx * wy
    t = se @ phi_hat
    for s in range(xs.shape[0]):
        for j in range(xs.shape[1]):
            xs[s, j] -= t[j]


@njit(cache=True)
def block_means(
    xs: np.ndarray,
    bad: np.ndarray,
    n_ok: int,
    nq: int,
    bias6: np.ndarray,
    phi_hat6: np.ndarray,
    se6: np.ndarray,
    correct: bool,
    quad: np.ndarray,
    r: np.ndarray,
):
    """A block's mean features and what its forecast missed (``StepMixin._block``).

    ``xs`` (K, m) the compensated features, ``bad`` (K,) the held rows (left out of the
    means while some are not); ``n_ok`` rows not held. Returns the mean (m,); the
    forecast's error ``d = mean[:6] - bias6 - phi_hat6`` (6,) (empty without a forecast,
    ``phi_hat6`` (0,)); and whether, with ``correct`` and a finite ``d``, ``se6 d`` (m,),
    the error's share of every feature, was taken out of both means. Writes into the
    caller's buffers (arrays a kernel returns cost their boxing): the mean of the rate
    products (nq,) over the rows not held into ``quad`` when ``n_ok`` and ``nq``, and
    ``se6 d`` into ``r`` (m,) when taken out.
    """
    k, m = xs.shape
    some = 0 < n_ok < k
    mean = np.zeros(m)
    n = 0
    for s in range(k):
        if some and bad[s]:
            continue
        n += 1
        for j in range(m):
            mean[j] += xs[s, j]
    mean *= 1.0 / n
    with_quad = n_ok > 0 and nq > 0
    if with_quad:
        quad[:] = 0.0
        for s in range(k):
            if n_ok < k and bad[s]:
                continue
            for j in range(nq):
                quad[j] += xs[s, m - nq + j]
        quad *= 1.0 / n_ok
    d = np.zeros(0)
    corrected = False
    if phi_hat6.shape[0]:
        d = mean[:6] - bias6 - phi_hat6
        if correct and np.isfinite(d.sum()):
            r[:] = np.ascontiguousarray(se6) @ d
            mean -= r
            if with_quad:
                for j in range(nq):
                    quad[j] = quad[j] - r[m - nq + j]
            corrected = True
    return mean, d, corrected


@njit(cache=True)
def extrapolated_load(
    f_mean: np.ndarray,
    sg_f: np.ndarray,
    geo: np.ndarray,
    first: bool,
    w_now: float,
    w_prev: float,
    f_prev: np.ndarray,
    sg_prev: np.ndarray,
):
    """The load the lift law reads at a block's end (``StepMixin._block``, which says why).

    ``f_mean`` (3,) the block's mean force less the biases, ``sg_f`` (3, nd) its
    sensitivity to the geometry states (estimates ``geo`` (nd,)), or (0, 0) without
    them. Unless ``first``, the line through the last block's ``f_prev`` (3,) and
    ``sg_prev`` ((0, 0): none) and this one's, at the weights ``w_now``, ``w_prev``
    (``vehicle_model.load_extrapolation_weights``). Returns the block's load less
    ``sg_f geo`` (3,), the extrapolated load (3,) and its sensitivity (``sg_f`` when not
    extrapolated).
    """
    if sg_f.shape[0]:
        f = f_mean - sg_f @ geo
    else:
        f = f_mean.copy()
    if first:
        return f, f, sg_f
    f_load = w_now * f + w_prev * f_prev
    if sg_f.shape[0] and sg_prev.shape[0]:
        return f, f_load, w_now * sg_f + w_prev * sg_prev
    return f, f_load, sg_f


@njit(cache=True)
def history_and_load(
    h: np.ndarray,
    w: np.ndarray,
    mean: np.ndarray,
    bias: np.ndarray,
    wd_smooth: np.ndarray,
    gain: float,
    sg_f: np.ndarray,
    geo: np.ndarray,
    first: bool,
    w_now: float,
    w_prev: float,
    f_prev: np.ndarray,
    sg_prev: np.ndarray,
):
    """:func:`history_row` (its arguments first) and then :func:`extrapolated_load` of the
    row's force (``StepMixin._block`` with the angle-of-attack state): one call where
    there were two. Returns :func:`extrapolated_load`'s three."""
    mean6 = history_row(h, w, mean, bias, wd_smooth, gain)
    return extrapolated_load(mean6[3:6], sg_f, geo, first, w_now, w_prev, f_prev, sg_prev)


@njit(cache=True)
def lift_load(
    f_b: np.ndarray,
    load_cov: np.ndarray,
    sin_a: float,
    cos_a: float,
    speed: float,
    axis: np.ndarray,
):
    """The lift law's load (``NavFilter.set_load``, which says why): the lift axis
    ``[sin a, 0, -cos a]`` written into ``axis`` (3,), and returned ``u = n_w / V^2`` of
    the force ``f_b`` (3,) and its variance from the force's noise ``load_cov`` (3, 3;
    (0, 0): none, 0)."""
    axis[0], axis[1], axis[2] = sin_a, 0.0, -cos_a
    n_w = axis @ f_b
    # products, not powers: a diverged speed gives 0 here, not an overflow
    speed2 = speed * speed
    u_var = 0.0
    if load_cov.shape[0]:
        u_var = (axis @ load_cov @ axis) / speed2 / speed2
    return n_w / speed2, u_var


@njit(cache=True)
def block_products(w_block: np.ndarray, pairs: np.ndarray):
    """The block mean of ``w_i w_j`` over its samples (nq,) and its mean rate (3,)."""
    k = w_block.shape[0]
    inv_k = 1.0 / k
    nq = pairs.shape[0]
    pred = np.zeros(nq)
    w_mean = np.zeros(3)
    for s in range(k):
        for a in range(3):
            w_mean[a] += w_block[s, a]
        for r in range(nq):
            pred[r] += w_block[s, pairs[r, 0]] * w_block[s, pairs[r, 1]]
    return pred * inv_k, w_mean * inv_k


@njit(cache=True)
def product_moments(p_rate: np.ndarray, pairs: np.ndarray):
    """``E[d_i d_j] = P_ij`` (nq,) of the rate error's products and their variances
    ``P_ii P_jj + P_ij^2`` (nq,) for a Gaussian rate error of covariance ``p_rate`` (3, 3)."""
    nq = pairs.shape[0]
    pij = np.empty(nq)
    spread = np.empty(nq)
    for r in range(nq):
        i, j = pairs[r, 0], pairs[r, 1]
        pij[r] = p_rate[i, j]
        spread[r] = p_rate[i, i] * p_rate[j, j] + pij[r] * pij[r]
    return pij, spread


@njit(cache=True)
def rate_model(
    w_block: np.ndarray,
    pairs: np.ndarray,
    rate_var: np.ndarray,
    h_base: np.ndarray,
    quad_d: np.ndarray,
    aided: np.ndarray,
    quad6_d: np.ndarray,
    sg: np.ndarray,
    dr: np.ndarray,
    axes: np.ndarray,
    solve_t: np.ndarray,
    dr0: int,
):
    """The block mean (nq,) of the rate products over the rates ``w_block`` (K, 3) and
    their Jacobian (nq, n) (``NavFilter.rate_model``, which says why).

    ``rate_var`` (3,) shrinks the mean rate the Jacobian is taken at (size 0: not
    shrunk); ``h_base`` (nq, n) the Jacobian's constant part; ``quad_d`` (nq, 3, 3) the
    products' derivatives (with the forecast's feedback); ``aided`` (nq, 6) what aided
    products leave in the solved ones (nq, 0 without) with ``quad6_d`` (6, 3, 3) their
    derivatives; with geometry states (``sg`` (k, nd), else (0, 0)) their columns from
    ``dr0`` and, with sensor positions (``axes`` (N, 3), else (0, 0)), the rate derivative
    of what the nominal removes for them at the estimates ``dr`` (nd,), positions first,
    and solve ``solve_t`` (k, N).
    """
    pred, w_mean = block_products(w_block, pairs)
    if rate_var.shape[0]:
        w_mean = shrink(w_mean, rate_var)
    h = h_base.copy()
    r = _RATE
    hr = _dot_last(quad_d, w_mean)
    if aided.shape[1]:
        hr += aided @ _dot_last(quad6_d, w_mean)
    if sg.shape[0]:
        nd = sg.shape[1]
        h[:, dr0 : dr0 + nd] = sg[6:]
        if axes.shape[0]:
            hr += geometry_rate_jacobian(w_mean, dr, axes, solve_t)[6:]
    h[:, r : r + 3] = hr
    return pred, h


@njit(cache=True)
def rate_measurement(
    w_block: np.ndarray,
    pairs: np.ndarray,
    h_base: np.ndarray,
    quad_d: np.ndarray,
    aided: np.ndarray,
    quad6_d: np.ndarray,
    sg: np.ndarray,
    dr: np.ndarray,
    axes: np.ndarray,
    solve_t: np.ndarray,
    dr0: int,
    p: np.ndarray,
    bias_q: np.ndarray,
    sqq: np.ndarray,
    k: int,
):
    """The rate products' prediction (nq,), Jacobian (nq, n) and noise (nq, nq) for a
    block of ``k`` samples (``NavFilter.measure_rate``, which says why): :func:`rate_model`
    at the rate shrunk by its variance in ``p`` (n, n), plus the rate error's product
    moments (:func:`product_moments`), the biases ``bias_q`` and ``S G dr_hat``; the noise
    ``sqq / k`` plus the products' spread."""
    prr = np.ascontiguousarray(p[_RATE : _RATE + 3, _RATE : _RATE + 3])
    rate_var = np.empty(3)
    for i in range(3):
        rate_var[i] = prr[i, i]
    pred, h = rate_model(
        w_block, pairs, rate_var, h_base, quad_d, aided, quad6_d, sg, dr, axes, solve_t, dr0
    )
    pij, spread = product_moments(prr, pairs)
    pred = pred + pij + bias_q
    r = sqq * (1.0 / k)
    for i in range(r.shape[0]):
        r[i, i] += spread[i]
    if sg.shape[0]:
        pred = pred + np.ascontiguousarray(sg[6:]) @ dr
    return pred, h, r


@njit(cache=True)
def gps_model(q: np.ndarray, w: np.ndarray, r: np.ndarray, n: int):
    """The antenna's offset ``C r`` and velocity ``C (w x r)`` (NED, 3,) and their
    Jacobians ``H_pos``, ``H_vel`` (3, n) (``NavFilter.gps_model``) at the attitude ``q``
    (4,) and rate ``w`` (3,), antenna ``r`` (3,) (FRD)."""
    c = dcm(q)
    cr = c @ r
    u = np.empty(3)
    u[0] = w[1] * r[2] - w[2] * r[1]
    u[1] = w[2] * r[0] - w[0] * r[2]
    u[2] = w[0] * r[1] - w[1] * r[0]
    cwr = c @ u
    hp = np.zeros((3, n))
    hv = np.zeros((3, n))
    hpa = -_skew(cr)
    hva = -_skew(cwr)
    hvr = -c @ _skew(r)
    for i in range(3):
        hp[i, _POS + i] = 1.0
        hv[i, _VEL + i] = 1.0
        for j in range(3):
            hp[i, _ATT + j] = hpa[i, j]
            hv[i, _ATT + j] = hva[i, j]
            hv[i, _RATE + j] = hvr[i, j]
    return cr, cwr, hp, hv


@njit(cache=True)
def rate_noise_cross(
    cq: np.ndarray, c: np.ndarray, dt: float, k: int, held: np.ndarray, n: int
) -> np.ndarray:
    """``E[dx v^T]`` (n, nq) of a block's propagation noise with its rate measurement's
    (``NavFilter.rate_noise_cross``, which says why): ``cq`` (6, nq) the features'
    cross-covariance with the products, ``c`` (3, 3) ``C_nb``, ``k`` the block's samples
    (interval ``dt``), ``held`` (k,) its held ones ((0,): none). (n, 0) with every sample
    held."""
    nq = cq.shape[1]
    if held.shape[0]:
        total = 0.0
        count = 0
        for j in range(held.shape[0]):
            if not held[j]:
                total += k - (j + 1)
                count += 1
        if count == 0:
            return np.zeros((n, 0))
        lag = total / count  # the mean samples from a measured one to the block end
    else:
        lag = 0.5 * (k - 1)
    cw = c @ np.ascontiguousarray(cq[0:3])
    cf = c @ np.ascontiguousarray(cq[3:6])
    a = dt * dt * lag
    m = np.zeros((n, nq))
    for i in range(3):
        for j in range(nq):
            m[_POS + i, j] = -a * cf[i, j]
            m[_VEL + i, j] = -dt * cf[i, j]
            m[_ATT + i, j] = -a * cw[i, j]
            m[_RATE + i, j] = -dt * cq[i, j]
    return m


@njit(cache=True)
def rate_update(
    quad_mean: np.ndarray,
    w_block: np.ndarray,
    pairs: np.ndarray,
    h_base: np.ndarray,
    quad_d: np.ndarray,
    aided: np.ndarray,
    quad6_d: np.ndarray,
    sg: np.ndarray,
    dr: np.ndarray,
    axes: np.ndarray,
    solve_t: np.ndarray,
    dr0: int,
    p: np.ndarray,
    bias_q: np.ndarray,
    sqq: np.ndarray,
    k: int,
    cq: np.ndarray,
    c: np.ndarray,
    dt: float,
    k_block: int,
    held: np.ndarray,
    rows: np.ndarray,
):
    """A block's rate products as a measurement, with its innovation covariance and NIS
    (``NavFilter.measure_rate``, which says why).

    ``quad_mean`` (nq,) the block's mean solved products over ``k`` samples; the
    prediction, Jacobian and noise are :func:`rate_measurement`'s (its arguments from
    ``w_block`` to ``sqq``); the noise's covariance with the block's propagation is
    :func:`rate_noise_cross`'s (``cq``, ``c``, ``dt``, ``k_block``, ``held``; ``cq``
    (0, 0): none). Only the products ``rows`` (nq,) are kept. Returns the innovation
    ``z`` (m,), ``H`` (m, n), ``R`` (m, m), the cross-covariance ``M`` (n, m) ((n, 0)
    without), ``S`` (m, m) (:func:`innovation_cov`) and the NIS (:func:`quadratic_form`).
    """
    n = p.shape[0]
    pred, h, r = rate_measurement(
        w_block, pairs, h_base, quad_d, aided, quad6_d, sg, dr, axes, solve_t, dr0, p, bias_q,
        sqq, k,
    )  # fmt: skip
    z = quad_mean - pred
    m = np.zeros((n, 0))
    if cq.shape[0]:
        m = rate_noise_cross(cq, c, dt, k_block, held, n)
    if not rows.all():
        # products an excluded channel leaves unsolved are the rate's own (aided)
        z = z[rows]
        h = h[rows]
        r = r[rows][:, rows]
        if m.shape[1]:
            m = m[:, rows]
    s = innovation_cov(h, p, r, m)
    return z, h, r, m, s, quadratic_form(z, s)


@njit(cache=True)
def innovation_cov(h: np.ndarray, p: np.ndarray, r: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """``H P H^T + R`` plus ``H M + M^T H^T`` (``cross`` ``M`` (n, m), or (n, 0) without)."""
    h = np.ascontiguousarray(h)
    s = h @ np.ascontiguousarray(p) @ h.T + r
    if cross.shape[1]:
        hm = h @ np.ascontiguousarray(cross)
        s += hm + hm.T
    return s


@njit(cache=True)
def inverse(a: np.ndarray) -> np.ndarray:
    """``a^-1`` (m, m), LAPACK's as numpy's: filterpy's ``KalmanFilter.inv`` for the small
    innovation covariances (numpy's call costs more than the inversion)."""
    return np.linalg.inv(np.ascontiguousarray(a))


@njit(cache=True)
def quadratic_form(y: np.ndarray, s: np.ndarray) -> float:
    """``y^T S^-1 y`` (``y`` (m,), ``S`` (m, m) symmetric positive definite): for m = 3 in
    closed form from S's upper triangle (inf unless its determinant is positive), else by
    one LAPACK solve."""
    if y.shape[0] != 3:
        return y @ np.linalg.solve(np.ascontiguousarray(s), np.ascontiguousarray(y))
    a, b, c = s[0, 0], s[0, 1], s[0, 2]
    d, e, f = s[1, 1], s[1, 2], s[2, 2]
    # adjugate of the symmetric 3 x 3 matrix
    ia, ib, ic = d * f - e * e, c * e - b * f, b * e - c * d
    id_, ie, if_ = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * ia + b * ib + c * ic
    x, yy, z = y[0], y[1], y[2]
    num = ia * x * x + id_ * yy * yy + if_ * z * z + 2.0 * (ib * x * yy + ic * x * z + ie * yy * z)
    return num / det if det > 0.0 else np.inf


@njit(cache=True)
def aoa_jacobian(
    n: int,
    aoa0: int,
    n_aoa: int,
    lift_w: float,
    lift_u_jac: float,
    vel: np.ndarray,
    lift_dw: float,
    lift: float,
    aoa_k: float,
    lift_axis: np.ndarray,
    bias_effect_f: np.ndarray,
    bias0: int,
    lift_sg_f: np.ndarray,
    dr0: int,
) -> np.ndarray:
    """``d alpha / d(error state)`` (n,) (``NavFilter.aoa_jacobian``, which says why):
    the law's states from column ``aoa0``, the velocity through the speed (``vel`` (3,)
    NED), the force biases from ``bias0`` and, unless ``lift_sg_f`` is (0, 0), the sensor
    positions from ``dr0`` through the load."""
    j = np.zeros(n)
    if n_aoa == 0:
        return j
    j[aoa0] = lift_w
    if n_aoa == 2:
        j[aoa0 + 1] = lift_w * lift_u_jac
    speed2 = vel[0] * vel[0] + vel[1] * vel[1] + vel[2] * vel[2]
    if speed2 <= 1.0:
        return j
    v = _VEL
    if lift_dw != 0.0:
        speed = math.sqrt(speed2)
        for a in range(3):
            j[v + a] += lift_dw * lift * vel[a] / speed
    if aoa_k > 0.0:
        wk = lift_w * aoa_k / speed2
        for a in range(3):
            j[v + a] += -2.0 * wk * lift_u_jac * vel[a]
        jb = lift_axis @ np.ascontiguousarray(bias_effect_f)
        for i in range(jb.shape[0]):
            j[bias0 + i] += -wk * jb[i]
        if lift_sg_f.shape[0]:
            js = lift_axis @ np.ascontiguousarray(lift_sg_f)
            for i in range(js.shape[0]):
                j[dr0 + i] += -wk * js[i]
    return j


@njit(cache=True)
def aoa_linear_var(
    p: np.ndarray,
    n: int,
    aoa0: int,
    n_aoa: int,
    lift_w: float,
    lift_u_jac: float,
    vel: np.ndarray,
    lift_dw: float,
    lift: float,
    aoa_k: float,
    lift_axis: np.ndarray,
    bias_effect_f: np.ndarray,
    bias0: int,
    lift_sg_f: np.ndarray,
    dr0: int,
) -> float:
    """``j P j`` for :func:`aoa_jacobian`'s ``j`` (its arguments follow ``p`` (n, n)): the
    angle of attack's variance through its Jacobian (``NavFilter.aoa_sigma``). The
    arguments are spelled out: a ``*args`` signature made every call pack them (0.2 us of
    its 2)."""
    j = aoa_jacobian(
        n, aoa0, n_aoa, lift_w, lift_u_jac, vel, lift_dw, lift, aoa_k, lift_axis, bias_effect_f,
        bias0, lift_sg_f, dr0,
    )  # fmt: skip
    n = j.shape[0]
    var = 0.0
    for a in range(n):
        if j[a] != 0.0:
            row = 0.0
            for b in range(n):
                row += p[a, b] * j[b]
            var += j[a] * row
    return var


# -------- the covariance check and the channels' health tests


#: A float64's exponent bits: all set for an infinity or a NaN, and only then.
_EXPONENT = np.uint64(0x7FF0000000000000)


@njit(cache=True)
def covariance_flaw(p: np.ndarray) -> int:
    """The per-block check of P: 0 if finite with a positive diagonal, 1 if not finite,
    2 if a variance is not positive (``NavFilter.check_covariance``).

    Finiteness from the bits: the largest exponent field over P is all ones exactly when
    some entry is infinite or NaN (a loop without early exits the compiler vectorises:
    0.4 us a call for a 50-state P, 1.6 us testing ``np.isfinite`` entry by entry).
    """
    n = p.shape[0]
    bits = np.ascontiguousarray(p).reshape(-1).view(np.uint64)
    top = np.uint64(0)
    for i in range(bits.shape[0]):
        e = bits[i] & _EXPONENT
        if e > top:
            top = e
    if top == _EXPONENT:
        return 1
    for i in range(n):
        if p[i, i] <= 0.0:
            return 2
    return 0


@njit(cache=True)
def held_rows(chmask: np.ndarray, nfmask: np.ndarray, excluded: int):
    """Rows (K,) held for a bad channel not in ``excluded`` (bit masks per row), their
    number, and how many rows have such a channel non-finite or else saturated
    (``Pipeline._count_held``)."""
    k = chmask.shape[0]
    bad = np.zeros(k, np.bool_)
    n_bad = 0
    n_nonfinite = 0
    n_saturated = 0
    keep = ~excluded
    for i in range(k):
        if chmask[i] & keep:
            bad[i] = True
            n_bad += 1
            if nfmask[i] & keep:
                n_nonfinite += 1
            else:
                n_saturated += 1
        elif nfmask[i] & keep:
            n_nonfinite += 1
    return bad, n_bad, n_nonfinite, n_saturated


@njit(cache=True)
def flat_line_runs(
    prev: np.ndarray,
    a: np.ndarray,
    run: np.ndarray,
    flat: np.ndarray,
    n_flat: int,
    d2: np.ndarray,
    rises: np.ndarray,
) -> int:
    """The flat-line test over a block of readings (``faults.ChannelMonitor``), in place.

    ``prev`` (2, N) the two readings before the block, ``a`` (K, N) the block's; ``run``
    (N,) each channel's repeats of its last reading so far and ``flat`` (N,) whether it
    was flat (``n_flat`` identical readings in a row). Updates ``run``, ``flat`` and
    ``prev`` (to the block's last two readings), writes the second differences of the
    readings into ``d2`` (K, N) and the rises of the flat flag as (sample, channel) rows
    by channel then sample into ``rises`` (at least (K N, 2)), and returns how many rises
    there are (the caller's buffer: a new array every block cost its boxing).
    """
    k, n = a.shape
    m = 0
    for c in range(n):
        r = run[c]
        was = flat[c]
        p1 = prev[0, c]  # the reading two before, then one before, the current one
        p2 = prev[1, c]
        for i in range(k):
            x = a[i, c]
            # NaN never repeats
            r = r + 1 if x == p2 else 0
            now = r + 1 >= n_flat
            if now and not was:
                rises[m, 0] = i
                rises[m, 1] = c
                m += 1
            was = now
            d2[i, c] = x - 2.0 * p2 + p1
            p1 = p2
            p2 = x
        run[c] = r
        flat[c] = was
        prev[0, c] = p1
        prev[1, c] = p2
    return m


@njit(cache=True)
def column_median_squares(win: np.ndarray) -> np.ndarray:
    """Each column's median of the squares of ``win`` (K, N) with no NaN (the noise-level
    test's window, ``faults.ChannelMonitor``): ``np.median(win * win, axis=0)``."""
    n = win.shape[1]
    out = np.empty(n)
    for c in range(n):
        col = win[:, c]
        out[c] = np.median(col * col)
    return out


@njit(cache=True)
def parity_cusum(
    r: np.ndarray,
    cov: np.ndarray,
    g_sig: np.ndarray,
    cusum: np.ndarray,
    allowance: float,
    threshold: float,
) -> int:
    """One step of the parity CUSUMs (``faults.ChannelMonitor.observe_parity``), in place.

    ``r`` (nq,) the rate products' innovation, ``cov`` (nq, nq) its covariance ``S``,
    ``g_sig`` (G, nq) the channel groups' signatures ``s_g``; each group's normalised
    projection ``s_g' S^-1 r / sqrt(s_g' S^-1 s_g)`` feeds its two one-sided CUSUMs
    ``cusum`` (G, 2). Returns the group whose larger statistic is the largest if that
    passes ``threshold`` (the first such on a tie), else -1; a non-finite ``r`` changes
    nothing (-1).
    """
    for i in range(r.shape[0]):
        if not np.isfinite(r[i]):
            return -1
    w = np.linalg.solve(np.ascontiguousarray(cov), np.ascontiguousarray(g_sig.T))  # (nq, G)
    best = -1
    best_top = threshold
    for g in range(g_sig.shape[0]):
        ss = 0.0
        rw = 0.0
        for i in range(r.shape[0]):
            ss += g_sig[g, i] * w[i, g]
            rw += r[i] * w[i, g]
        z = rw / math.sqrt(max(ss, 1e-300))
        cusum[g, 0] = max(0.0, cusum[g, 0] + z - allowance)
        cusum[g, 1] = max(0.0, cusum[g, 1] - z - allowance)
        top = max(cusum[g, 0], cusum[g, 1])
        if top > best_top:
            best, best_top = g, top
    return best
