"""Failed channels out of the solve: the pipeline's side of :mod:`filters.faults`.

A channel the health tests isolate is excluded from the samples the filter has not
yet used, from the fault's onset on (the monitor watches the input, a fusion lag
ahead of the filter: a flat line found 25 samples after it began is out of every
block). The blocks then solve the remaining channels, rate-aided where they must be
(:mod:`filters.reduced`), and the filter switches to that solve's noise, transition
and rate measurement at the first block that holds the exclusion
(:meth:`filters.ekf.NavFilter.set_solve`). Exclusion lasts for the rest of the run.
A layout the remaining channels cannot solve (angular acceleration or force lost)
keeps the channel, and says so once in the counts.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from filters.noise import filter_noise
from filters.reduced import reduced_solve
from ngnav.layout import rate_quadratics

#: The count of isolated channels the remaining ones could not do without.
NOT_EXCLUDED = "channels isolated but kept (the rest cannot solve without them)"


class ExclusionMixin:
    """Exclude isolated channels and solve the blocks with the rest."""

    def _exclude_from(self, channel: int, onset_s: float) -> None:
        """Exclude ``channel`` (0-based) from the stored samples at ``onset_s`` on."""
        bit = 1 << channel
        if self._excluded & bit:
            return
        mask = self._excluded | bit
        if self._reduced_for(mask) is None:
            self.counts[NOT_EXCLUDED] = self.counts.get(NOT_EXCLUDED, 0) + 1
            return
        self._excluded = mask
        used = self._n - self._base
        first = int(np.searchsorted(self._t[:used], onset_s - 1e-9))
        if self.started:
            first = max(first, self._i0 + 1 - self._base)  # what the filter has used stays
        self._excl[first:used] |= bit

    def _reduced_for(self, mask: int):
        """The reduced solve of ``mask`` (cached), or None when it cannot be solved."""
        if mask not in self._reduced:
            try:
                red = reduced_solve(self.cfg.layout, self.cfg.noise_sigma_mps2, self._cols, mask)
            except ValueError:
                red = None
            self._reduced[mask] = red
        return self._reduced[mask]

    def _solve_now(self) -> np.ndarray:
        """The solve (k, N) the filter's model is set for."""
        if self._filter_mask == 0:
            return self._smat
        return self._reduced[self._filter_mask].solve_matrix

    def _features(self, g0: int, g1: int, mask: int, omega_b_rps: np.ndarray) -> np.ndarray:
        """Solved features (K, k) of stored samples ``g0 .. g1 - 1`` (global indices)
        without the channels in ``mask``; aided terms from the rate ``omega_b_rps`` (3,).

        A block takes one mask for all its samples (the compensation and the noise are
        the solve's): the exclusions of its last sample."""
        b = self._base
        a = self._ach[g0 - b : g1 - b]
        if not mask:
            return a @ self._smat.T
        red = self._reduced[mask]
        return a @ red.solve_matrix.T - red.aided_quadratics @ rate_quadratics(omega_b_rps)

    def _switch_solve(self, mask: int) -> None:
        """Set the filter's model for the solve without the channels in ``mask``."""
        cfg = self.cfg
        nf = self.nf
        red = self._reduced[mask]
        s_old = self._solve_now()
        s_new = red.solve_matrix
        # the bias states are the solve's raw feature biases S b: map them to the new
        # solve through the channels the old one still saw (exact for a square solve)
        old, new = self._solved, red.solved
        bias_map = np.eye(self._k)
        bias_map[new] = 0.0
        bias_map[np.ix_(new, old)] = (s_new @ np.linalg.pinv(s_old[old]))[new]
        se = None if self._e_chan is None else s_new @ self._e_chan
        noise = filter_noise(s_new, cfg, None if se is None else se[:, 0:6])
        if self.method == "oracle":
            noise = replace(noise, position_sigma_m=0.0)
        unsolved = np.flatnonzero(~new)
        if unsolved.size:
            # a feature no remaining channel solves keeps its bias state, which nothing
            # reads; its prior stays the whole solve's, so that a start again's covariance
            # is positive definite (the reduced solve's zero row gave it none)
            prior = noise.bias_prior_cov.copy()
            block = np.ix_(unsolved, unsolved)
            prior[block] = self.noise.bias_prior_cov[block]
            noise = replace(noise, bias_prior_cov=prior)
        nq_rows = new[6:]
        nf.set_solve(
            noise,
            s_new,
            None if se is None else se[6:, 6:12],
            None if se is None else se[0:6, 6:12],
            nq_rows,
            red.aided_quadratics,
            bias_map,
        )
        # what the pipeline keeps of the noise: the load's, the forecast error's floor
        # and the sensor positions' Jacobian noise scale with the raw per-sample variance
        raw_old = np.diag((s_old * cfg.noise_sigma_mps2**2) @ s_old.T)[0:6]
        raw_new = np.diag((s_new * cfg.noise_sigma_mps2**2) @ s_new.T)[0:6]
        ratio = raw_new / raw_old
        self.forecast_error_floor = self.forecast_error_floor * ratio
        self.wdot_jacobian_var = self.wdot_jacobian_var * ratio[0:3]
        self._load_noise_cov = noise.feature_cov[3:6, 3:6].copy()
        self._se = se
        self._solved = new.copy()
        self._filter_mask = mask
        self.monitor.set_signatures(s_new[6:][nq_rows] * self._parity_on)


