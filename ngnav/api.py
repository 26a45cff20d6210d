"""The public Python API: the few names a notebook needs.

A composition root beside the command line (``ngnav.cli``): the core never
imports the filter or the telemetry, so this is where they meet. ::

    import numpy as np
    from ngnav import api

    sim = api.simulate("uav-survey")                      # a flight with its truth
    res = api.run(sim.samples, sim.fixes, sim.config)     # the GPS/array filter
    est = res.estimates                                   # arrays over the E epochs
    sigma_pos_m = np.sqrt(np.diagonal(est.cov_nav, axis1=1, axis2=2)[:, 0:3])
    err = api.errors(est, sim.truth)                      # truth minus estimate
    print(api.summary(err))

Every array is SI; frames and units are in the names (``pos_ned_m``,
``vel_ned_mps``, ``q_nb``, ``omega_b_rps``). ``cov_nav`` (E, 12, 12) is the full
covariance of position, velocity, attitude (a NED small angle, rad) and body rate.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from filters.evaluate import ErrorSummary, RunErrors, nees, run_errors, summarise
from filters.output import read_estimates_csv as _read_csv
from filters.output import read_estimates_npz as _read_npz
from filters.pipeline import Pipeline, run_filter
from ngnav.errors import CovarianceError, LostTrackError
from ngnav.records import ArraySamples, Estimates, FlightTruth, GpsFixes, NavEstimate, RunResult
from ngnav.runconfig import RunConfig
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import SimulatedRun, simulate_flight
from telemetry.runfiles import RunInputs
from telemetry.runfiles import read_run as _read_run
from telemetry.runfiles import write_run as _write_run

__all__ = [
    "ArraySamples",
    "CovarianceError",
    "ErrorSummary",
    "Estimates",
    "FlightTruth",
    "GpsFixes",
    "LostTrackError",
    "NavEstimate",
    "RunConfig",
    "RunErrors",
    "RunResult",
    "SimulatedRun",
    "errors",
    "nees",
    "pipeline_factory",
    "read_estimates",
    "read_run",
    "run",
    "simulate",
    "summary",
    "write_run",
]


def simulate(
    scenario: str = "uav-survey", run_index: int = 0, overrides: Sequence[str] = ()
) -> SimulatedRun:
    """Simulate one flight of a scenario: array samples, GPS fixes, configuration, truth.

    Parameters
    ----------
    scenario : str
        A shipped flight scenario (``uav-survey``, ``tactical``, ``static``) or a TOML path.
    run_index : int
        Monte Carlo index ``i``: the run draws from ``default_rng([seed, i])``.
    overrides : sequence of str
        ``section.key=value`` overrides, as ``--set`` takes them.

    Returns
    -------
    SimulatedRun
        ``samples``, ``fixes``, ``config`` (what the filter is told) and ``truth``.
    """
    return simulate_flight(load_flight(scenario, list(overrides)), run_index)


def run(
    samples: ArraySamples,
    fixes: GpsFixes,
    config: RunConfig,
    *,
    compensation: str | None = None,
    use_gps: bool = True,
    smooth: bool = False,
) -> RunResult:
    """Run the GPS/array filter over a whole run.

    Parameters
    ----------
    samples : ArraySamples
        Channel outputs (T, N), m/s^2, uniformly sampled; non-finite rows are held.
    fixes : GpsFixes
        GPS fixes (time of validity, geodetic position, NED velocity, 1-sigma accuracies).
    config : RunConfig
        What the filter knows (a run directory's ``config.toml``).
    compensation : str, optional
        Override ``config.compensation.method`` (``gm11``, ``line``, ``last``, ``none``).
    use_gps : bool
        False runs the array alone after initialisation.
    smooth : bool
        Also run the Rauch-Tung-Striebel pass (:mod:`filters.smoother`): the result's
        ``smoothed`` holds the smoothed epochs with their covariance.

    Returns
    -------
    RunResult
        ``estimates`` (:class:`ngnav.records.Estimates`, the full 12 x 12 navigation
        covariance per epoch), GPS ``innovations``, ``rate_nis``, ``counts``, and
        ``final`` (:class:`ngnav.records.NavEstimate`: the last epoch with the whole
        error state's covariance, ``final.block_cov("b_f")`` for one block).

    Raises
    ------
    ValueError
        A configuration the filter refuses, or data it cannot use.
    CovarianceError
        The filter diverged (``LostTrackError``: it lost its track); the exception's
        ``partial`` holds the estimates up to then.
    """
    return run_filter(
        samples, fixes, config, compensation=compensation, use_gps=use_gps, smooth=smooth
    )


def read_run(path: str | Path) -> RunInputs:
    """Read a run: a directory (``config.toml``, ``array.csv``, ``gps.csv``) or a ``.tlog``.

    The result's ``samples``, ``fixes`` and ``config`` go to :func:`run`; ``reports``
    counts what reading skipped.
    """
    return _read_run(path)


def read_estimates(path: str | Path) -> tuple[Estimates, NavEstimate | None]:
    """Read what ``ngnav run`` wrote: ``estimates.npz`` or ``estimates.csv``.

    Returns the epochs as :class:`Estimates` and the last epoch with the whole error
    state's covariance (:class:`NavEstimate`). From the ``.npz`` the navigation
    covariance is full (with its correlations); from the ``.csv`` it is the diagonal
    of the sigmas the file keeps, and there is no last-epoch record (None).
    """
    p = Path(path)
    if p.suffix == ".npz":
        return _read_npz(p)
    return _read_csv(p), None


def write_run(path: str | Path, samples: ArraySamples, fixes: GpsFixes, config: RunConfig) -> Path:
    """Write a run as a directory of CSV files and ``config.toml``, or as a ``.tlog``."""
    return _write_run(path, samples, fixes, config)


def errors(estimates: Estimates, truth: FlightTruth) -> RunErrors:
    """Truth minus estimate at every epoch: position, velocity, attitude (NED small
    angle, rad), roll/pitch/yaw (deg) and rate; ``stacked()`` gives (E, 12)."""
    return run_errors(estimates, truth)


def summary(err: RunErrors) -> ErrorSummary:
    """RMS and maximum of each error (horizontal and vertical position, velocity, roll,
    pitch, yaw, rate)."""
    return summarise(err)


def pipeline_factory(
    compensation: str | None = None, keep_estimates: bool = True, smooth: bool = False
) -> Callable[[RunConfig, Callable[[NavEstimate], None]], Pipeline]:
    """A factory that builds the GPS/array filter for a MAVLink stream session.

    Parameters
    ----------
    compensation : str, optional
        Override the configuration's compensation (``gm11``, ``line``, ``last``, ``none``).
    keep_estimates : bool
        Keep every epoch for the run's result (False for an endless live link).
    smooth : bool
        Smooth the run once it is finished (a tlog replay; needs ``keep_estimates``).

    Returns
    -------
    callable
        ``make(config, on_epoch) -> Pipeline``, as
        :class:`telemetry.session.StreamSession` takes it.
    """

    def make(cfg: RunConfig, on_epoch: Callable[[NavEstimate], None]) -> Pipeline:
        return Pipeline(
            cfg,
            compensation=compensation,
            on_epoch=on_epoch,
            keep_estimates=keep_estimates,
            smooth=smooth,
        )

    return make
