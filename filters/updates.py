"""Kalman updates beyond filterpy's plain one, built on it.

:class:`Measurement` is what every measurement model gives the filter: ``(z, H, R)``
and, where there is one, the noise's correlation with the propagation.
:func:`update_correlated` is filterpy's own correlated-noise update
(``KalmanFilter.update_correlated``), for noise correlated with the prior's error;
:func:`quadratic_form` is the NIS ``y^T S^-1 y`` the gates test.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np
from filterpy.kalman import KalmanFilter
from filterpy.kalman import update as kf_update

from filters import kernels


class Measurement(NamedTuple):
    """One measurement as filterpy's ``update`` takes it, at a zero error state.

    Attributes
    ----------
    z : array (m,)
        The innovation: measured minus predicted, in the measurement's units (the
        error state is zero between updates, so it is filterpy's residual ``z - H x``).
    H : array (m, n)
        Its Jacobian on the error state.
    R : array (m, m)
        Its noise covariance.
    cross : array (n, m) or None
        ``E[dx v^T]``, the prior error's covariance with the noise (the rate products'
        with their block's propagation noise); None where they are independent.
    """

    z: np.ndarray
    H: np.ndarray
    R: np.ndarray
    cross: np.ndarray | None = None

    def innovation_cov(self, p: np.ndarray) -> np.ndarray:
        """``S = H P H^T + R`` (plus ``H M + M^T H^T`` with a cross-covariance ``M``)."""
        return kernels.innovation_cov(
            self.H, p, self.R, kernels.ABSENT if self.cross is None else self.cross
        )

    def take(self, rows: np.ndarray) -> Measurement:
        """The measurement of the rows ``rows`` (boolean (m,)) only: the components a
        source did not measure (a fix without altitude) left out."""
        cross = None if self.cross is None else self.cross[:, rows]
        return Measurement(self.z[rows], self.H[rows], self.R[np.ix_(rows, rows)], cross)


class _Engines(threading.local):
    """Per thread, one filterpy ``KalmanFilter`` per ``(n, m)``, holding nothing between calls."""

    def __init__(self) -> None:
        self.by_size: dict[tuple[int, int], KalmanFilter] = {}


_engines = _Engines()


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
    the propagation noise of the block the measurement was made over): filterpy's
    ``KalmanFilter.update_correlated`` (Simon, *Optimal State Estimation*, 7.1):
    ``S = H P H^T + H M + M^T H^T + R``, ``K = (P H^T + M) S^-1``,
    ``P+ = P - K (H P + M^T)``. With ``m`` None (independent noise) it is filterpy's
    plain update. (Its ``P+`` is not the Joseph form: the filter symmetrises P in the
    reset that follows every update, :func:`filters.kernels.reset_rows_in_place`.)
    """
    if m is None:
        return kf_update(x, p, z, r, h)
    size = (x.shape[0], z.shape[0])
    kf = _engines.by_size.get(size)
    if kf is None:
        kf = _engines.by_size[size] = KalmanFilter(dim_x=size[0], dim_z=size[1])
        kf.inv = kernels.inverse
    kf.x, kf.P, kf.M = x, p, m
    kf.update_correlated(z, r, h)
    x_new, p_new = kf.x, kf.P
    kf.x = kf.P = kf.M = None  # hold no caller's arrays
    return x_new, p_new


def quadratic_form(y: np.ndarray, s: np.ndarray) -> float:
    """``y^T S^-1 y`` for a symmetric positive definite S (:func:`kernels.quadratic_form`)."""
    return kernels.quadratic_form(np.asarray(y, dtype=float), np.asarray(s, dtype=float))
