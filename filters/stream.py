"""The pipeline's input side: samples and fixes in any interleaving, held to the fusion horizon."""

from __future__ import annotations

import bisect

import numpy as np

from filters import kernels
from ngnav.errors import CovarianceError
from ngnav.layout import kinematic_features


class StreamMixin:
    """Buffer samples and fixes, start the filter when it can, run blocks to the horizon."""

    # ------------------------------------------------------------------ input
    def replay(self, samples, fixes, progress=None) -> None:
        """Push a whole recorded run (``ArraySamples``, ``GpsFixes``) in arrival order (a
        fix after the samples before its arrival) and finish; ``progress(fraction)`` as
        the samples go in."""
        t = samples.t_s
        arrival = fixes.t_s + fixes.latency_s
        order = np.argsort(arrival, kind="stable")
        # the sample after which each fix arrives
        after = np.searchsorted(t, arrival[order], side="right")
        i = 0
        n_t = t.shape[0]
        step = max(1, n_t // 50)
        for m, j in zip(order.tolist(), after.tolist(), strict=True):
            while i < j:
                k = min(j, i + step)
                self.push_samples(t[i:k], samples.accel_mps2[i:k])
                i = k
                if progress is not None:
                    progress(i / n_t)
            self.push_fix(
                fixes.t_s[m],
                fixes.lat_deg[m],
                fixes.lon_deg[m],
                fixes.alt_m[m],
                fixes.vel_ned_mps[m],
                fixes.h_acc_m[m],
                fixes.v_acc_m[m],
                fixes.vel_acc_mps[m],
            )
        while i < n_t:
            k = min(n_t, i + step)
            self.push_samples(t[i:k], samples.accel_mps2[i:k])
            i = k
            if progress is not None:
                progress(i / n_t)
        self.finish()

    def push_samples(self, t_s: np.ndarray, accel_mps2: np.ndarray) -> int:
        """Take consecutive array samples (K,), (K, N) m/s^2; returns epochs recorded.

        The samples must continue the uniform grid (a gap is the caller's to
        fill with NaN rows, as the readers do); non-finite and saturated rows
        are held and counted.
        """
        if self.finished:
            raise ValueError("the pipeline has finished; it takes no more samples")
        t_s = np.asarray(t_s, dtype=float).reshape(-1)
        raw = np.asarray(accel_mps2, dtype=float).reshape(t_s.shape[0], -1)
        if raw.shape[1] != self.n_channels:
            raise ValueError(
                f"config layout has {self.n_channels} channels, the array data has {raw.shape[1]}"
            )
        if t_s.shape[0] == 0:
            return 0
        cfg = self.cfg
        nonfinite = ~np.isfinite(raw)
        with np.errstate(invalid="ignore"):
            bad_ch = nonfinite | (np.abs(raw) >= cfg.range_mps2 * (1 - 1e-9))
        nf_bits, bad_bits = nonfinite @ self._bits, bad_ch @ self._bits
        # a bad channel reads its offset (zero once calibrated): a row held whole then
        # holds no NaN, and a row whose bad channel is excluded keeps its good ones
        a = (np.where(bad_ch, cfg.offset_mps2, raw) - cfg.offset_mps2) / cfg.scale
        if self._d_true is not None:
            # the exact mounting-error term: true geometry, true motion
            tr = self.truth
            g = slice(self._n, self._n + t_s.shape[0])
            phi = kinematic_features(tr.omega_dot_b_rps2[g], tr.f_b_mps2[g], tr.omega_b_rps[g])
            a -= phi @ self._d_true.T
        self._append(t_s, raw, a, nf_bits, bad_bits)
        return self._advance()

    def push_fix(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vel_ned_mps: np.ndarray,
        h_acc_m: float,
        v_acc_m: float,
        vel_acc_mps: float,
    ) -> int:
        """Take one GPS fix (time of validity, WGS-84, NED velocity, 1-sigma); returns epochs.

        An altitude or velocity component the receiver did not give is NaN: the filter
        fuses the rest (:meth:`NavFilter.update_gps`), but starts only on a whole fix.
        Without an altitude the horizontal position is placed at the filter's altitude
        (the reference point's before the start).
        """
        if self.finished:
            raise ValueError("the pipeline has finished; it takes no more fixes")
        no_alt = not np.isfinite(alt_m)
        if no_alt:
            alt_m = self._ltp.to_geodetic(self.nf.pos)[2] if self.started else self._ltp.alt0_m
        ned = self._ltp.to_ned(
            np.array([lat_deg], dtype=float),
            np.array([lon_deg], dtype=float),
            np.array([alt_m], dtype=float),
        )[0]
        if no_alt:
            ned[2] = np.nan
        fix = (
            float(t_s),
            ned,
            np.array(vel_ned_mps, dtype=float).reshape(3),
            np.array([h_acc_m, h_acc_m, v_acc_m], dtype=float),
            float(vel_acc_mps),
            self._n_fix,
        )
        self._n_fix += 1
        if not self.started:
            self._fixes.append(fix)
            return self._advance()
        self._place_fix(fix)
        return self._advance()

    def finish(self) -> int:
        """No more input: process the buffered tail; returns epochs recorded.

        Raises ValueError if the filter never started (no usable fix).
        """
        if self.finished:
            return 0
        if not self.started:
            if self._n < 2:
                raise ValueError(f"the run holds {self._n} array samples; at least 2 are needed")
            if not self._try_start(final=True):
                raise ValueError(
                    "no whole GPS fix (latitude, longitude, altitude and 3-D velocity) after "
                    "the alignment period: cannot set position and velocity"
                )
        self.finished = True
        n_before = self.n_epochs
        last = self._n - 1
        t_last = self._t[last - self._base]
        keep = []
        for idx, order, fix in self._pending:
            if idx > last:
                if fix[0] <= t_last + self.dt / 2:
                    keep.append((last, order, fix))
                else:
                    self.counts["gps fixes outside the array's time span"] += 1
            else:
                keep.append((idx, order, fix))
        self._pending = sorted(keep)
        self._run_blocks(final=True)
        # a fix that came later than the fusion lag after the last block has no block left
        self.counts["gps fixes after the last array sample"] += len(self._late) + len(self._pending)
        self._late, self._pending = [], []
        if self.smoother is not None:
            self.smoother.posterior(self.nf)
        return self.n_epochs - n_before

    # ---------------------------------------------------------------- start
    def _place_fix(self, fix: tuple) -> None:
        """File a fix that arrived after the start (pending, late or outside)."""
        t_fix = fix[0]
        if t_fix < self._t0 - self.dt / 2:
            self.counts["gps fixes outside the array's time span"] += 1
            return
        idx = int(np.rint((t_fix - self._t0) / self.dt))
        if idx <= self._i0:
            if idx <= self._i_start:
                self.counts["gps fixes before the filter start"] += 1
                return
            self.counts["gps fixes later than the fusion lag"] += 1
            self._late.append(fix)
            return
        bisect.insort(self._pending, (idx, fix[5], fix))

    def _advance(self) -> int:
        n_before = self.n_epochs
        if not self.started and not self._try_start(final=False):
            return 0
        self._run_blocks(final=False)
        return self.n_epochs - n_before

    def _try_start(self, final: bool) -> bool:
        cfg = self.cfg
        ini = cfg.initial
        t = self._t[: self._n]  # nothing is dropped before the start: base is 0
        if self._n < 2:
            return False
        if self.dt is None:
            if self._n < 9 and not final:
                return False
            self.dt = float(np.median(np.diff(t)))
            if not self.dt > 0:
                raise ValueError("array sample times do not increase")
        dt = self.dt
        t0 = t[0]
        if ini.alignment == "static":
            if t[-1] < t0 + ini.static_s and not final:
                return False
            i_align = int(np.searchsorted(t, t0 + ini.static_s))
        else:
            i_align = 0
        lag_n = self._lag_n()
        best = None
        for fix in self._fixes:
            inside = fix[0] >= t0 - dt / 2 and fix[0] <= t[-1] + dt / 2
            idx = min(int(np.rint((fix[0] - t0) / dt)), self._n - 1)
            if not inside or idx < i_align or not whole_fix(fix):
                continue
            if best is None or (fix[0], fix[5]) < (best[1][0], best[1][5]):
                best = (idx, fix)
        if best is None:
            return False
        i_start, first = best
        if not final and self._n - 1 < i_start + lag_n:
            return False  # an earlier fix may still arrive within the lag
        self._t0 = t0
        self._monitor_to(min(i_start + lag_n, self._n - 1) + 1)
        self._start(i_start, first)
        rest = [f for f in self._fixes if f is not first]
        self._fixes = []
        for fix in sorted(rest, key=lambda f: f[5]):
            self._place_fix(fix)
        return True

    def _lag_n(self) -> int:
        return int(np.ceil(self.cfg.filter.fusion_lag_s / self.dt - 1e-9))

    # --------------------------------------------------------------- blocks
    def _run_blocks(self, final: bool) -> None:
        last = self._n - 1
        lag_n = 0 if final else self._lag_n()
        while True:
            i1 = self._next_grid
            if self._pending and self._pending[0][0] < i1:
                i1 = self._pending[0][0]
            if final:
                if self._i0 >= last:
                    break
                i1 = min(i1, last)
            elif i1 + lag_n > last:
                break
            self._monitor_to(min(i1 + lag_n, last) + 1)
            if (
                self._forced_losses
                and self._lost is None
                and self._t[i1 - self._base] >= self._forced_losses[0]
            ):
                self._forced_losses.pop(0)
                self.lose_track("forced")
            if self._lost is not None:
                self._lost_block(i1)
                continue
            n_rate = len(self._rate_nis)
            try:
                self._block(i1)
            except CovarianceError as exc:
                self.lose_track(str(exc))  # raises if the last start again was too recent
                # the failed block counts as lost: its rate update is the lost block's
                for series in (self._rate_nis, self._rate_nis_t, self._rate_nis_dof):
                    del series[n_rate:]
                self._lost_block(i1)

    def _count_held(self, g0: int, g1: int, excluded: int) -> tuple[np.ndarray, int]:
        """Count rows ``g0 .. g1 - 1`` (global) held for a bad channel not in ``excluded``
        (non-finite when one of those is, else saturated); returns the held rows (bool)
        and their number."""
        if g0 > self._last_bad:  # no bad channel in these rows (and none non-finite)
            return np.zeros(g1 - g0, dtype=np.bool_), 0
        b = self._base
        bad, n_bad, n_nonfinite, n_saturated = kernels.held_rows(
            self._chmask[g0 - b : g1 - b], self._nfmask[g0 - b : g1 - b], excluded
        )
        if n_nonfinite or n_saturated:
            self.counts["samples held (non-finite)"] += n_nonfinite
            self.counts["samples held (saturated)"] += n_saturated
        return bad, n_bad

    def _monitor_to(self, g_end: int) -> None:
        """Run the channels' health tests up to sample ``g_end`` (global, exclusive).

        They run a fusion lag ahead of the blocks, on what has arrived by then whatever the
        chunking (so a live link and a replay find the same faults at the same samples), and
        an isolated channel is excluded from its fault's onset where the blocks have not
        used it yet."""
        if g_end <= self._mon_n:
            return
        b = self._base
        rows = slice(self._mon_n - b, g_end - b)
        self.monitor.observe_samples(self._t[rows], self._raw[rows])
        self._mon_n = g_end
        for channel, onset_s in self.monitor.take_isolations():
            self._exclude_from(channel, onset_s)

    def _append(self, t_s, raw, a, nf_bits, bad_bits) -> None:
        """Append rows to the sample store (amortised growth; processed rows dropped)."""
        m = t_s.shape[0]
        used = self._n - self._base
        if used + m > self._t.shape[0]:
            # drop what the blocks no longer need (keep the last processed sample)
            drop = max(0, self._i0 - self._base) if self.started else 0
            keep = slice(drop, used)
            cap = max(4096, 2 * (used - drop + m))
            for name in ("_t", "_raw", "_ach", "_nfmask", "_chmask", "_excl"):
                old = getattr(self, name)
                new = np.empty((cap, *old.shape[1:]), dtype=old.dtype)
                new[: used - drop] = old[keep]
                setattr(self, name, new)
            self._base += drop
            used -= drop
        r = slice(used, used + m)
        self._t[r] = t_s
        self._raw[r] = raw
        self._ach[r] = a
        self._nfmask[r] = nf_bits
        self._chmask[r] = bad_bits
        marked = np.flatnonzero(bad_bits)
        if marked.shape[0]:
            self._last_bad = self._n + int(marked[-1])
        self._excl[r] = self._excluded
        self._n += m


def whole_fix(fix: tuple) -> bool:
    """A fix with every position and velocity component (what a start needs)."""
    return bool(np.isfinite(fix[1]).all() and np.isfinite(fix[2]).all())
