"""Channel health: a failed accelerometer detected and isolated (issue 55).

Three tests, each for the faults it sees best:

- **Flat line** (dead, stuck, saturated): a working channel's noise makes two
  consecutive readings equal only when both fall in one quantisation step; with the
  step no larger than the noise that happens less than 28 % of the time, so
  :data:`FLAT_RUN` identical readings in a row (probability below 1e-13) say the
  channel has stopped. Reading exactly 0 is ``dead``, the full-scale rail
  ``saturated``, any other value ``stuck``. Isolated at once: the run is the
  channel's own.
- **Noise level** (noisy): the second differences of a channel's samples remove
  its motion (a jerk of 100 m/s^3 moves them by 1e-4 m/s^2 at 1 kHz) and leave
  ``6 sigma^2`` of white noise. Over :data:`NOISE_WINDOW` samples the median of their
  squares (a shock of a few samples does not move it) above :data:`NOISY_RATIO` times
  its expected value is a noisy channel; isolated at once.
- **Parity** (drift, and any offset): given the filter's rate the rate products are
  predicted, so the nine outputs over-determine the six other unknowns; the three
  parity directions are the rate measurement's innovation ``r`` (its covariance
  ``S`` holds the rate's and the biases' uncertainty). An offset ``d`` on channel
  ``i`` moves ``r`` by ``s_i d``, ``s_i`` the channel's column of the solve's rate
  rows. A one-sided CUSUM per channel group and sign on the normalised projection
  ``s_i' S^-1 r / sqrt(s_i' S^-1 s_i)`` alarms at :data:`CUSUM_H`; the group with
  the largest statistic is named. Channels whose signatures are parallel form one
  group (on the nine-cube {2, 5}, {3, 8}, {6, 9}: each pair alone carries one
  angular acceleration): an offset there is detected but the parity cannot say
  which of the two it is. A parity offset does not heal by itself: the group stays
  marked for the rest of the run, and the parity raises no second event while it
  holds the first.

Every fault becomes one :class:`ngnav.records.FaultEvent` (the candidate channels,
the kind, when detected, when isolated); a parity alarm on a group is isolated
later if a sample test names one of its channels.
"""

from __future__ import annotations

import warnings

import numpy as np

from filters import kernels
from ngnav.records import FaultEvent

#: Identical consecutive readings that make a flat line (probability < 1e-13 per run
#: for a working channel whose quantisation step is at most its noise).
FLAT_RUN = 25
#: Samples per noise-level window (0.1 s at 1 kHz, 1 s at 100 Hz).
NOISE_WINDOW = 100
#: The window's median square second difference over its expected value that makes a
#: noisy channel: the noise's variance ten times its configuration (its sigma 3.2
#: times). Measured on white noise: ``python -m filters.faults`` prints the largest
#: ratio over a million windows.
NOISY_RATIO = 10.0
#: The median of a chi-square variable with one degree of freedom.
_CHI2_1_MEDIAN = 0.454936423119572
#: The CUSUM's allowance: half a standard deviation of the normalised projection per
#: block (it accumulates offsets larger than that).
CUSUM_K = 0.5
#: The CUSUM's alarm threshold. For unit-variance Gaussian projections Siegmund's
#: approximation puts the mean run between false alarms at 3e9 blocks per statistic
#: (8000 hours at 100 Hz, over 12 statistics 700 hours); measured fault-free flight
#: hours and alarms: ``ngnav faults`` (docs/design.md, "Channel faults").
CUSUM_H = 20.0
#: Signatures closer than this in the innovation's metric (|cos|) share a group.
_PARALLEL_COS = 0.999


def signature_groups(signatures: np.ndarray) -> list[tuple[int, ...]]:
    """Channels (0-based) grouped by parallel parity signature (columns of (nq, N))."""
    s = np.asarray(signatures, dtype=float)
    norms = np.linalg.norm(s, axis=0)
    groups: list[list[int]] = []
    for i in range(s.shape[1]):
        if norms[i] == 0.0:
            continue  # a channel the parity does not see
        for g in groups:
            j = g[0]
            if abs(s[:, i] @ s[:, j]) >= _PARALLEL_COS * norms[i] * norms[j]:
                g.append(i)
                break
        else:
            groups.append([i])
    return [tuple(g) for g in groups]


