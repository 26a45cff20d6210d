"""Shared test helpers."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from filters.ekf import FilterNoise, NavFilter
from ngnav.frontend import ArraySolver
from ngnav.layout import ArrayLayout, nine_accelerometer_cube

#: The repository's root (where ``python -m ngnav.cli`` runs).
ROOT = Path(__file__).resolve().parents[1]

#: CLI flags of the short ``tactical`` flight the subprocess tests run (200 Hz array).
SHORT_TACTICAL_ARGS = ("--scenario", "tactical", "--set", "run.rate_hz=200")

#: The three cross products of the rate (wy wz, wx wz, wx wy) as index pairs.
PAIRS = np.array([[1, 2], [0, 2], [0, 1]])


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


def level_filter(
    position_sigma_m: float = 0.0, aoa_sigma_rad: float = 0.0
) -> tuple[NavFilter, ArrayLayout, ArraySolver]:
    """A filter on the nine-accelerometer cube (1 mg noise), initialised level at rest."""
    layout = nine_accelerometer_cube(0.1)
    solver = ArraySolver(layout, np.full(9, 1e-3))
    cov = solver.covariance()
    noise = FilterNoise(cov, cov, cov * 1e-6, position_sigma_m)
    nf = NavFilter(
        noise,
        PAIRS,
        np.zeros(3),
        sensor_axes_b=layout.axes_b,
        solve_matrix=solver.solve_matrix,
        aoa_prior_sigma_rad=aoa_sigma_rad,
    )
    initialise_level(nf)
    return nf, layout, solver


def run_cli(*args: str, check: bool = True, timeout: float = 600.0) -> subprocess.CompletedProcess:
    """``python -m ngnav.cli ARGS`` as a real subprocess from the repository root.

    With ``check`` a non-zero exit raises AssertionError carrying its stderr.
    """
    proc = subprocess.run(
        [sys.executable, "-m", "ngnav.cli", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(proc.stderr)
    return proc


def run_study(name: str, *args: str, check: bool = True, timeout: float = 600.0):
    """``python -m studies.NAME ARGS`` from the checkout, as a real subprocess."""
    proc = subprocess.run(
        [sys.executable, "-m", f"studies.{name}", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"studies.{name} {args} failed:\n{proc.stderr}")
    return proc
