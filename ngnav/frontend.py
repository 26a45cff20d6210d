"""Inverse of the array output model: kinematics from accelerometer outputs.

:class:`ArraySolver` solves, by weighted least squares on the design matrix of
:mod:`ngnav.layout`, for angular acceleration, specific force and whichever
quadratic rate terms the layout excites and can solve alongside them (the most
strongly excited first). The terms it cannot (all of them on a six-sensor layout, an
as-built nine-cube's faint rate squares) are *rate-aided*: computed from a rate
supplied by the caller. A layout that
cannot determine angular acceleration and specific force is refused with an
error that names the unobservable direction.

:func:`nine_cube_closed_form` is the paper's eq. 26 for the nine-sensor cube.
"""

from __future__ import annotations

import numpy as np

from ngnav.layout import (
    FEATURE_NAMES,
    N_FEATURES,
    OMEGA_DOT,
    RATE_PRODUCTS,
    RATE_SQUARES,
    SPECIFIC_FORCE,
    ArrayLayout,
    rate_quadratics,
)
from ngnav.records import ArrayKinematics

_LINEAR = np.arange(6)
_QUADRATIC = np.arange(6, N_FEATURES)


def _describe_direction(v: np.ndarray, names: list[str]) -> str:
    v = v / np.max(np.abs(v))
    terms = [f"{c:+.2f}*{n}" for c, n in zip(v, names, strict=True) if abs(c) > 0.05]
    return " ".join(terms)


def _rank_check(h: np.ndarray, names: list[str], rtol: float = 1e-9) -> str | None:
    """Return a description of an unobservable direction of ``h``, or None if full rank."""
    _u, s, vt = np.linalg.svd(h, full_matrices=True)
    smax = s[0] if s.size else 0.0
    rank = int(np.sum(s > rtol * max(smax, 1e-300)))
    if rank == h.shape[1]:
        return None
    return _describe_direction(vt[rank], names)


class ArraySolver:
    """Least-squares solver for body kinematics from one array layout.

    Parameters
    ----------
    layout : ArrayLayout
        The nominal geometry to invert.
    noise_sigma_mps2 : float or array (N,), optional
        White-noise standard deviation of each channel, m/s^2; sets the weights
        of the least squares and the covariance reported by
        :meth:`covariance`. Default: equal weights, unit sigma.

    Attributes
    ----------
    solved_features : tuple of str
        Names of the features solved from the outputs (see
        :data:`ngnav.layout.FEATURE_NAMES`).
    rate_aided : bool
        True when the layout excites quadratic rate terms it cannot solve with the
        others (the solved set takes the most strongly excited that it can): then
        :meth:`solve` needs ``omega_b_rps``.

    Raises
    ------
    ValueError
        If angular acceleration and specific force are not all observable; the
        message names the missing direction.
    """

    def __init__(self, layout: ArrayLayout, noise_sigma_mps2: float | np.ndarray = 1.0) -> None:
        self.layout = layout
        g = layout.design
        n = layout.n_sensors
        sigma = np.broadcast_to(np.asarray(noise_sigma_mps2, dtype=float), (n,)).copy()
        if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise ValueError("noise_sigma_mps2 must be positive and finite for every channel")
        self.noise_sigma_mps2 = sigma
        scale = max(np.max(np.abs(g[:, _QUADRATIC])), 1e-300) if n else 1.0
        excited = _QUADRATIC[np.max(np.abs(g[:, _QUADRATIC]), axis=0) > 1e-12 * scale]
        lin_names = [FEATURE_NAMES[i] for i in _LINEAR]
        missing = _rank_check(g[:, _LINEAR], lin_names)
        if missing is not None:
            raise ValueError(
                f"layout {layout.name!r} ({n} sensors) cannot observe angular acceleration and "
                f"specific force: no output responds to the direction {missing}"
            )
        # the rate terms the outputs solve with the linear ones, strongest first; the rest
        # (e.g. an as-built cube's faint rate squares) are computed from a rate (aided)
        strength = np.linalg.norm(g[:, excited] / sigma[:, None], axis=0)
        cols, aided = list(_LINEAR), []
        for c in excited[np.argsort(-strength, kind="stable")]:
            trial = sorted([*cols, int(c)])
            if _rank_check(g[:, trial], [FEATURE_NAMES[i] for i in trial]) is None:
                cols = trial
            else:
                aided.append(int(c))
        self._cols = np.array(cols, dtype=int)
        self._aided_cols = np.array(sorted(aided), dtype=int)
        self.rate_aided = self._aided_cols.size > 0
        self.solved_features = tuple(FEATURE_NAMES[i] for i in self._cols)
        h = g[:, self._cols]
        w = 1.0 / sigma
        hw = h * w[:, None]
        # Solution operator: x = S @ A, via a pseudo-inverse of the whitened matrix (SVD).
        self._solve_matrix = np.linalg.pinv(hw) * w[None, :]
        self._info = hw.T @ hw
        self._aided_design = g[:, self._aided_cols]

    @property
    def solved_columns(self) -> np.ndarray:
        """Feature indices (k,) solved from the outputs, in the order of :attr:`solve_matrix`."""
        return self._cols.copy()

    @property
    def aided_columns(self) -> np.ndarray:
        """Quadratic feature indices computed from a supplied rate (empty unless rate-aided)."""
        return self._aided_cols.copy()

    @property
    def solve_matrix(self) -> np.ndarray:
        """Operator S (k, N) with ``x = S @ A`` for the solved features (read-only copy)."""
        return self._solve_matrix.copy()

    def covariance(self) -> np.ndarray:
        """Cramer-Rao covariance ``(H^T R^-1 H)^-1`` (k, k) of the solved features."""
        return np.linalg.inv(self._info)

    def solve_features(
        self, accel_mps2: np.ndarray, omega_b_rps: np.ndarray | None = None
    ) -> np.ndarray:
        """Solved features phi (..., 12) from outputs (..., N); unsolved columns are NaN.

        Parameters
        ----------
        accel_mps2 : array (..., N)
            Sensor outputs, m/s^2.
        omega_b_rps : array (..., 3), optional
            Body rate, rad/s. Required when :attr:`rate_aided`; then the
            quadratic terms are computed from it and reported in phi.
        """
        a = np.asarray(accel_mps2, dtype=float)
        n = self.layout.n_sensors
        if a.shape[-1] != n:
            raise ValueError(
                f"layout {self.layout.name!r} has {n} channels, the samples have {a.shape[-1]}"
            )
        phi = np.full((*a.shape[:-1], N_FEATURES), np.nan)
        if self.rate_aided:
            if omega_b_rps is None:
                raise ValueError(
                    f"layout {self.layout.name!r} excites rate terms "
                    f"{[FEATURE_NAMES[i] for i in self._aided_cols]} that its outputs cannot "
                    "separate from angular acceleration: pass omega_b_rps (rate-aided solve)"
                )
            w = np.broadcast_to(np.asarray(omega_b_rps, dtype=float), (*a.shape[:-1], 3))
            quad = rate_quadratics(w)[..., self._aided_cols - 6]
            a = a - quad @ self._aided_design.T
            phi[..., self._aided_cols] = quad
        phi[..., self._cols] = a @ self._solve_matrix.T
        return phi

    def solve(
        self,
        accel_mps2: np.ndarray,
        t_s: np.ndarray | None = None,
        omega_b_rps: np.ndarray | None = None,
    ) -> ArrayKinematics:
        """Solve a block of samples (T, N) into an :class:`ArrayKinematics` record.

        Non-finite samples raise ValueError naming the first bad row; callers
        that want a fallback (hold the prediction) use the compensation loop.
        """
        a = np.atleast_2d(np.asarray(accel_mps2, dtype=float))
        bad = np.flatnonzero(~np.all(np.isfinite(a), axis=-1))
        if bad.size:
            raise ValueError(f"sample {bad[0]} has a non-finite channel: {a[bad[0]]}")
        phi = self.solve_features(a, omega_b_rps)
        t = np.arange(a.shape[0], dtype=float) if t_s is None else np.asarray(t_s, dtype=float)
        return kinematics_from_features(t, phi)


