"""The error state's algebra: derivative tensors, the curvature forms, the body-frame reset.

Shared by the process, measurement and vehicle models (:mod:`filters.ekf`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from filters import kernels
from filters.state import ATT, RATE, VEL


def shrink_to_size(x: np.ndarray, var: np.ndarray, clear_sigmas: float = 0.0) -> np.ndarray:
    """A noisy estimate for a Jacobian: each component to ``sign(x) sqrt(max(0, x^2 - var))``.

    ``x^2 - var`` is the unbiased estimate of the true component's square (``var`` the
    estimate's noise variance, (3,)). A Jacobian built from the estimate itself would
    take noise for motion and claim information the measurement does not hold
    (errors in variables); where the component is within its noise it reads zero, and
    where its unbiased size is within ``clear_sigmas`` sigmas of zero when that noise is
    shared with the measurement's innovation (the sensor positions' angular acceleration:
    ``filters.step``).
    """
    x = np.asarray(x, dtype=float)
    var = np.asarray(var, dtype=float)
    if x.shape != var.shape:
        raise ValueError(f"shrink_to_size: x {x.shape} and var {var.shape} differ")
    return kernels.shrink(x, var, clear_sigmas * clear_sigmas)


def _product_derivatives(pairs: Sequence[Sequence[int]]) -> np.ndarray:
    """``D`` (len(pairs), 3, 3) with ``d(w_i w_j)/dw = D[r] @ w`` for each pair ``(i, j)``.

    ``D[r, c, m] = [c = i][m = j] + [c = j][m = i]``.
    """
    d = np.zeros((len(pairs), 3, 3))
    for r, (i, j) in enumerate(pairs):
        d[r, i, j] += 1.0
        d[r, j, i] += 1.0
    return d


#: The (attitude, velocity) error rows of the body-velocity models' second-order term.
_DTHETA_DV = np.r_[ATT, VEL]
#: (attitude, velocity, rate) error indices: the body-velocity remainder's variables.
_DTHETA_DV_DW = np.r_[ATT, VEL, RATE]


def body_velocity_reset_jacobian(
    dtheta: np.ndarray, dxi_v: np.ndarray, vel_ned_mps: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The velocity rows of the body-velocity error's reset Jacobian, ``(G_vv, G_vtheta)``.

    A correction ``(dtheta, dxi_v)`` (NED rad, NED m/s) injected body-style
    (:meth:`NavFilter._inject` with ``body_velocity_error``) at the nominal velocity
    ``vel_ned_mps`` leaves errors ``e`` about the old nominal; about the new one the
    velocity error is, to first order in ``e``,

    ``xi_v' = (I + [dtheta]x) e_v + ([dtheta]x [v]x - [dxi_v]x - [v]x [dtheta]x / 2) e_theta``

    (``C' dv_b' = exp(dtheta) C (dv_b - dv_b_hat)`` and the new attitude error
    ``(I + [dtheta]x / 2) e_theta``: ``exp(dtheta') = exp(dtheta + e) exp(-dtheta)``, whose
    first-order term is ``[dtheta, e] / 2``). Both (3, 3).
    """
    return kernels.body_velocity_reset_rows(
        np.asarray(dtheta, dtype=float),
        np.asarray(dxi_v, dtype=float),
        np.asarray(vel_ned_mps, dtype=float),
    )


def attitude_reset_jacobian(dtheta: np.ndarray) -> np.ndarray:
    """The attitude rows of the reset Jacobian of a correction ``dtheta`` (NED rad), (3, 3).

    ``I + [dtheta]x / 2``, the left (NED) error's reset (checked against exact rotations
    in tests/test_body_velocity_error.py), with its heading column held at ``e_z``
    (observability-constrained, as OC-EKFs hold their unobservable directions): a turn
    of the whole solution about the vertical is the left error's ``e_z`` at every epoch,
    and exactly unobservable at rest. The exact reset's column, ``e_z + dtheta x e_z / 2``,
    put a part of a large heading variance into the tilt's rows at every tilt correction,
    which the fixes then read as heading information: at rest (`static`, 16 runs) the
    heading's sigma fell from 5.0 to 3.6 deg while its error stayed at 5.8 deg rms (z^2
    2.83); held, 4.9-5.0 deg and 0.92-1.00 (docs/notes/filter-notes.md, "the zero-rate
    update at rest").
    """
    return kernels.attitude_reset_rows(np.asarray(dtheta, dtype=float))


