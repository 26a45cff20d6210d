"""Smooth motion primitives shared by the simulations and the filter's lift-off blend."""

from __future__ import annotations

import numpy as np


def min_jerk_step(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quintic minimum-jerk step ``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`` on [0, 1].

    Returns s, ds/dtau, d2s/dtau2; constant 0 before and 1 after the step. A
    Python ``float`` gives floats (the filter's per-block path; the same formulas
    without array overhead), anything else arrays.
    """
    if type(tau) is float:
        x = min(max(tau, 0.0), 1.0)
        return (
            x**3 * (10 - 15 * x + 6 * x * x),
            30 * x**2 * (1 - x) ** 2,
            60 * x * (1 - x) * (1 - 2 * x),
        )
    x = np.clip(np.asarray(tau, dtype=float), 0.0, 1.0)
    s = x**3 * (10 - 15 * x + 6 * x * x)
    ds = 30 * x**2 * (1 - x) ** 2
    dds = 60 * x * (1 - x) * (1 - 2 * x)
    return s, ds, dds
