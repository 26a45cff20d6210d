"""Rauch-Tung-Striebel smoothing of a finished run (``ngnav run --smooth``).

The filter's blocks are not the textbook's predict-then-update: a block's rate
measurement has noise correlated with the block's own propagation noise, and every
update is followed by the error's reset (its Jacobian). So the forward pass carries,
through each block, the joint of the state at the block's start with the current one
(a lag-one clone, :class:`LagOne`): at the propagation their cross-covariance is
``P_j F^T``, and every update and reset on the current state acts on it exactly as
the filter acts on its own covariance. At the block's end that gives ``x_{j|j+1}``
(the start's estimate given the block's measurements: ``x_j [+] d``), its covariance
``P_{j|j+1}`` and the cross-covariance ``X`` with the posterior ``x_{j+1}, P_{j+1}``.
Backwards, from the last epoch (smoothed = filtered), the Gaussian conditioning
``x_j | x_{j+1}`` (the future data tell ``x_j`` nothing more once ``x_{j+1}`` is
known):

- ``C = X P_{j+1}^-1``;
- ``x^s_j = x_j [+] (d + C (x^s_{j+1} [-] x_{j+1}))``;
- ``P^s_j = P_{j|j+1} + C (P^s_{j+1} - P_{j+1}) C^T``.

``P^s_j`` is about ``x_j``, where the recursion needs it; the output is about the
smoothed nominal, so it takes the correction's reset Jacobian, as the filter's covariance
takes its injection's (a correction of the filter's size, milliradians, turned a
direction the vehicle models knew to 0.1 urad into a mix with the other attitude axes:
on `tactical` run 42 the joint NEES at the models' update epochs was 277 against 12,
27 with it). With the body-frame velocity error the NED velocity's second-order part is
added, as in the filter's records.

With independent noise and no resets this is the textbook RTS pass (filterpy's
``rts_smoother``; tests/test_smoother.py checks both that and an exact batch solution
with correlated noise). ``[+]`` and ``[-]`` are the filter's own error injection:
additive for every block but the attitude, the NED (left) rotation
``q = exp(dtheta) q``, and the velocity where the filter takes its error in the body frame.

The filter's fallbacks are followed exactly too. A position and velocity put on a fix,
or a heading set, forget their old correlations: their new errors owe nothing to the
start's (:meth:`LagOne.forget`), so the pass carries on across them through the other
states (a coast's end is smoothed from both sides). An attitude reopened adds variance,
as process noise does. A posterior that is not positive definite restarts the pass
there (counted).

What a block stores (two n x n triangles, the n x n cross-covariance and the nominal
state, 41 kB at n = 50) goes to an unnamed temporary file as the filter runs, so a
long run's smoothing takes disk, not memory.
"""

from __future__ import annotations

import tempfile

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from filters.algebra import (
    apply_reset_jacobian,
    attitude_reset_jacobian,
    body_velocity_reset_jacobian,
    ned_velocity_curvature,
)
from filters.state import ATT, POS, RATE, VEL
from filters.updates import Measurement
from ngnav.rotation import (
    dcm_from_quat,
    quat_conjugate,
    quat_from_rotvec,
    quat_multiply,
    quat_rotate_by_rotvec,
    quat_to_rotvec,
)

#: Counter name of the smoother's restarts, in the run's counts.
RESTARTS = "smoother restarts (posterior not positive definite)"


