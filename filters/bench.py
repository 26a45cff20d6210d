"""Speed benchmark of the whole GPS/array pipeline beside a bare filterpy loop.

``ngnav bench-filter`` simulates a flight scenario (``uav-survey`` by
default: 1 kHz array, 5 Hz GPS), keeps its first ``seconds`` of flight, and
times :func:`filters.pipeline.run_filter` on it: array solve, GM(1,1)
compensation, nominal propagation, filter prediction, the rate measurement
and the GPS updates: everything a recorded run goes through except file
reading. Beside it, in the same process and on the same core, it times a
*bare* filterpy loop with the same state size and the same number of
predictions and updates of each size and kind, the vehicle models' and the rest's
included (random but fixed F, Q, H, R): the floor set by filterpy itself. The rate
update is the pipeline's, filterpy's correlated-noise update
(:func:`filters.updates.update_correlated`, with a fixed cross-covariance); the others
are filterpy's plain ``update``. Wall-clock figures on shared machines are noisy: the median
of several repeats is reported, and the ratio of the two is the figure to
compare between machines. The repeats alternate (pipeline, bare loop,
pipeline, ...) so that both see the same machine load, and the ratio is the
median of each pair's ratio.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, fields

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update

from filters.pipeline import run_filter
from filters.updates import update_correlated
from ngnav.bench import _pin_one_core
from ngnav.records import ArraySamples, GpsFixes
from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.simulate import simulate_flight


@dataclass(frozen=True)
class FilterBench:
    """Timings (s) of the pipeline and of the bare loop over the same run."""

    scenario: str
    samples: int
    blocks: int
    gps_fixes: int
    model_updates: int
    rest_updates: int
    state_size: int
    array_rate_hz: float
    filter_rate_hz: float
    gps_rate_hz: float
    pipeline_s: tuple[float, ...]
    bare_s: tuple[float, ...]

    @property
    def pipeline_samples_per_s(self) -> float:
        return self.samples / statistics.median(self.pipeline_s)

    @property
    def bare_samples_per_s(self) -> float:
        return self.samples / statistics.median(self.bare_s)

    @property
    def slowdown(self) -> float:
        """Pipeline time over bare-loop time: the median of the ratios of the repeats' pairs."""
        return statistics.median(p / b for p, b in zip(self.pipeline_s, self.bare_s, strict=True))

    @property
    def pipeline_step_us(self) -> float:
        """Median microseconds per filter step (one block and its share of the GPS fixes)."""
        return 1e6 * statistics.median(self.pipeline_s) / self.blocks

    @property
    def bare_step_us(self) -> float:
        """The bare loop's median microseconds per step."""
        return 1e6 * statistics.median(self.bare_s) / self.blocks

    def as_dict(self) -> dict:
        """The figures as plain numbers (``ngnav bench-filter --json``)."""
        return {
            "scenario": self.scenario,
            "samples": self.samples,
            "blocks": self.blocks,
            "gps_fixes": self.gps_fixes,
            "model_updates": self.model_updates,
            "rest_updates": self.rest_updates,
            "state_size": self.state_size,
            "array_rate_hz": self.array_rate_hz,
            "filter_rate_hz": self.filter_rate_hz,
            "gps_rate_hz": self.gps_rate_hz,
            "pipeline_samples_per_s": self.pipeline_samples_per_s,
            "bare_samples_per_s": self.bare_samples_per_s,
            "pipeline_real_time_factor": self.pipeline_samples_per_s / self.array_rate_hz,
            "pipeline_step_us": self.pipeline_step_us,
            "bare_step_us": self.bare_step_us,
            "pipeline_over_bare": self.slowdown,
            "pipeline_s": list(self.pipeline_s),
            "bare_s": list(self.bare_s),
        }


def _first_seconds(samples: ArraySamples, fixes: GpsFixes, seconds: float):
    n = int(np.searchsorted(samples.t_s, samples.t_s[0] + seconds, side="right"))
    keep = fixes.t_s <= samples.t_s[n - 1]
    sliced = {f.name: getattr(fixes, f.name)[keep] for f in fields(fixes)}
    return ArraySamples(samples.t_s[:n], samples.accel_mps2[:n]), GpsFixes(**sliced)


