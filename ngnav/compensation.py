"""The paper's closed-loop mounting-error compensation (eq. 22, SPEC section 4).

At sample j the loop forecasts rate, angular acceleration and specific force
one step ahead from the last ``window`` compensated estimates, evaluates the
exact error term ``A_e = E (phi_hat - phi_ref)`` with the calibrated mounting
errors (``E`` from :meth:`ngnav.mounting.MountingErrors.error_matrix`),
subtracts it from the measured outputs and solves the nominal layout. The rate
is the trapezoidal integral of the compensated angular acceleration.

``phi_ref`` is the state at which the outputs were zeroed (the paper's zero
taken at rest): the static part of ``A_e`` is already in that zero, so only the
change from it is subtracted. Pass zeros when the outputs were not zeroed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ngnav.frontend import ArraySolver
from ngnav.layout import N_FEATURES, OMEGA_DOT, RATE_PRODUCTS, SPECIFIC_FORCE
from ngnav.records import ArraySamples, freeze_fields

#: Channels the loop forecasts, in order: rate (3), angular acceleration (3), specific force (3).
STATE_CHANNELS: tuple[str, ...] = (
    "omega_x",
    "omega_y",
    "omega_z",
    "omega_dot_x",
    "omega_dot_y",
    "omega_dot_z",
    "f_x",
    "f_y",
    "f_z",
)
#: Index pairs giving the quadratic features [wx^2, wy^2, wz^2, wy wz, wx wz, wx wy].
_QUAD_I = np.array([0, 1, 2, 1, 0, 0])
_QUAD_J = np.array([0, 1, 2, 2, 2, 1])
#: The same pairs as ``(i, j)`` tuples of ``w_i w_j``, in that order.
QUAD_PAIRS: tuple[tuple[int, int], ...] = tuple(
    zip(_QUAD_I.tolist(), _QUAD_J.tolist(), strict=True)
)
RATE = slice(0, 3)
RATE_DOT = slice(3, 6)
FORCE = slice(6, 9)


class Predictor(Protocol):
    name: str
    window: int

    def forecast(self, history: np.ndarray, j: int) -> tuple[np.ndarray, int]: ...


@dataclass(frozen=True)
class CompensatedKinematics:
    """Output of the compensation loop.

    Attributes
    ----------
    t_s : array (T,)
        Times, s.
    omega_b_rps : array (T, 3)
        Integrated body rate, rad/s.
    omega_dot_b_rps2 : array (T, 3)
        Compensated angular acceleration, rad/s^2.
    f_b_mps2 : array (T, 3)
        Compensated specific force at the body origin, m/s^2.
    rate_products_rps2 : array (T, 3)
        Compensated ``[wy wz, wx wz, wx wy]``; NaN for layouts that cannot solve them.
    predictor : str
        Name of the predictor used.
    n_fallbacks : int
        Channel forecasts where the predictor fell back to the last value.
    n_held : int
        Invalid (non-finite) samples replaced by the forecast (``on_invalid="hold"``).
    """

    t_s: np.ndarray
    omega_b_rps: np.ndarray
    omega_dot_b_rps2: np.ndarray
    f_b_mps2: np.ndarray
    rate_products_rps2: np.ndarray
    predictor: str
    n_fallbacks: int
    n_held: int

    def __post_init__(self) -> None:
        freeze_fields(
            self,
            {
                "t_s": (),
                "omega_b_rps": (3,),
                "omega_dot_b_rps2": (3,),
                "f_b_mps2": (3,),
                "rate_products_rps2": (3,),
            },
        )

    def state(self) -> np.ndarray:
        """The loop's channels (T, 9) in :data:`STATE_CHANNELS` order."""
        return np.hstack([self.omega_b_rps, self.omega_dot_b_rps2, self.f_b_mps2])