class LagOne:
    """The joint of the state at a block's start with the current state, through a block.

    The filter calls :meth:`start` at its propagation, :meth:`update` before each
    measurement update and :meth:`reset` with each reset's Jacobian.

    Attributes
    ----------
    cross : array (n, n)
        ``Cov(dx_start, dx_now)``.
    p_start : array (n, n)
        The start state's covariance given the measurements so far.
    d_start : array (n,)
        The start state's correction by those measurements (error coordinates).
    """

    def __init__(self) -> None:
        self.cross: np.ndarray | None = None
        self.p_start: np.ndarray | None = None
        self.d_start: np.ndarray | None = None

    def start(self, p: np.ndarray, phi: np.ndarray) -> None:
        """A block's propagation by ``phi`` from the covariance ``p`` (before it)."""
        self.cross = p @ phi.T
        self.p_start = p.copy()
        self.d_start = np.zeros(p.shape[0])

    def update(self, meas: Measurement, p: np.ndarray) -> None:
        """The measurement ``meas`` about to update the current state (prior ``p``)."""
        if self.cross is None:
            return
        h = meas.H
        s = meas.innovation_cov(p)
        pht = p @ h.T
        if meas.cross is not None:
            pht = pht + meas.cross
        # the start's gain: its covariance with the innovation is X H^T (the noise is
        # independent of the start's error)
        kc = np.linalg.solve(s, (self.cross @ h.T).T).T
        k = np.linalg.solve(s, pht.T).T
        self.d_start += kc @ meas.z
        self.p_start -= kc @ s @ kc.T
        self.cross -= kc @ (s @ k.T)

    def forget(self, idx: slice | list[int]) -> None:
        """States the filter has just put on a fix or a configured value, with their old
        correlations dropped (a reset, not a measurement): the start tells nothing about
        their new errors."""
        if self.cross is not None:
            self.cross[:, idx] = 0.0

    def reset(
        self, ga: np.ndarray, gvv: np.ndarray | None = None, gvt: np.ndarray | None = None
    ) -> None:
        """The current state's reset after an update: the attitude's Jacobian ``ga`` (and
        the body-frame velocity's ``gvv``, ``gvt``), applied to the cross-covariance's
        columns as the filter applies them to its covariance (:meth:`NavFilter._inject`)."""
        if self.cross is None:
            return
        x = self.cross
        cols_t = x[:, ATT] @ ga.T
        if gvv is not None:
            x[:, VEL] = x[:, VEL] @ gvv.T + x[:, ATT] @ gvt.T
        x[:, ATT] = cols_t


class SmootherLog:
    """The forward pass's stores for the backward pass, spooled to a temporary file.

    Give the filter :attr:`lag` (``nf.lag``) and call :meth:`posterior` at the start of
    every block (before its propagation) and once at the end of the run; then
    :meth:`smooth`.

    Parameters
    ----------
    n : int
        Size of the error state (the nominal state has one value more: the quaternion).
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.lag = LagOne()
        self._iu = np.triu_indices(n)
        self._m = n + 1  # nominal values
        ntri = self._iu[0].size
        # posterior rows: t, nominal, body-frame velocity error, P triangle
        self._post_len = 2 + self._m + ntri
        # lag rows: d_start, P_start triangle, cross
        self._lag_len = n + ntri + n * n
        self._post = tempfile.TemporaryFile()
        self._lags = tempfile.TemporaryFile()
        self.n_posteriors = 0
        self.n_lags = 0

    @staticmethod
    def nominal(nf) -> np.ndarray:
        """The filter's nominal state as one vector (pos, vel, q, w, bias, dr, dg, aoa)."""
        aoa = [nf.aoa_b, nf.aoa_k][: nf.layout.n_aoa]
        return np.concatenate([nf.pos, nf.vel, nf.q, nf.w, nf.bias, nf.dr, nf.dg, aoa])

    def posterior(self, nf) -> None:
        """Store the filter's state now: the end of one block and the start of the next."""
        lag = self.lag
        if lag.cross is not None:
            self._lags.write(lag.d_start.tobytes())
            self._lags.write(lag.p_start[self._iu].tobytes())
            self._lags.write(lag.cross.tobytes())
            self.n_lags += 1
            lag.cross = None
        head = np.concatenate([[nf.t_s], self.nominal(nf), [float(nf.in_body_frame())]])
        self._post.write(head.tobytes())
        self._post.write(nf.P[self._iu].tobytes())
        self.n_posteriors += 1

    def _rows(self, f, length: int, count: int) -> np.ndarray:
        f.flush()
        if count == 0:
            return np.empty((0, length))
        return np.memmap(f, dtype=np.float64, mode="r", shape=(count, length))

    def _full(self, tri: np.ndarray) -> np.ndarray:
        p = np.zeros((self.n, self.n))
        p[self._iu] = tri
        return p + np.triu(p, 1).T

    def smooth(self, layout) -> tuple[list[tuple], int]:
        """Run the backward pass over the stored blocks (and delete the stores).

        Parameters
        ----------
        layout : filters.state.StateLayout
            The filter's state layout (for the bias block's size).

        Returns
        -------
        rows : list of tuple
            One per posterior (time order): ``(t_s, pos, vel, q, w, bias, cov_nav)``,
            the smoothed nominal and its 12 x 12 navigation covariance.
        restarts : int
            Blocks whose chain a posterior not positive definite broke.
        """
        if self.n_posteriors != self.n_lags + 1:
            raise ValueError(f"smoother: {self.n_posteriors} posteriors for {self.n_lags} blocks")
        m, n = self._m, self.n
        post = self._rows(self._post, self._post_len, self.n_posteriors)
        lags = self._rows(self._lags, self._lag_len, self.n_lags)
        ntri = self._iu[0].size
        nb = layout.bias.stop - layout.bias.start
        rows: list[tuple] = [None] * self.n_posteriors
        nxt = post[-1]
        x_next, p_next = np.array(nxt[1 : 1 + m]), self._full(nxt[2 + m :])
        xs, ps = x_next, p_next
        rows[-1] = _row(nxt[0], xs, ps, nb, bool(nxt[1 + m]))
        restarts = 0
        for j in range(self.n_lags - 1, -1, -1):
            a = post[j]
            xa = np.array(a[1 : 1 + m])
            b = lags[j]
            try:
                # C^T = P_{j+1}^-1 X^T
                ct = cho_solve(cho_factor(p_next), b[n + ntri :].reshape(n, n).T)
            except (LinAlgError, ValueError):
                ct = None
            body = bool(a[1 + m])
            if ct is None:
                restarts += 1
                xs, ps = xa, self._full(a[2 + m :])
                p_out = ps
            else:
                c = ct.T
                e_next = boxminus(xs, x_next, bool(nxt[1 + m]))
                corr = b[0:n] + c @ e_next
                xs = boxplus(xa, corr, body)
                ps = self._full(b[n : n + ntri]) + c @ (ps - p_next) @ ct
                ps = 0.5 * (ps + ps.T)
                # ps is about x_j (the recursion needs it there); the output is about
                # the smoothed nominal: the correction's reset Jacobian, as the filter's
                # injection applies its own
                ga = attitude_reset_jacobian(corr[ATT])
                gv = body_velocity_reset_jacobian(corr[ATT], corr[VEL], xa[3:6]) if body else ()
                p_out = apply_reset_jacobian(ps, ga, *gv)
            rows[j] = _row(a[0], xs, p_out, nb, body)
            nxt = a
            x_next, p_next = xa, self._full(a[2 + m :])
        del post, lags, nxt, a
        self.close()
        return rows, restarts

    def close(self) -> None:
        """Delete the temporary stores."""
        self._post.close()
        self._lags.close()


