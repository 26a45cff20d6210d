"""Shared test helpers."""

import numpy as np

from filters.ekf import NavFilter


def initialise_level(nf: NavFilter) -> None:
    """Level, at rest at the origin: 1 m / 0.1 m/s / 0.01 rad / 0.01 rad/s sigmas."""
    nf.initialise(
        0.0,
        np.zeros(3),
        np.zeros(3),
        np.array([1.0, 0, 0, 0]),
        np.zeros(3),
        1.0,
        0.1,
        np.full(3, 0.01),
        0.01,
    )