def apply_reset_jacobian(
    p: np.ndarray, ga: np.ndarray, gvv: np.ndarray | None = None, gvt: np.ndarray | None = None
) -> np.ndarray:
    """``G p G^T`` (n, n) for the reset Jacobian ``G``: the identity but for the attitude
    rows ``ga`` (:func:`attitude_reset_jacobian`) and, with the body-frame velocity error,
    the velocity rows ``gvv``, ``gvt`` (:func:`body_velocity_reset_jacobian`). Returns a
    new symmetric array."""
    if gvv is None:
        gvv = gvt = kernels.ABSENT
    return kernels.reset_rows(np.asarray(p, dtype=float), ga, gvv, gvt, ATT.start, VEL.start)


def ned_velocity_curvature(vel_ned_mps: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3,) and covariance (3, 3) of the NED velocity's second-order part, m/s, under
    the body-frame velocity error with covariance ``p`` (n, n) about the nominal velocity
    ``vel_ned_mps``.

    The true NED velocity is ``v + xi_v + c``, ``c = dtheta x xi_v - dtheta x (dtheta x v)
    / 2``: each component a quadratic form ``x^T M_i x / 2`` over ``x = (dtheta, xi_v)``,
    so ``E c_i = tr(M_i P) / 2`` and ``Cov(c_i, c_j) = tr(M_i P M_j P) / 2``.
    """
    return kernels.ned_velocity_curvature(np.asarray(vel_ned_mps, dtype=float), p)


#: Largest curvature ``|v| |dtheta|^2 / 2`` (m/s) of a correction the body-frame velocity
#: error (``NavFilter.body_velocity_error``) injects body-style. A larger attitude
#: correction (a tilt relearned after :meth:`NavFilter.reopen_attitude`, tens of degrees)
#: would turn the NED velocity by metres per second beyond the update's linear step and
#: the next GPS velocities would fail their gate: such a correction is injected as the
#: NED error's (velocity added, attitude reset only). 0.05 m/s is half a GPS velocity
#: sigma; at 60 m/s it lets through corrections up to 2.3 deg, the hand-over's 1 deg with
#: room.
BODY_INJECTION_MAX_CURVATURE_MPS = 0.05
#: Largest curvature ``|v| tr(P_att) / 2`` (m/s) the attitude's uncertainty may give the
#: NED velocity while the body-frame velocity error is in use
#: (:meth:`NavFilter.in_body_frame`): above it (a heading several degrees uncertain, a
#: tilt reopened) the NED error's linearisation is the better one, since the NED velocity
#: does not depend on the attitude at all. A GPS velocity sigma (0.1 m/s).
BODY_FRAME_MAX_CURVATURE_MPS = 0.1


def force_curvature_variance(f_n: np.ndarray, p_att: np.ndarray) -> np.ndarray:
    """Variance (3,) of each NED axis of ``b = [dtheta]x^2 f / 2`` for ``dtheta ~ N(0, P_att)``.

    The attitude error's second-order action on the force ``f_n`` (NED, m/s^2):
    ``b_i = dtheta^T M_i dtheta`` with ``M_i = (e_i f^T + f e_i^T) / 4 - f_i I / 2``,
    and a Gaussian quadratic form's variance is ``2 tr(M_i P M_i P)``, which expands to
    ``(u_i^2 + (f.u) P_ii) / 4 + f_i^2 |P|_F^2 / 2 - f_i (P u)_i`` with ``u = P f``;
    (m/s^2)^2.
    """
    return kernels.force_curvature_variance(
        np.asarray(f_n, dtype=float), np.asarray(p_att, dtype=float)
    )