#: A signature nearer than this to the plane of two others (the sine of its angle from it)
#: lies in it: the same 2.6 deg as :data:`_PARALLEL_COS`.
_COPLANAR_SIN = float(np.sqrt(1.0 - _PARALLEL_COS**2))


def pair_isolability(signatures: np.ndarray) -> dict[tuple[int, int], str]:
    """What the parity can tell of two channels (0-based, ``i < j``) that fail together.

    Two offsets move the innovation in the plane of their signatures (columns of (nq, N));
    the parity can name the pair only if no other group's signature lies in that plane.
    Each pair's verdict: ``"isolable"``; ``"one group"`` (parallel signatures: one
    direction, as for one channel of the group); ``"ambiguous"`` (a third group's
    signature lies in their plane: that group with either one moves the innovation the
    same way); ``"unseen"`` (a channel with no signature). Offsets in one direction that
    grow alike are told apart by no test on the innovation alone.
    """
    s = np.asarray(signatures, dtype=float)
    groups = signature_groups(s)
    group_of = {c: g for g, grp in enumerate(groups) for c in grp}
    unit = [s[:, grp[0]] / np.linalg.norm(s[:, grp[0]]) for grp in groups]
    out: dict[tuple[int, int], str] = {}
    for i in range(s.shape[1]):
        for j in range(i + 1, s.shape[1]):
            gi, gj = group_of.get(i), group_of.get(j)
            if gi is None or gj is None:
                out[(i, j)] = "unseen"
            elif gi == gj:
                out[(i, j)] = "one group"
            else:
                plane = np.column_stack([unit[gi], unit[gj]])
                verdict = "isolable"
                for g, u in enumerate(unit):
                    if g in (gi, gj):
                        continue
                    coef, *_ = np.linalg.lstsq(plane, u, rcond=None)
                    if np.linalg.norm(u - plane @ coef) <= _COPLANAR_SIN:
                        verdict = "ambiguous"
                        break
                out[(i, j)] = verdict
    return out