#: A suspect channel's offset walk while the parity names its group but not the
#: channel, m/s^2 per sqrt(s): room for a drift of 1 milli-g per second, 0.1 m/s^2 in
#: 10 s, against this walk's 0.32 m/s^2 over 10 s.
SUSPECT_WALK_MPS2_RTS = 0.03
#: The filter's estimate of one suspect's offset at this many sigmas, with every other
#: suspect's within :data:`CLEAR_SIGMAS`, names it.
NAME_SIGMAS = 5.0
#: See :data:`NAME_SIGMAS`.
CLEAR_SIGMAS = 2.0


class SuspectsMixin:
    """A parity alarm on a group: carry the offset in the biases until one is named."""

    def _suspect(self, channels: tuple[int, ...], t_s: float) -> None:
        """Channels (0-based) of which one is faulty: let the bias states carry its offset."""
        nf = self.nf
        u = self._solve_now()[:, list(channels)]  # the raw feature biases' directions, per m/s^2
        nf.set_extra_bias_walk(SUSPECT_WALK_MPS2_RTS**2 * (u @ u.T))
        bs = nf.layout.bias
        # what reads each suspect's offset from the biases, once per alarm
        self._suspects = (tuple(channels), np.linalg.pinv(u), nf.bias.copy(), nf.P[bs, bs].copy())

    def _test_suspects(self) -> None:
        """Name a suspect whose offset estimate stands out (then it is isolated)."""
        if self._suspects is None:
            return
        channels, lu, b0, p0 = self._suspects
        if self._excluded & sum(1 << c for c in channels):
            # a sample test named one of them: it is out, the others are clear
            self._clear_suspects()
            return
        nf = self.nf
        bs = nf.layout.bias
        d = lu @ (nf.bias - b0)
        # the change's uncertainty: the estimate's now and at the alarm (their
        # correlation left out: conservative)
        sd = np.sqrt(np.diag(lu @ (nf.P[bs, bs] + p0) @ lu.T))
        z = np.abs(d) / sd
        best = int(np.argmax(z))
        others = np.delete(z, best)
        if z[best] >= NAME_SIGMAS and np.all(others <= CLEAR_SIGMAS):
            self.monitor.isolate(channels[best], nf.t_s)
            self._clear_suspects()

    def _clear_suspects(self) -> None:
        self.nf.set_extra_bias_walk(np.zeros_like(self.nf.extra_bias_walk))
        self._suspects = None