def _spread(count: int, n_blocks: int) -> np.ndarray:
    """How many of ``count`` updates fall in each of ``n_blocks`` blocks, evenly spread."""
    if count <= 0 or n_blocks <= 0:
        return np.zeros(max(n_blocks, 0), dtype=int)
    at = np.arange(count) * n_blocks // count
    return np.bincount(at, minlength=n_blocks)


def bare_loop(
    n_state: int,
    n_blocks: int,
    n_rate: int,
    n_fixes: int,
    n_scalar: int = 0,
    n_rest: int = 0,
    seed: int = 0,
) -> float:
    """Seconds for filterpy alone with the pipeline's measurement counts: ``n_blocks``
    predictions and rate updates (correlated with the propagation, as the pipeline's), two
    3-D updates per fix (position, velocity), ``n_scalar`` 1-D updates (the vehicle models)
    and ``n_rest`` 3-D ones (the zero rate at rest), each kind spread evenly over the
    blocks."""
    rng = np.random.default_rng(seed)
    f = np.eye(n_state) + 0.01 * rng.normal(size=(n_state, n_state))
    q = np.eye(n_state) * 1e-6
    h_rate = rng.normal(size=(n_rate, n_state))
    h_3 = rng.normal(size=(3, n_state))
    h_1 = rng.normal(size=(1, n_state))
    r_rate = np.eye(n_rate)
    # the noise's cross-covariance: small enough that P stays positive definite (at 1e-2
    # this P, tied to the same H at every block, went indefinite)
    m_rate = 1e-4 * rng.normal(size=(n_state, n_rate))
    r_3 = np.eye(3)
    r_1 = np.eye(1)
    x = np.zeros(n_state)
    p = np.eye(n_state)
    fixes = _spread(n_fixes, n_blocks)
    scalars = _spread(n_scalar, n_blocks)
    rests = _spread(n_rest, n_blocks)
    t0 = time.perf_counter()
    for b in range(n_blocks):
        x, p = kf_predict(x, p, f, q)
        x, p = update_correlated(x, p, np.zeros(n_rate), r_rate, h_rate, m_rate)
        for _ in range(fixes[b]):
            x, p = kf_update(x, p, np.zeros(3), r_3, h_3)
            x, p = kf_update(x, p, np.zeros(3), r_3, h_3)
        for _ in range(rests[b]):
            x, p = kf_update(x, p, np.zeros(3), r_3, h_3)
        for _ in range(scalars[b]):
            x, p = kf_update(x, p, np.zeros(1), r_1, h_1)
        p = 0.5 * (p + p.T)
    return time.perf_counter() - t0


def run_filter_bench(scn: FlightScenario, seconds: float = 120.0, repeats: int = 5) -> FilterBench:
    """Time the pipeline and the bare loop ``repeats`` times each, on one core."""
    if seconds <= 0 or repeats < 1:
        raise ValueError("seconds must be positive and repeats at least 1")
    _pin_one_core()
    sim = simulate_flight(scn, 0)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, seconds)
    times, bare = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = run_filter(samples, fixes, sim.config)
        times.append(time.perf_counter() - t0)
        n_state, n_blocks = res.state_size, res.counts["blocks"]
        if n_blocks == 0:
            raise ValueError(
                f"the first {seconds:g} s of {scn.name!r} hold no filter block (the filter "
                "starts after the alignment and the first fix): time more seconds"
            )
        c = res.counts
        n_fixes = c["gps fixes used"]
        n_scalar = c["sideslip updates"] + c["angle-of-attack updates"]
        n_rest = c["zero-rate updates at rest"]
        bare.append(bare_loop(n_state, n_blocks, res.rate_dim, n_fixes, n_scalar, n_rest))
    return FilterBench(
        scn.name,
        samples.t_s.shape[0],
        n_blocks,
        n_fixes,
        n_scalar,
        n_rest,
        n_state,
        scn.run.rate_hz,
        scn.filter.rate_hz,
        scn.gps.rate_hz,
        tuple(times),
        tuple(bare),
    )
