"""The epoch store: the stacked estimates are the epochs' values, as ``Estimates.from_rows``
stacks them, across the columns' growth, a lost track's empty epoch and a cleared store."""

from __future__ import annotations

import numpy as np

from filters import kernels
from filters.epochs import CHUNK_EPOCHS, EpochStore
from filters.pipeline import _NO_AOA
from filters.state import N_NAV
from ngnav.records import Estimates


def _record(store: EpochStore, rng: np.random.Generator, t_s: float, n: int, nb: int) -> tuple:
    """One epoch (NED velocity error: the record's velocity and covariance are the state's),
    through the kernel as ``Pipeline._record`` writes it; returns it as a row."""
    a = rng.normal(size=(n, n))
    p = a @ a.T
    pos, vel, q, w, bias = (rng.normal(size=m) for m in (3, 3, 4, 3, nb))
    e = store.next_row()
    kernels.epoch_record(
        p, vel, False, 0.0, pos, q, w, bias, store.nav, store.cov, e, store.p, _NO_AOA
    )
    rest = (t_s, None, float(rng.normal()), float(rng.random()), e % 3, True)
    store.rest.append(rest)
    np.testing.assert_array_equal(store.p, p)
    return (t_s, pos, vel, q, w, bias, p[:N_NAV, :N_NAV].copy(), *rest[1:])


def _assert_same(a: Estimates, b: Estimates) -> None:
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)


def test_store_stacks_the_epochs_as_the_rows_do():
    rng = np.random.default_rng(0)
    n, nb = 20, 9
    store = EpochStore(nb, n)
    rows = [_record(store, rng, 0.01 * i, n, nb) for i in range(CHUNK_EPOCHS + 5)]
    store.add_lost(99.0)
    nan_like = [np.full(np.shape(v), np.nan) for v in rows[-1][1:7]]  # position to covariance
    rows.append((99.0, *nan_like, None, np.nan, np.nan, 0, False))  # no bound; not valid
    assert len(store) == CHUNK_EPOCHS + 6
    _assert_same(store.estimates(), Estimates.from_rows(rows))
    store.clear()
    rows = [_record(store, rng, 1.0, n, nb)]
    _assert_same(store.estimates(), Estimates.from_rows(rows))
