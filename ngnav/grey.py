"""GM(1,1) grey forecasting (paper section 3.2, standard form in SPEC section 3).

For a short positive sequence ``x0 = (x0(1) .. x0(n))``, ``n >= 4``:

1. accumulate ``x1(k) = sum_{i<=k} x0(i)``;
2. background values ``z1(k) = (x1(k) + x1(k-1)) / 2``, k = 2..n;
3. least squares of ``x0(k) = -a z1(k) + b`` (k = 2..n) for the development
   coefficient ``a`` and the grey input ``b``;
4. restore ``x0^(k+1) = (b - a x0(1)) * expm1(a)/a * exp(-a k)``, the exact
   difference of the time response ``x1^(k+1) = (x0(1) - b/a) e^{-ak} + b/a``,
   written so that it keeps full precision on nearly constant windows (where
   ``x1^(k+1) - x1^(k)`` cancels catastrophically) and has the limit ``b`` as
   ``a -> 0``.

Signed data (angular rates cross zero) are shifted by a constant before the
fit and shifted back afterwards; see :func:`auto_shift`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Shortest window GM(1,1) accepts: 3 equations for 2 unknowns.
MIN_WINDOW = 4
#: |a| above this marks a fit outside GM(1,1)'s valid range (Liu & Lin, Grey
#: Information, 2006: the model is meaningless for -a >= 2); forecasters fall
#: back to the last value there.
MAX_ABS_A = 2.0


def _expm1_over_x(a: np.ndarray) -> np.ndarray:
    """``expm1(a)/a`` with the limit 1 at a = 0, accurate for tiny a."""
    a = np.asarray(a, dtype=float)
    small = np.abs(a) < 1e-8
    safe = np.where(small, 1.0, a)
    return np.where(small, 1.0 + 0.5 * a, np.expm1(a) / safe)


def auto_shift(x0: np.ndarray, axis: int = -1) -> np.ndarray:
    """The default shift that makes a window positive for GM(1,1).

    A window whose minimum is positive is not shifted. Otherwise the shift puts
    the minimum one spread (max - min) above zero, so the shifted data lie in
    ``[s, 2 s]``; a constant non-positive window is shifted to 1.0. The shift is
    a constant over the window, removed again from every fitted and forecast
    value.

    Parameters
    ----------
    x0 : array (..., n)
        Windows, oldest first along ``axis``.

    Returns
    -------
    array (...)
        Shift per window, in the units of ``x0``.
    """
    lo = np.min(x0, axis=axis)
    spread = np.max(x0, axis=axis) - lo
    margin = np.where(spread > 0, spread, 1.0)
    return np.where(lo > 0, 0.0, margin - lo)


@dataclass(frozen=True)
class GreyFitQuality:
    """Textbook admissibility and accuracy measures of a GM(1,1) fit.

    Attributes
    ----------
    class_ratios : array (n-1,)
        ``sigma(k) = x0(k-1) / x0(k)`` of the (shifted) data, k = 2..n.
    ratio_admissible : bool
        All class ratios inside ``(exp(-2/(n+1)), exp(2/(n+1)))``.
    posterior_variance_ratio : float
        ``C = S2 / S1``: residual spread over data spread (0 for an exact fit
        of constant data, inf for a non-exact fit of constant data).
    small_error_probability : float
        ``P = share of k with |e(k) - mean(e)| < 0.6745 S1``.
    """

    class_ratios: np.ndarray
    ratio_admissible: bool
    posterior_variance_ratio: float
    small_error_probability: float

    @property
    def grade(self) -> str:
        """Accuracy grade from (C, P): good, qualified, barely, or unqualified."""
        c, p = self.posterior_variance_ratio, self.small_error_probability
        if p >= 0.95 and c <= 0.35:
            return "good"
        if p >= 0.80 and c <= 0.50:
            return "qualified"
        if p >= 0.70 and c <= 0.65:
            return "barely"
        return "unqualified"


class GreyModel11:
    """GM(1,1) grey model with scikit-learn conventions.

    Parameters
    ----------
    shift : "auto", float or None
        Constant added to the data before fitting and removed after.
        ``"auto"`` (default): :func:`auto_shift`, no shift for positive data.
        A float: that shift. None: no shift; non-positive data then raise.

    Attributes (after :meth:`fit`)
    ------------------------------
    a_ : float
        Development coefficient (the paper's m).
    b_ : float
        Grey input (the paper's u).
    shift_ : float
        The shift used.
    fitted_ : array (n,)
        Restored sequence in the units of ``x0``; ``fitted_[0] == x0[0]``.
    n_ : int
        Window length.

    Examples
    --------
    >>> m = GreyModel11().fit([27260, 29547, 32411, 35388])
    >>> round(m.a_, 6), round(float(m.forecast()[0]), 2)
    (-0.089995, 38713.4)
    """

    def __init__(self, shift: str | float | None = "auto") -> None:
        self.shift = shift

    def fit(self, x0: np.ndarray) -> GreyModel11:
        """Fit the model to a sequence (n,), n >= 4, oldest first. Returns self."""
        x = np.asarray(x0, dtype=float)
        if x.ndim != 1:
            raise ValueError(f"GM(1,1) fits a one-dimensional sequence, got shape {x.shape}")
        n = x.shape[0]
        if n < MIN_WINDOW:
            raise ValueError(f"GM(1,1) needs at least {MIN_WINDOW} values, got {n}")
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise ValueError(f"x0[{bad[0]}] is not finite ({x[bad[0]]})")
        if self.shift == "auto":
            c = float(auto_shift(x))
        elif self.shift is None:
            c = 0.0
            if np.any(x <= 0):
                raise ValueError(
                    "GM(1,1) needs positive data; x0 has values <= 0 (use shift='auto')"
                )
        else:
            c = float(self.shift)
            if not math.isfinite(c):
                raise ValueError(f"shift must be finite, got {self.shift}")
            if np.any(x + c <= 0):
                raise ValueError(f"shift {c} leaves values <= 0; use a larger shift or 'auto'")
        y = x + c
        x1 = np.cumsum(y)
        z = 0.5 * (x1[1:] + x1[:-1])
        design = np.column_stack([-z, np.ones(n - 1)])
        # Column scaling keeps lstsq well conditioned when |z| >> 1 (large shifts).
        scale = np.linalg.norm(design, axis=0)
        sol, *_ = np.linalg.lstsq(design / scale, y[1:], rcond=None)
        a, b = sol / scale
        self.a_ = float(a)
        self.b_ = float(b)
        self.shift_ = c
        self.n_ = n
        self._y1 = float(y[0])
        self._x0 = x.copy()
        k = np.arange(1, n)
        fitted = np.empty(n)
        fitted[0] = x[0]
        fitted[1:] = self._restore(k) - c
        self.fitted_ = fitted
        return self

    def _restore(self, k: np.ndarray) -> np.ndarray:
        a, b = self.a_, self.b_
        return (b - a * self._y1) * _expm1_over_x(a) * np.exp(-a * np.asarray(k, dtype=float))

    def _check_fitted(self) -> None:
        if not hasattr(self, "a_"):
            raise RuntimeError("this GreyModel11 is not fitted yet: call fit(x0) first")

    def forecast(self, steps: int = 1) -> np.ndarray:
        """The next ``steps`` values after the fitted window, shape (steps,)."""
        self._check_fitted()
        if int(steps) != steps or steps < 1:
            raise ValueError(f"steps must be a positive integer, got {steps}")
        k = np.arange(self.n_, self.n_ + int(steps))
        return self._restore(k) - self.shift_

    def quality(self) -> GreyFitQuality:
        """Class-ratio admissibility, posterior-variance ratio C and small-error probability P."""
        self._check_fitted()
        y = self._x0 + self.shift_
        n = self.n_
        ratios = y[:-1] / y[1:]
        lo, hi = math.exp(-2.0 / (n + 1)), math.exp(2.0 / (n + 1))
        admissible = bool(np.all((ratios > lo) & (ratios < hi)))
        e = self._x0 - self.fitted_
        s1 = float(np.std(self._x0))
        s2 = float(np.std(e))
        if s1 == 0.0:
            c = 0.0 if s2 == 0.0 else math.inf
            p = 1.0 if s2 == 0.0 else 0.0
        else:
            c = s2 / s1
            p = float(np.mean(np.abs(e - e.mean()) < 0.6745 * s1))
        return GreyFitQuality(ratios, admissible, c, p)


def one_step_forecast(
    windows: np.ndarray, shift: str | float | np.ndarray = "auto", axis: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised GM(1,1) one-step forecasts of many windows at once.

    The same model as :class:`GreyModel11`; the two-parameter least squares is
    solved in centred closed form (``a = -cov(z, x0) / var(z)``), which is what
    a QR solve of ``[-z, 1]`` reduces to and keeps full precision for large
    shifts.

    Parameters
    ----------
    windows : array (..., n)
        Windows, oldest first on the last axis, n >= 4, finite.
    shift : "auto", float or array (...)
        Shift per window (see :func:`auto_shift`).
    axis : {-1, 0}
        The window axis: -1 (default) for (..., n), 0 for (n, ...) such as a
        history block (n, C) of C channels.

    Returns
    -------
    forecast : array (...)
        ``x0^(n+1)`` in the units of the windows.
    fell_back : array (...) of bool
        Where the fit was unusable (``|a| > MAX_ABS_A`` or non-finite) and the
        last value was returned instead.
    """
    x = np.asarray(windows, dtype=float)
    if axis == 0:
        x_last = x.T
    elif axis == -1:
        x_last = x
    else:
        raise ValueError(f"axis must be -1 or 0, got {axis}")
    n = x_last.shape[-1]
    if n < MIN_WINDOW:
        raise ValueError(f"GM(1,1) needs windows of at least {MIN_WINDOW} values, got {n}")
    c = auto_shift(x_last) if isinstance(shift, str) else np.asarray(shift, dtype=float)
    ops = grey_operators(n)
    m = n - 1
    if axis == 0:  # (n, C): project along the first axis, results (2m+2, C)
        y = x + c
        proj = ops.T @ y
        dz, dy, zm, ym = proj[:m], proj[m : 2 * m], proj[2 * m], proj[2 * m + 1]
        y0 = y[0]
        red = 0
    else:
        y = x + c[..., None]
        proj = y @ ops  # (..., 2m + 2): centred z, centred Y, mean z, mean Y
        dz, dy = proj[..., :m], proj[..., m : 2 * m]
        zm, ym = proj[..., 2 * m], proj[..., 2 * m + 1]
        y0 = y[..., 0]
        red = -1
    var = np.sum(dz * dz, axis=red)
    cov = np.sum(dz * dy, axis=red)
    a = np.divide(-cov, var, out=np.zeros_like(var), where=var > 0)
    valid = np.abs(a) <= MAX_ABS_A  # also keeps exp() below from overflowing
    a_ok = np.where(valid, a, 0.0)
    b = ym + a_ok * zm
    f = (b - a_ok * y0) * _expm1_over_x(a_ok) * np.exp(-a_ok * n) - c
    fell_back = ~(valid & np.isfinite(f))
    return np.where(fell_back, x_last[..., -1], f), fell_back


_OPERATOR_CACHE: dict[int, np.ndarray] = {}


def grey_operators(n: int) -> np.ndarray:
    """Linear operator (n, 2(n-1)+2) mapping a window to centred z, centred Y, mean z, mean Y."""
    ops = _OPERATOR_CACHE.get(n)
    if ops is None:
        lower = np.tril(np.ones((n, n)))
        mz = 0.5 * (lower[1:] + lower[:-1])  # z1(k), k = 2..n
        my = np.eye(n)[1:]  # x0(k), k = 2..n
        centre = np.eye(n - 1) - 1.0 / (n - 1)
        ops = np.hstack(
            [(centre @ mz).T, (centre @ my).T, mz.mean(axis=0)[:, None], my.mean(axis=0)[:, None]]
        )
        ops.setflags(write=False)
        _OPERATOR_CACHE[n] = ops
    return ops