def compensate(
    samples: ArraySamples,
    solver: ArraySolver,
    error_matrix: np.ndarray | None,
    predictor: Predictor,
    *,
    reference_features: np.ndarray | None = None,
    omega0_b_rps: np.ndarray | None = None,
    on_invalid: str = "raise",
) -> CompensatedKinematics:
    """Run the paper's compensation loop (eq. 22) over a block of samples.

    Parameters
    ----------
    samples : ArraySamples
        Outputs (T, N), m/s^2, already scaled and zeroed as the caller wants.
    solver : ArraySolver
        Solver of the *nominal* layout.
    error_matrix : array (N, 12) or None
        ``E`` of the calibrated mounting errors; None runs the loop without
        compensation (the nominal solve, with the same rate integration).
    predictor : Predictor
        One-step-ahead predictor of the 9 loop channels.
    reference_features : array (12,), optional
        Features at which the outputs were zeroed; zeros by default.
    omega0_b_rps : array (3,), optional
        Rate at the first sample; zero by default.
    on_invalid : {"raise", "hold"}
        A sample with a non-finite channel raises ValueError naming it, or is
        replaced by the forecast and counted in ``n_held``.

    Returns
    -------
    CompensatedKinematics
        The history is seeded with the uncompensated solution of the first
        sample, so the first ``window`` forecasts work from it.
    """
    if on_invalid not in ("raise", "hold"):
        raise ValueError(f"on_invalid must be 'raise' or 'hold', got {on_invalid!r}")
    a = samples.accel_mps2
    n_sensors = solver.layout.n_sensors
    if samples.n_channels != n_sensors:
        raise ValueError(f"solver expects {n_sensors} channels, samples have {samples.n_channels}")
    t = samples.t_s
    n_samples = t.shape[0]
    e = np.zeros((n_sensors, N_FEATURES)) if error_matrix is None else np.asarray(error_matrix)
    if e.shape != (n_sensors, N_FEATURES):
        raise ValueError(f"error_matrix must have shape ({n_sensors}, 12), got {e.shape}")
    compensating = error_matrix is not None
    phi_ref = np.zeros(N_FEATURES) if reference_features is None else np.asarray(reference_features)
    w0 = np.zeros(3) if omega0_b_rps is None else np.asarray(omega0_b_rps, dtype=float)
    invalid = samples.invalid
    if np.any(invalid) and on_invalid == "raise":
        i = int(np.flatnonzero(invalid)[0])
        raise ValueError(f"sample {i} (t = {t[i]} s) has a non-finite channel: {a[i]}")
    if invalid[0]:
        raise ValueError("the first sample must be valid: it seeds the loop")

    window = predictor.window
    hist = np.empty((n_samples + window, 9))
    phi_out = np.full((n_samples, N_FEATURES), np.nan)
    first = solver.solve_features(a[0], omega_b_rps=w0)
    hist[:window] = np.concatenate([w0, first[OMEGA_DOT], first[SPECIFIC_FORCE]])
    # Everything linear is done for all samples at once: with S the solve operator,
    # phi_j = S a_j + S E phi_ref - S E phi_hat_j (+ the rate-aided quadratic terms).
    cols, aided = solver.solved_columns, solver.aided_columns
    smat = solver.solve_matrix
    se = smat @ e  # (k, 12)
    sa = np.where(invalid[:, None], 0.0, a) @ smat.T + se @ phi_ref  # (T, k)
    g_aided = smat @ solver.layout.design[:, aided]  # (k, n_aided)
    aided_q = aided - 6
    qi, qj = _QUAD_I, _QUAD_J
    dt = np.diff(t, prepend=t[0])
    w_prev = w0
    wd_prev = first[OMEGA_DOT]
    n_fallbacks = 0
    n_held = 0
    phi_hat = np.empty(N_FEATURES)
    for j in range(n_samples):
        x_hat, nf = predictor.forecast(hist[j : j + window], j)
        n_fallbacks += nf
        w_hat = x_hat[RATE]
        quad = w_hat[qi] * w_hat[qj]
        phi = phi_out[j]
        if invalid[j]:
            n_held += 1
            phi[:6] = x_hat[3:]
            phi[6:] = quad
        else:
            x = sa[j]
            if compensating:
                phi_hat[:6] = x_hat[3:]
                phi_hat[6:] = quad
                x = x - se @ phi_hat
            if aided.size:
                x = x - g_aided @ quad[aided_q]
                phi[aided] = quad[aided_q]
            phi[cols] = x
        wd = phi[OMEGA_DOT]
        w = w_prev + 0.5 * (wd_prev + wd) * dt[j]
        row = hist[j + window]
        row[RATE] = w
        row[RATE_DOT] = wd
        row[FORCE] = phi[SPECIFIC_FORCE]
        w_prev, wd_prev = w, wd
    state = hist[window:]
    return CompensatedKinematics(
        t_s=t,
        omega_b_rps=state[:, RATE],
        omega_dot_b_rps2=state[:, RATE_DOT],
        f_b_mps2=state[:, FORCE],
        rate_products_rps2=phi_out[:, RATE_PRODUCTS],
        predictor=predictor.name,
        n_fallbacks=n_fallbacks,
        n_held=n_held,
    )
