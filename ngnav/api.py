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
from dataclasses import dataclass
from pathlib import Path

from filters.evaluate import ErrorSummary, RunErrors, nees, run_errors, summarise
from filters.output import read_estimates_csv as _read_csv
from filters.output import read_estimates_npz as _read_npz
from filters.pipeline import Pipeline, run_filter
from ngnav.bench_session import BenchCalibration, calibrate_bench
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
    "BenchCalibration",
    "CovarianceError",
    "ErrorSummary",
    "Estimates",
    "FlightTruth",
    "GpsFixes",
    "LostTrackError",
    "NavEstimate",
    "RunConfig",
    "RunErrors",
    "RunReport",
    "RunResult",
    "SimulatedRun",
    "calibrate",
    "consistency",
    "errors",
    "nees",
    "pipeline_factory",
    "plot",
    "read_estimates",
    "read_run",
    "run",
    "simulate",
    "simulate_bench",
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


def simulate_bench(
    scenario: str = "uav-survey",
    run_index: int = 0,
    out: str | Path | None = None,
    *,
    continuous: bool = False,
    overrides: Sequence[str] = (),
):
    """Simulate the bench session of a flight run's array, for :func:`calibrate`.

    18 still poses (one recording each, or one recording with turns between them with
    ``continuous``) and 9 rate-table poses of run ``run_index``'s array, with its truth.
    With ``out`` the session is written there as ``ngnav calibrate`` reads it (and
    ``truth_calibration.toml``). Returns a :class:`ngnav.sim.bench_recordings.BenchSession`.
    """
    from ngnav.sim.bench_recordings import bench_session, write_bench_session

    session = bench_session(
        load_flight(scenario, list(overrides)), run_index, continuous=continuous
    )
    if out is not None:
        write_bench_session(session, out)
    return session


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


def warm_up() -> None:
    """Run the filter over the first 3 s of the shipped ``tactical`` flight (0.7 s cached).

    The filter's inner loops are compiled on their first use on a machine (about 20 s)
    and loaded from a disk cache after (:mod:`filters.kernels`). A live link calls this
    before it listens: a first step that compiled would stall it while its input queued
    and overflowed.
    """
    from filters.bench import _first_seconds

    sim = simulate_flight(load_flight("tactical"), 0)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, 3.0)
    run_filter(samples, fixes, sim.config)


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


def calibrate(directory: str | Path) -> BenchCalibration:
    """Calibrate an array from a bench session's directory (as ``ngnav calibrate``).

    The directory holds ``config.toml`` (``[array]``, ``[sensor]``), the static poses
    (``static/*.csv`` or one ``array.csv``) and, optionally, rate-table poses
    (``spin/*.csv`` with a ``.toml`` each). The result's ``static`` and ``spin`` hold the
    fits with their 1-sigmas; ``section`` is the ``[calibration]`` text a run's
    ``config.toml`` takes (write it where you want it). See :mod:`ngnav.bench_session`.
    """
    return calibrate_bench(directory)


@dataclass(frozen=True)
class RunReport:
    """What :func:`plot` drew: the PNG ``figures``, the HTML ``report`` and its ``summary``
    lines."""

    figures: list[Path]
    report: Path
    summary: list[str]


