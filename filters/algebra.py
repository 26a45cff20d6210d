"""The error state's algebra: derivative tensors, the curvature forms, the body-frame reset.

Shared by the process, measurement and vehicle models (:mod:`filters.ekf`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from filters.state import ATT, RATE, VEL
from ngnav.rotation import skew


def shrink_to_size(x: np.ndarray, var: np.ndarray) -> np.ndarray:
    """A noisy estimate for a Jacobian: each component to ``sign(x) sqrt(max(0, x^2 - var))``.

    ``x^2 - var`` is the unbiased estimate of the true component's square (``var`` the
    estimate's noise variance, (3,)). A Jacobian built from the estimate itself would
    take noise for motion and claim information the measurement does not hold
    (errors in variables); where the component is within its noise it reads zero.
    """
    return np.array(
        [
            math.copysign(math.sqrt(max(xi * xi - v, 0.0)), xi) if xi else 0.0
            for xi, v in zip(np.asarray(x).tolist(), np.asarray(var).tolist(), strict=True)
        ]
    )


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
_DTHETA_DV_IX = np.ix_(_DTHETA_DV, _DTHETA_DV)
#: (attitude, velocity, rate) error indices: the body-velocity remainder's variables.
_DTHETA_DV_DW = np.r_[ATT, VEL, RATE]
#: Levi-Civita symbol: ``(a x b)_i = EPS[i] a . b``, EPS[i, j, k] = eps_ijk.
_EPS = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_i, _j, _k] = 1.0
    _EPS[_i, _k, _j] = -1.0


_E3 = np.eye(3)
#: The NED velocity curvature's bilinear part, ``(dtheta x xi_v)_i``, as ``x^T M_i x / 2``
#: over ``x = (dtheta, xi_v)`` (:meth:`NavFilter.velocity_curvature`).
_CURVATURE_CROSS = np.zeros((3, 6, 6))
_CURVATURE_CROSS[:, 0:3, 3:6] = _EPS
_CURVATURE_CROSS[:, 3:6, 0:3] = _EPS.transpose(0, 2, 1)


def _axial(x: np.ndarray) -> np.ndarray:
    """``sum_jk eps_ijk x_jk`` (3,): ``E[a x b]`` for ``x = E[a b^T]``."""
    return np.array([x[1, 2] - x[2, 1], x[2, 0] - x[0, 2], x[0, 1] - x[1, 0]])


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
    st = skew(np.asarray(dtheta, dtype=float))
    sv = skew(np.asarray(vel_ned_mps, dtype=float))
    gvv = np.eye(3) + st
    gvt = st @ sv - skew(np.asarray(dxi_v, dtype=float)) - 0.5 * sv @ st
    return gvv, gvt


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
