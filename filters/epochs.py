"""The run's epochs, stacked as they are recorded (``Pipeline._record``).

Each epoch's position, NED velocity, attitude, rate and biases and its navigation
covariance (12 x 12) are written by :func:`filters.kernels.epoch_record` into a row of
columns kept in chunks of :data:`CHUNK_EPOCHS` rows (a full chunk stays as it is and a new
one starts: no copy while the run grows); the rest of the epoch (its time, bound, angle of
attack, faulty channels, validity) goes into a list. Stacking per-epoch arrays at the run's
end instead cost about 5 us an epoch (issue 56: the arrays lie scattered over the heap), and
so did columns that doubled when full (their copies).
"""

from __future__ import annotations

import numpy as np

from filters.state import N_NAV
from ngnav.records import Estimates

#: Rows (epochs) in a chunk of the columns.
CHUNK_EPOCHS = 4096
#: ``nav``'s columns before the biases: position, NED velocity, quaternion, rate.
_NAV = 13


class EpochStore:
    """The epochs so far: the current chunk's ``nav`` (C, 13 + nb) and ``cov`` (C, 12, 12)
    columns (their first :attr:`i` rows written) after the full chunks, ``rest`` one tuple
    ``(t_s, bound, aoa, aoa_sigma, faulty, valid)`` an epoch, and ``p`` (n, n) the latest
    epoch's whole covariance.

    Parameters
    ----------
    n_bias : int
        The bias states (nb).
    n : int
        The error state's size.
    """

    def __init__(self, n_bias: int, n: int) -> None:
        self._width = _NAV + n_bias
        self._full: list[tuple[np.ndarray, np.ndarray]] = []
        self._new_chunk()
        self.i = 0
        self.rest: list[tuple] = []
        self.p = np.empty((n, n))

    def _new_chunk(self) -> None:
        self.nav = np.empty((CHUNK_EPOCHS, self._width))
        self.cov = np.empty((CHUNK_EPOCHS, N_NAV, N_NAV))

    def __len__(self) -> int:
        return len(self._full) * CHUNK_EPOCHS + self.i

    def next_row(self) -> int:
        """Take the next row of the current chunk (a new chunk when it is full); returns its
        index in :attr:`nav` and :attr:`cov`, for the kernel to write. The caller appends
        the epoch's :attr:`rest`."""
        i = self.i
        if i == CHUNK_EPOCHS:
            self._full.append((self.nav, self.cov))
            self._new_chunk()
            i = 0
        self.i = i + 1
        return i

    def add_lost(self, t_s: float) -> None:
        """An empty epoch at ``t_s``: a lost track's, NaN and not valid (the fields the
        last epoch has none of stay None)."""
        _, bound, aoa, aoa_sigma, _, _ = self.rest[-1]
        nan = (None if bound is None else np.full((N_NAV, N_NAV), np.nan),)
        nan += tuple(None if v is None else np.nan for v in (aoa, aoa_sigma))
        i = self.next_row()
        self.rest.append((t_s, *nan, 0, False))
        self.nav[i] = np.nan
        self.cov[i] = np.nan

    def clear(self) -> None:
        """Forget the epochs (a run that keeps only the latest)."""
        self._full.clear()
        self.i = 0
        self.rest.clear()

    def estimates(self) -> Estimates:
        """The epochs as :class:`Estimates`."""
        if not self.rest:
            raise ValueError("no estimates to stack")
        nav = np.concatenate([c[0] for c in self._full] + [self.nav[: self.i]])
        cov = np.concatenate([c[1] for c in self._full] + [self.cov[: self.i]])
        t, *optional = zip(*self.rest, strict=True)  # bound, aoa, its sigma, faulty, valid
        return Estimates(
            np.array(t),
            nav[:, 0:3].copy(),
            nav[:, 3:6].copy(),
            nav[:, 6:10].copy(),
            nav[:, 10:13].copy(),
            nav[:, _NAV:].copy(),
            cov,
            *[None if c[0] is None else np.array(c) for c in optional],
        )