class ChannelMonitor:
    """The three health tests over one array's channels, and the events they raise.

    Parameters
    ----------
    noise_sigma_mps2 : array (N,)
        Each channel's white noise per sample, m/s^2 (the run's configuration).
    range_mps2 : float
        Full scale, m/s^2 (a flat line there is ``saturated``).
    signatures : array (nq, N)
        Each channel's effect on the rate-product innovation per m/s^2 of offset (the
        solve matrix's rate rows).
    """

    def __init__(
        self, noise_sigma_mps2: np.ndarray, range_mps2: float, signatures: np.ndarray
    ) -> None:
        sigma = np.asarray(noise_sigma_mps2, dtype=float).reshape(-1)
        n = sigma.shape[0]
        self.n_channels = n
        self.range_mps2 = float(range_mps2)
        # the median of a squared N(0, 6 sigma^2) second difference
        self._d2_median = 6.0 * sigma * sigma * _CHI2_1_MEDIAN
        self._parity_channels: set[int] = set()  # channels a parity alarm has named
        self.set_signatures(signatures)
        # carried sample state: the last two readings, the flat run's length
        self._prev = np.full((2, n), np.nan)
        self._run = np.zeros(n, dtype=np.int64)  # repeats of the last reading so far
        self._win = np.empty((NOISE_WINDOW, n))
        self._win_n = 0
        self._flat = np.zeros(n, dtype=bool)
        self._rises = np.empty((n, 2), np.int64)  # kernels.flat_line_runs's output, grown
        self._noisy = np.zeros(n, dtype=bool)
        self._t_last = np.nan  # the last sample's time, s
        #: Every fault found, in the order found.
        self.events: list[FaultEvent] = []
        self._open: dict[int, int] = {}  # channel -> index of its event
        self._isolations: list[tuple[int, float]] = []
        self._ambiguous: list[tuple[tuple[int, ...], float]] = []

    def set_signatures(self, signatures: np.ndarray) -> None:
        """Each channel's effect on the rate-product innovation (nq, N), per m/s^2: the
        solve's rate rows (again after channels are excluded, with their columns zero).
        The parity CUSUMs start again; a parity alarm already raised stays."""
        self._sig = np.asarray(signatures, dtype=float).reshape(-1, self.n_channels)
        self.groups = signature_groups(self._sig)
        g = np.array([self._sig[:, grp[0]] for grp in self.groups], dtype=float)
        self._g_sig = g.reshape(len(self.groups), self._sig.shape[0])
        self._cusum = np.zeros((len(self.groups), 2))  # (group, sign)
        held = self._parity_channels
        self._parity = np.array([bool(held & set(grp)) for grp in self.groups], dtype=bool)

    def take_ambiguous(self) -> list[tuple[tuple[int, ...], float]]:
        """Parity alarms on a group of channels (0-based) since the last call, with their
        times: one of them is faulty, the parity cannot say which."""
        out, self._ambiguous = self._ambiguous, []
        return out

    def isolate(self, channel: int, t_s: float) -> None:
        """Name ``channel`` (0-based) of an open parity alarm: isolated by another
        test (the filter's estimate of its offset, :mod:`filters.exclusion`)."""
        self._isolate(channel, "drift", t_s, t_s)

    def take_isolations(self) -> list[tuple[int, float]]:
        """Channels (0-based) isolated since the last call, each with the time its fault
        began as the test sees it (s): a flat line's first reading, a noisy window's
        first sample, a parity alarm's block."""
        out, self._isolations = self._isolations, []
        return out

    # ----------------------------------------------------------------- state
    @property
    def faulty_mask(self) -> int:
        """Bit ``i`` set: channel ``i + 1`` fails a test now (flat, noisy or its parity)."""
        bad = self._flat | self._noisy
        bad[list(self._parity_channels)] = True
        return sum(1 << int(i) for i in np.flatnonzero(bad))

    # ---------------------------------------------------------------- samples
    def observe_samples(self, t_s: np.ndarray, raw_mps2: np.ndarray) -> None:
        """Run the flat-line and noise tests over consecutive samples (K,), (K, N)."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        k = t.shape[0]
        if k == 0:
            return
        a = np.asarray(raw_mps2, dtype=float).reshape(k, self.n_channels)
        t_before = self._t_last
        self._t_last = float(t[-1])
        # -- flat line: repeats of the previous reading, all channels (each rise of the
        # flat flag is an alarm; the first one opens the event); and the second
        # differences for the noise level, straight into its window when they fit
        w0 = self._win_n
        direct = w0 + k <= NOISE_WINDOW
        d2 = self._win[w0 : w0 + k] if direct else np.empty((k, self.n_channels))
        if self._rises.shape[0] < k * self.n_channels:
            self._rises = np.empty((k * self.n_channels, 2), np.int64)
        m = kernels.flat_line_runs(self._prev, a, self._run, self._flat, FLAT_RUN, d2, self._rises)
        if m:
            for kh, c in self._rises[:m].tolist():  # by channel, then time
                value = a[kh, c]
                if value == 0.0:
                    kind = "dead"
                elif abs(value) >= self.range_mps2 * (1 - 1e-9):
                    kind = "saturated"
                else:
                    kind = "stuck"
                onset = float(t[kh]) - (FLAT_RUN - 1) * _interval(t, t_before)
                self._isolate(c, kind, float(t[kh]), onset)
        # -- noise level: the median square of second differences over whole windows
        if direct:
            self._win_n = w0 + k
            if self._win_n == NOISE_WINDOW:
                self._win_n = 0
                self._noise_window(float(t[k - 1]), t, t_before)
            return
        k0 = 0
        while k0 < k:
            k1 = min(k, k0 + NOISE_WINDOW - self._win_n)
            self._win[self._win_n : self._win_n + k1 - k0] = d2[k0:k1]
            self._win_n += k1 - k0
            k0 = k1
            if self._win_n < NOISE_WINDOW:
                break
            self._win_n = 0
            self._noise_window(float(t[k1 - 1]), t, t_before)

    def _noise_window(self, t_end: float, t: np.ndarray, t_before: float) -> None:
        """The noise-level test on a whole window ending at ``t_end`` (s), in the samples
        ``t`` (K,) observed after the one at ``t_before`` (s; their interval dates an
        onset, :func:`_interval`)."""
        if np.isnan(self._win).any():
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN channel
                ratio = np.nanmedian(self._win * self._win, axis=0) / self._d2_median
        else:  # the same value, compiled
            ratio = kernels.column_median_squares(self._win) / self._d2_median
        noisy = ratio > NOISY_RATIO
        for c in np.flatnonzero(noisy & ~self._noisy).tolist():
            onset = t_end - (NOISE_WINDOW - 1) * _interval(t, t_before)
            self._isolate(c, "noisy", t_end, onset)
        self._noisy = noisy

    # ----------------------------------------------------------------- parity
    def observe_parity(self, t_s: float, innovation: np.ndarray, cov: np.ndarray) -> None:
        """Run the parity CUSUM on one rate-product innovation (nq,) and its covariance."""
        if not self.groups:
            return
        c = self._cusum
        # an offset on one channel moves every group whose signature is not orthogonal
        # to its own, its own the fastest (Cauchy-Schwarz in the S^-1 metric): the
        # largest statistic names the group, and the CUSUMs start again
        try:
            gi = kernels.parity_cusum(
                np.asarray(innovation, dtype=float), cov, self._g_sig, c, CUSUM_K, CUSUM_H
            )
        except np.linalg.LinAlgError:
            return
        if gi < 0:
            return
        c[:] = 0.0
        if not self._parity.any():
            self._parity[gi] = True
            self._parity_channels |= set(self.groups[gi])
            self._detect(self.groups[gi], float(t_s))

    # ----------------------------------------------------------------- events
    def _detect(self, channels: tuple[int, ...], t_s: float) -> None:
        """A parity alarm on a group: one event, isolated if the group is one channel."""
        if any(c in self._open for c in channels):
            return
        iso = t_s if len(channels) == 1 else float("nan")
        ev = FaultEvent(tuple(c + 1 for c in channels), "drift", t_s, iso)
        self.events.append(ev)
        for c in channels:
            self._open[c] = len(self.events) - 1
        if len(channels) == 1:
            self._isolations.append((channels[0], t_s))
        else:
            self._ambiguous.append((tuple(channels), t_s))

    def _isolate(self, channel: int, kind: str, t_s: float, onset_s: float) -> None:
        """A sample test names a channel: isolate its open event, or a new one."""
        self._isolations.append((channel, onset_s))
        idx = self._open.get(channel)
        if idx is not None:
            ev = self.events[idx]
            if not np.isnan(ev.isolated_at_s) and ev.kind == kind:
                return
            self.events[idx] = FaultEvent(
                (channel + 1,),
                kind,
                ev.detected_at_s,
                t_s if np.isnan(ev.isolated_at_s) else ev.isolated_at_s,
            )
            for c in [x - 1 for x in ev.channels if x - 1 != channel]:
                self._open.pop(c, None)
                self._parity_channels.discard(c)
            return
        self.events.append(FaultEvent((channel + 1,), kind, t_s, t_s))
        self._open[channel] = len(self.events) - 1


def _interval(t: np.ndarray, t_before: float) -> float:
    """The sample interval, s, of the samples ``t`` (K,) observed after the one at
    ``t_before`` (NaN: none); read only to date a fault's onset."""
    if t.shape[0] > 1:
        return _median(np.diff(t))
    return float(t[0] - t_before) if np.isfinite(t_before) else 0.0


def _median(x: np.ndarray) -> float:
    """``np.median`` of a short 1-D array without its general machinery (same value)."""
    n = x.shape[0]
    y = np.sort(x)
    h = n // 2
    return float(y[h]) if n % 2 else float((y[h - 1] + y[h]) / 2.0)