def _row(t: float, x: np.ndarray, p: np.ndarray, nb: int, body: bool) -> tuple:
    """One smoothed epoch: ``(t_s, pos, vel, q, w, bias, cov_nav)``; with the body-frame
    velocity error (``body``) the NED velocity a user reads, as the filter's records give it
    (the second-order part's mean and covariance added)."""
    vel = x[3:6].copy()
    cov = p[:12, :12].copy()
    if body:
        mc, cc = ned_velocity_curvature(vel, p)
        vel += mc
        cov[VEL, VEL] += cc
    rest = (x[6:10].copy(), x[10:13].copy(), x[13 : 13 + nb].copy())
    return (float(t), x[0:3].copy(), vel, *rest, cov)


def boxplus(x: np.ndarray, e: np.ndarray, body: bool = False) -> np.ndarray:
    """The nominal vector ``x`` (n + 1,) corrected by the error ``e`` (n,), as the filter
    injects it: attitude ``q <- exp(dtheta) q``, everything else added, but with the
    body-frame velocity error (``body``) ``v <- exp(dtheta) (v + xi_v - dtheta x v)``."""
    out = np.empty_like(x)
    dth = e[ATT]
    out[0:3] = x[0:3] + e[POS]
    if body:
        out[3:6] = dcm_from_quat(quat_from_rotvec(dth)) @ (x[3:6] + e[VEL] + np.cross(x[3:6], dth))
    else:
        out[3:6] = x[3:6] + e[VEL]
    out[6:10] = quat_rotate_by_rotvec(x[6:10], dth, left=True)
    out[10:] = x[10:] + e[RATE.start :]
    return out


def boxminus(x: np.ndarray, y: np.ndarray, body: bool = False) -> np.ndarray:
    """The error ``e`` with ``x = y [+] e`` (:func:`boxplus`), (n,)."""
    e = np.empty(x.shape[0] - 1)
    e[POS] = x[0:3] - y[0:3]
    dth = quat_to_rotvec(quat_multiply(x[6:10], quat_conjugate(y[6:10])))
    e[ATT] = dth
    if body:
        e[VEL] = dcm_from_quat(quat_from_rotvec(dth)).T @ x[3:6] - y[3:6] - np.cross(y[3:6], dth)
    else:
        e[VEL] = x[3:6] - y[3:6]
    e[RATE.start :] = x[10:] - y[10:]
    return e
