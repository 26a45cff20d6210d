"""One-step-ahead predictors for the compensation loop (paper section 3.2).

Each predictor forecasts the next value of C channels from the last ``window``
values, ``forecast(history, j) -> (values (C,), n_fallbacks)``, history of
shape (window, C), oldest first; ``j`` is the index of the sample being
predicted (only the oracle uses it). The same loop runs each of them, so the
comparison between GM(1,1) and simpler predictors is like for like.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from ngnav.grey import MAX_ABS_A, MIN_WINDOW, grey_operators, one_step_forecast


@dataclass(frozen=True)
class LastValuePredictor:
    """Forecast = the last value (zero-order hold)."""

    name: str = "last"
    window: int = 1

    def forecast(self, history: np.ndarray, j: int) -> tuple[np.ndarray, int]:
        return history[-1], 0


@dataclass(frozen=True)
class LinePredictor:
    """Least-squares straight line over the window, extrapolated one step."""

    window: int = 5
    name: str = "line"
    _weights: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.window < 2:
            raise ValueError(f"a line needs a window of at least 2, got {self.window}")
        k = np.arange(self.window, dtype=float)
        design = np.column_stack([np.ones_like(k), k])
        weights = np.array([1.0, float(self.window)]) @ np.linalg.pinv(design)
        weights.setflags(write=False)
        object.__setattr__(self, "_weights", weights)

    def forecast(self, history: np.ndarray, j: int) -> tuple[np.ndarray, int]:
        return self._weights @ history, 0


@dataclass(frozen=True)
class GreyPredictor:
    """GM(1,1) one-step forecast per channel (see :func:`ngnav.grey.one_step_forecast`).

    Parameters
    ----------
    window : int
        Window length n >= 4.
    shift : "auto" or array (C,)
        ``"auto"``: per-window shift of :func:`ngnav.grey.auto_shift`. An array:
        a fixed shift per channel (must keep the data positive).
    """

    window: int = 5
    shift: str | np.ndarray = "auto"
    name: str = "gm11"

    def __post_init__(self) -> None:
        if self.window < MIN_WINDOW:
            raise ValueError(f"GM(1,1) needs a window of at least {MIN_WINDOW}, got {self.window}")
        ops = np.ascontiguousarray(grey_operators(self.window).T)  # (2m + 2, n)
        object.__setattr__(self, "_ops", ops)
        if not isinstance(self.shift, str):
            shift = np.array(self.shift, dtype=float)
            shift.setflags(write=False)
            object.__setattr__(self, "shift", shift)

    def forecast(self, history: np.ndarray, j: int) -> tuple[np.ndarray, int]:
        """GM(1,1) forecast of each column of ``history`` (n, C).

        A lean path for a fixed shift computes the same formula as
        :func:`ngnav.grey.one_step_forecast` with fewer array operations; any
        window it cannot take (zero variance, a = 0, |a| > MAX_ABS_A) goes to
        that function, which handles it.
        """
        c = self.shift
        if isinstance(c, str):
            values, fell_back = one_step_forecast(history, c, axis=0)
            return values, int(np.count_nonzero(fell_back))
        f, ok = _gm11_forecast(history, self._ops, c, MAX_ABS_A)
        if ok:
            return f, 0
        values, fell_back = one_step_forecast(history, c, axis=0)
        return values, int(np.count_nonzero(fell_back))


@dataclass(frozen=True)
class OraclePredictor:
    """The true value at the predicted sample (simulation only).

    Parameters
    ----------
    truth : array (T, C)
        True channel values at every sample of the run.
    """

    truth: np.ndarray
    name: str = "oracle"
    window: int = 1

    def forecast(self, history: np.ndarray, j: int) -> tuple[np.ndarray, int]:
        return self.truth[j], 0


def noise_gain(predictor, history: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """How much of the history's white noise the one-step forecast carries.

    ``sum_r (d forecast_c / d history_rc)^2`` per channel (C,), by central
    differences at ``history`` (window, C): the forecast's variance over the
    variance of one history row, for independent rows of equal variance.
    1 for the last value; ``1/n + (n + 1)^2 / 4 / S_xx`` = 1.1 for a line
    through 5 points; about 1.5 for GM(1,1) over 5 points (its exponential
    follows the newest points more). A fallback forecast (non-finite) gives
    NaN there.

    Parameters
    ----------
    predictor
        Any predictor of this module (``forecast(history, j)``).
    history : array (window, C)
        Where to linearise: the forecast of a nonlinear predictor (GM(1,1))
        depends on the values, so take a history like the one it will see.
    step : float
        Central-difference step, in the channels' units.
    """
    h0 = np.array(history, dtype=float)
    if h0.ndim != 2 or h0.shape[0] < 1:
        raise ValueError(f"history must be (window, C), got shape {h0.shape}")
    gain = np.zeros(h0.shape[1])
    for r in range(h0.shape[0]):
        up, down = h0.copy(), h0.copy()
        up[r] += step
        down[r] -= step
        d = (predictor.forecast(up, 0)[0] - predictor.forecast(down, 0)[0]) / (2.0 * step)
        gain += d * d
    return gain


@njit(cache=True)
def _gm11_forecast(history: np.ndarray, ops: np.ndarray, c: np.ndarray, max_abs_a: float):
    """GM(1,1)'s one-step forecast (C,) of each column of ``history`` (n, C), shifted by
    ``c`` (C,), from its window operators ``ops`` (2m + 2, n: centred z, centred Y, mean z,
    mean Y; m = n - 1); and False where a window needs the general path (zero variance,
    a = 0, |a| > ``max_abs_a``)."""
    y = history + c
    p = ops @ y
    n, nc = y.shape
    m = n - 1
    f = np.empty(nc)
    for j in range(nc):
        var = 0.0
        cov = 0.0
        for i in range(m):
            var += p[i, j] * p[i, j]
            cov += p[m + i, j] * p[i, j]
        if var == 0.0:
            return f, False
        a = -(cov / var)
        if a == 0.0 or abs(a) > max_abs_a:
            return f, False
        f[j] = (p[2 * m + 1, j] + a * (p[2 * m, j] - y[0, j])) * (np.expm1(a) / a)
        f[j] *= np.exp(-n * a)
        f[j] -= c[j]
    return f, True
