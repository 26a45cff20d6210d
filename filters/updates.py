"""Kalman updates beyond filterpy's plain one, built on it.

:func:`update_correlated` is filterpy's ``update`` on the state augmented with the
measurement noise, for noise correlated with the prior's error; :func:`quadratic_form`
is the NIS ``y^T S^-1 y`` the gates test; :func:`update_consider` the Schmidt update
that leaves some states unestimated and :func:`refresh_markov_state` the step of a
first-order Gauss-Markov error carried as such a state.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import update as kf_update


def update_correlated(
    x: np.ndarray,
    p: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
    h: np.ndarray,
    m: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update whose measurement noise ``v`` is correlated with the state error.

    As filterpy's ``update(x, P, z, R, H)`` (residual ``z - H x``), but with
    ``m`` (n, nz) = ``E[dx v^T]``, the prior error's covariance with the noise (here:
    the propagation noise of the block the measurement was made over). filterpy's
    update runs on the state augmented with ``v`` (covariance ``[[P, M], [M^T, R]]``,
    ``H_a = [H, I]``, no further noise), which gives the correlated-noise filter
    (Simon, *Optimal State Estimation*, 7.1): ``S = H P H^T + H M + M^T H^T + R``,
    ``K = (P H^T + M) S^-1``, ``P+ = P - K (H P + M^T)``; the noise rows are dropped.
    With ``m`` None (independent noise) it is filterpy's plain update.
    """
    if m is None:
        return kf_update(x, p, z, r, h)
    n, nz = x.shape[0], z.shape[0]
    pa = np.empty((n + nz, n + nz))
    pa[:n, :n] = p
    pa[:n, n:] = m
    pa[n:, :n] = m.T
    pa[n:, n:] = r
    ha = np.hstack([h, np.eye(nz)])
    xa, pa = kf_update(np.concatenate([x, np.zeros(nz)]), pa, z, np.zeros((nz, nz)), ha)
    return xa[:n], pa[:n, :n]


def update_consider(
    x: np.ndarray,
    p: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
    h: np.ndarray,
    m: np.ndarray | None,
    fixed: slice | np.ndarray | None,
    return_gain: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`update_correlated` that leaves the states in ``fixed`` unestimated (Schmidt).

    The Schmidt-Kalman ("consider") update: the states in ``fixed`` keep their value
    and covariance, their gain rows are zero, and the covariance of every other state
    and its cross-covariance with them follow the gain actually applied,
    ``P+ = P - K (H P + M^T) - (P H^T + M) K^T + K S K^T`` (the general form for any
    gain ``K`` with noise correlated with the prior as ``M``; with the optimal gain it
    is :func:`update_correlated`'s). The measurement still counts their uncertainty:
    ``S = H P H^T + H M + M^T H^T + R`` includes it, so a poorly known parameter
    widens the update's uncertainty instead of being pulled to fit the data. filterpy
    has no consider update; with ``fixed`` None this is :func:`update_correlated`.
    ``fixed`` is a slice or an integer index array of the consider states. With
    ``return_gain`` the gain applied (n, nz) is returned too, as a third element.
    """
    if fixed is None and not return_gain:
        return update_correlated(x, p, z, r, h, m)
    ph = p @ h.T
    if m is not None:
        ph = ph + m
    s = h @ ph + r
    if m is not None:
        hm = h @ m
        s = s + hm.T  # h P h^T + h M + M^T h^T + R (ph already holds M)
    s = 0.5 * (s + s.T)
    k = np.linalg.solve(s, ph.T).T
    if fixed is not None:
        k[fixed] = 0.0
    y = z - h @ x
    kph = k @ ph.T
    p_new = p - kph - kph.T + k @ s @ k.T
    if return_gain:
        return x + k @ y, 0.5 * (p_new + p_new.T), k
    return x + k @ y, 0.5 * (p_new + p_new.T)


def refresh_markov_state(p: np.ndarray, i: int, var: float, phi: float) -> np.ndarray:
    """Step a first-order Gauss-Markov error carried as state ``i`` of covariance ``p``.

    The error follows ``b+ = a b + u`` with ``u`` independent of everything before,
    chosen so that ``b+`` has variance ``var`` and correlation ``phi`` with ``b``
    relative to its size: ``a = phi sqrt(var / P_ii)``, ``Var u = (1 - phi^2) var``.
    Row and column ``i`` of ``p`` are scaled by ``a`` (the cross-covariances follow
    the state) and ``P_ii`` becomes ``var``. A congruence plus a nonnegative diagonal
    term, so ``p`` stays positive semidefinite. With ``P_ii = 0`` (the first step)
    or ``phi = 0`` the error is fresh: its row and column are zeroed.
    ``a = 0`` when ``var`` is 0 as well.

    Parameters
    ----------
    p : array (n, n)
        Covariance, modified in place and returned.
    i : int
        Index of the Gauss-Markov state.
    var : float
        Its variance after the step (>= 0; units of the state squared).
    phi : float
        Correlation with the previous value, in [-1, 1] (``exp(-dt / tau)`` for a
        stationary process; negative where the error's law changes sign).
    """
    if not (np.isfinite(var) and var >= 0.0):
        raise ValueError(f"var must be a finite number >= 0, got {var}")
    if not -1.0 <= phi <= 1.0:
        raise ValueError(f"phi must be in [-1, 1], got {phi}")
    old = float(p[i, i])
    a = phi * np.sqrt(var / old) if old > 0.0 and var > 0.0 else 0.0
    p[i, :] *= a
    p[:, i] *= a
    p[i, i] = var
    return p


def quadratic_form(y: np.ndarray, s: np.ndarray) -> float:
    """``y^T S^-1 y`` for a symmetric positive definite S (closed form for 3 x 3)."""
    if y.shape[0] != 3:
        return float(y @ np.linalg.solve(s, y))
    (a, b, c), (_, d, e), (_, _, f) = s.tolist()
    # adjugate of the symmetric 3 x 3 matrix
    ia, ib, ic = d * f - e * e, c * e - b * f, b * e - c * d
    id_, ie, if_ = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * ia + b * ib + c * ic
    x, yy, z = y.tolist()
    num = ia * x * x + id_ * yy * yy + if_ * z * z + 2.0 * (ib * x * yy + ic * x * z + ie * yy * z)
    return num / det if det > 0.0 else float("inf")
