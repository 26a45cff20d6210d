"""The run's epochs, stacked as they are recorded (``Pipeline._record``).

Each epoch's position, NED velocity, attitude, rate and biases and its navigation
covariance (12 x 12) are written by :func:`filters.kernels.epoch_record` into a row of
columns that grow by doubling; the rest of the epoch (its time, bound, angle of attack,
faulty channels, validity) goes into a list. Stacking per-epoch arrays at the run's end
instead cost about 5 us an epoch (issue 56: the arrays lie scattered over the heap).
"""

from __future__ import annotations

import numpy as np

from filters.state import N_NAV
from ngnav.records import Estimates

#: The columns' first length (epochs); they double when full.
FIRST_EPOCHS = 1024
#: ``nav``'s columns before the biases: position, NED velocity, quaternion, rate.
_NAV = 13


class EpochStore:
    """The epochs so far: ``nav`` (E, 13 + nb) and ``cov`` (E, 12, 12) columns (their first
    :attr:`n` rows), ``rest`` one tuple ``(t_s, bound, aoa, aoa_sigma, faulty, valid)`` each,
    and ``p`` (n, n) the latest epoch's whole covariance.

    Parameters
    ----------
    n_bias : int
        The bias states (nb).
    n : int
        The error state's size.
    """

    def __init__(self, n_bias: int, n: int) -> None:
        self.n = 0
        self.nav = np.empty((FIRST_EPOCHS, _NAV + n_bias))
        self.cov = np.empty((FIRST_EPOCHS, N_NAV, N_NAV))
        self.rest: list[tuple] = []
        self.p = np.empty((n, n))

    def __len__(self) -> int:
        return self.n

    def next_row(self) -> int:
        """Take the next row of the columns (grown when full); returns its index, for the
        kernel to write. The caller appends the epoch's :attr:`rest`."""
        e = self.n
        if e == self.nav.shape[0]:
            self.nav = np.concatenate([self.nav, np.empty_like(self.nav)])
            self.cov = np.concatenate([self.cov, np.empty_like(self.cov)])
        self.n = e + 1
        return e

    def add_lost(self, t_s: float) -> None:
        """An empty epoch at ``t_s``: a lost track's, NaN and not valid (the fields the
        last epoch has none of stay None)."""
        _, bound, aoa, aoa_sigma, _, _ = self.rest[-1]
        nan = (None if bound is None else np.full((N_NAV, N_NAV), np.nan),)
        nan += tuple(None if v is None else np.nan for v in (aoa, aoa_sigma))
        e = self.next_row()
        self.rest.append((t_s, *nan, 0, False))
        self.nav[e] = np.nan
        self.cov[e] = np.nan

    def clear(self) -> None:
        """Forget the epochs (a run that keeps only the latest)."""
        self.n = 0
        self.rest.clear()

    def velocity(self, e: int) -> np.ndarray:
        """Epoch ``e``'s NED velocity (3,), a copy."""
        return self.nav[e, 3:6].copy()

    def estimates(self) -> Estimates:
        """The epochs as :class:`Estimates`."""
        if not self.n:
            raise ValueError("no estimates to stack")
        nav = self.nav[: self.n]
        t, *optional = zip(*self.rest, strict=True)  # bound, aoa, its sigma, faulty, valid
        return Estimates(
            np.array(t),
            nav[:, 0:3].copy(),
            nav[:, 3:6].copy(),
            nav[:, 6:10].copy(),
            nav[:, 10:13].copy(),
            nav[:, _NAV:].copy(),
            self.cov[: self.n].copy(),
            *[None if c[0] is None else np.array(c) for c in optional],
        )
