"""Speed benchmark: the front end plus the GM(1,1) compensation loop, nine channels.

``ngnav bench`` times :func:`ngnav.compensation.compensate` (array solve,
GM(1,1) forecasts of the nine loop channels, exact error term, rate
integration) on simulated nine-cube samples, on one core, and reports the
median of several repeats in samples per second. Wall-clock numbers on shared
machines are noisy: quote the median and compare ratios run in one process.
"""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass

import numpy as np

from ngnav.compensation import compensate
from ngnav.frontend import ArraySolver
from ngnav.layout import nine_accelerometer_cube
from ngnav.mounting import MountingErrors
from ngnav.predictors import GreyPredictor, LastValuePredictor, LinePredictor
from ngnav.records import ArraySamples
from ngnav.sim.turntable import fixed_axis_turn


@dataclass(frozen=True)
class BenchResult:
    name: str
    samples: int
    seconds: tuple[float, ...]

    @property
    def median_s(self) -> float:
        return statistics.median(self.seconds)

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.median_s


def _pin_one_core() -> None:
    if hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        except OSError:
            pass


def run_bench(n_samples: int = 20_000, repeats: int = 5, window: int = 5) -> list[BenchResult]:
    """Time the compensation loop with each predictor; returns one result per case."""
    _pin_one_core()
    rng = np.random.default_rng([2006, 99])
    layout = nine_accelerometer_cube(0.1)
    truth = fixed_axis_turn(
        np.deg2rad(90.0),
        duration_s=n_samples / 100.0 - 0.02,
        rest_before_s=0.0,
        rest_after_s=0.0,
        rate_hz=100.0,
        axis_b=np.array([0.3, -0.2, 1.0]),
        pivot_b_m=np.array([0.05, 0.05, 0.05]),
    )
    errors = MountingErrors(rng.normal(0, 0.002, (9, 3)), rng.normal(0, 0.01, (9, 2)))
    a = errors.real_layout(layout).outputs(
        truth.omega_dot_b_rps2, truth.f_b_mps2, truth.omega_b_rps
    )
    a = a + rng.normal(0.0, 0.006, a.shape)
    samples = ArraySamples(truth.t_s, a)
    solver = ArraySolver(layout)
    e = errors.error_matrix(layout)
    shift = np.repeat([2.1, 245.0, 24.5], 3)
    cases = {
        "solve only (vectorised, no loop)": None,
        "loop, no compensation": (None, LastValuePredictor()),
        "loop + GM(1,1) compensation": (e, GreyPredictor(window=window, shift=shift)),
        "loop + line compensation": (e, LinePredictor(window=window)),
        "loop + last-value compensation": (e, LastValuePredictor()),
    }
    results = []
    for name, case in cases.items():
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            if case is None:
                solver.solve(samples.accel_mps2, samples.t_s)
            else:
                compensate(samples, solver, case[0], case[1])
            times.append(time.perf_counter() - t0)
        results.append(BenchResult(name, samples.t_s.shape[0], tuple(times)))
    return results