def kinematics_from_features(t_s: np.ndarray, phi: np.ndarray) -> ArrayKinematics:
    """Wrap feature vectors (T, 12) into an :class:`ArrayKinematics` record."""
    return ArrayKinematics(
        t_s=t_s,
        omega_dot_b_rps2=phi[:, OMEGA_DOT],
        f_b_mps2=phi[:, SPECIFIC_FORCE],
        rate_products_rps2=phi[:, RATE_PRODUCTS],
        rate_squares_rps2=phi[:, RATE_SQUARES],
    )


def nine_cube_closed_form(accel_mps2: np.ndarray, lever_arm_m: float) -> np.ndarray:
    """The paper's closed form (eq. 26) for the nine-sensor cube.

    Parameters
    ----------
    accel_mps2 : array (..., 9)
        Outputs A1..A9, m/s^2, in the order of
        :func:`ngnav.layout.nine_accelerometer_cube`.
    lever_arm_m : float
        Cube edge l, m.

    Returns
    -------
    array (..., 9)
        ``[wdot_x, wdot_y, wdot_z, f_x, f_y, f_z, w_y w_z, w_x w_z, w_x w_y]``.
    """
    a = np.asarray(accel_mps2, dtype=float)
    if a.shape[-1] != 9:
        raise ValueError(f"the nine-cube closed form needs 9 channels, got {a.shape[-1]}")
    a1, a2, a3, a4, a5, a6, a7, a8, a9 = np.moveaxis(a, -1, 0)
    k = 0.5 / lever_arm_m
    return np.stack(
        [
            k * (a4 + a9 - a6 - a7),
            k * (a3 + a7 - a1 - a8),
            k * (a1 + a5 - a2 - a4),
            a1,
            a4,
            a7,
            k * (a6 + a9 - a4 - a7),
            k * (a3 + a8 - a1 - a7),
            k * (a2 + a5 - a1 - a4),
        ],
        axis=-1,
    )