def plot(
    run: str | Path, out: str | Path | None = None, estimates: str | Path | None = None
) -> RunReport:
    """Draw a run's figures and its self-contained HTML report (as ``ngnav plot``).

    ``run`` is a run directory after ``ngnav run`` (``config.toml``, ``gps.csv``,
    ``estimates.csv``, and ``truth.csv`` for the errors); ``estimates`` another estimates
    file (e.g. ``estimates.smoothed.csv``); ``out`` the folder (default ``RUN/plots``).
    """
    import numpy as np
    from scipy.stats import chi2

    from filters.evaluate import run_errors, summarise
    from filters.output import nis_path, read_estimates_csv, read_nis_csv
    from filters.supervision import GATE_PROBABILITY
    from filters.vehicle_model import COAST_AFTER_FIXES, COAST_AFTER_S
    from ngnav.geodesy import LocalTangentPlane
    from ngnav.plots import RunPlotData, outage_spans, plot_run, write_report
    from ngnav.runconfig import read_run_config
    from ngnav.runio import read_gps_csv, read_truth_csv

    src = Path(run)
    if not src.is_dir():
        raise ValueError(f"{src}: not a run directory (config.toml, gps.csv, estimates.csv)")
    est_path = Path(estimates) if estimates else src / "estimates.csv"
    if not est_path.is_file():
        raise ValueError(f"{est_path}: no such file; run `ngnav run {src}` first")
    cfg = read_run_config(src / "config.toml")
    fixes, _ = read_gps_csv(src / "gps.csv")
    est = read_estimates_csv(est_path)
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    fix_ned = ltp.to_ned(fixes.lat_deg, fixes.lon_deg, fixes.alt_m)
    nis = read_nis_csv(nis_path(est_path)) if nis_path(est_path).is_file() else None
    summary = [
        f"run {src}: {est.t_s.size} estimates over {est.t_s[0]:.2f}-{est.t_s[-1]:.2f} s "
        f"({est_path.name}), {fixes.t_s.size} GPS fixes"
    ]
    if nis is not None:
        summary.append(
            f"GPS positions rejected by the gate: {int((~nis.pos_accepted).sum())}, "
            f"velocities: {int((~nis.vel_accepted).sum())} (of {nis.t_s.size})"
        )
    err_stacked = None
    truth_csv = src / "truth.csv"
    if truth_csv.is_file():
        err = run_errors(est, read_truth_csv(truth_csv))
        err_stacked = err.stacked()
        s = summarise(err)
        summary.append(
            f"against truth.csv: horizontal RMS {s.horiz_rms_m:.3f} m, vertical "
            f"{s.vert_rms_m:.3f} m, roll/pitch/yaw RMS {s.roll_rms_deg:.3f}/"
            f"{s.pitch_rms_deg:.3f}/{s.yaw_rms_deg:.3f} deg, rate {s.rate_rms_dps:.3f} deg/s"
        )
    # an outage as the filter counts one: no fix for 1 s, or 5 fix intervals if longer
    interval = float(np.median(np.diff(fixes.t_s))) if fixes.t_s.size > 1 else 1.0
    outages = outage_spans(fixes.t_s, max(COAST_AFTER_S, COAST_AFTER_FIXES * interval))
    if outages:
        spans = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in outages)
        summary.append(f"GPS outages (shaded): {spans}")
    data = RunPlotData(
        est,
        fixes.t_s,
        fix_ned,
        nis=nis,
        nis_gate=float(chi2.ppf(GATE_PROBABILITY, 3)),
        outages=outages,
        errors=err_stacked,
    )
    out_dir = Path(out) if out else src / "plots"
    files = plot_run(data, out_dir)
    report = write_report(out_dir, files, f"ngnav: {src.name}", summary)
    return RunReport(files, report, summary)


def consistency(
    scenario: str = "tactical",
    runs: int = 50,
    *,
    overrides: Sequence[str] = (),
    method: str | None = None,
    workers: int = 2,
    scheduler: str | None = None,
    smooth: bool = False,
    profile_s: float | None = None,
    from_s: float | None = None,
    first: int = 0,
) -> dict:
    """NEES and NIS over Monte Carlo runs of a scenario (as ``ngnav consistency``).

    Runs ``first .. first + runs - 1`` (another ``first``: another draw) on
    dask.distributed: ``workers`` local processes, or the cluster at ``scheduler``
    (``tcp://HOST:8786``). ``smooth`` judges the smoothed
    estimates. Returns the report (``blocks``: each NEES block's and NIS's share inside
    the 95 % band, mean and bounds; ``target``; ``diverged``; with ``smooth`` the RMS
    ratios under ``smoothed``). See :func:`filters.consistency.consistency`.
    """
    from filters.consistency import consistency as _consistency

    return _consistency(
        load_flight(scenario, list(overrides)),
        runs,
        method,
        workers,
        profile_s=profile_s,
        from_s=from_s,
        scheduler=scheduler,
        smooth=smooth,
        first=first,
    )
