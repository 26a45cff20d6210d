"""Fault trials: simulated flights with one injected channel fault, and what the tests found.

``ngnav faults`` runs them (:func:`fault_trial` per run, on the campaign's workers): for
each kind of fault, on each channel in turn (run ``i`` takes channel ``i mod N + 1``),
starting at a time drawn per run inside the flight's ``[start_from_s, start_to_s]``; and
fault-free runs for the false alarms. Each trial reports the latency of detection and
isolation, whether the channel named was the one injected, and for a drift what it had
cost the attitude at detection over its 1-sigma (the drift must be found before it costs
the attitude more than its 3 sigma): the faulted run's estimate against the same run's
without the fault, so that an error the flight had anyway is not blamed on the drift.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from filters.state import ATT
from ngnav.errors import CovarianceError
from ngnav.sim.faults import TRIAL_DRIFT_MPS2_PER_S, ChannelFault


@dataclass(frozen=True)
class TrialOutcome:
    """One trial's result (times in s from the fault's start; NaN when it did not happen).

    Attributes
    ----------
    run : int
    fault : ChannelFault or None
        The fault injected (None for a fault-free run).
    detected_s, isolated_s : float
        Latency of the first event that names or includes the channel, and of its
        isolation.
    named : tuple of int
        The channels that event named (empty when nothing was found).
    kind : str
        The kind the event gave ("" when nothing was found).
    false_alarms : int
        Events on other channels, and before the fault's start.
    attitude_sigmas : float
        For a drift: the largest attitude error over its 1-sigma, per axis, at detection.
    attitude_cost_sigmas : float
        For a drift: the same for what the drift cost, the faulted run's attitude error
        less the fault-free run's at that epoch (same run, same noise).
    flight_s : float
        The flight time the tests watched, s.
    failure : str
        How the run stopped early ("" when it ran to its end).
    """

    run: int
    fault: ChannelFault | None
    detected_s: float
    isolated_s: float
    named: tuple[int, ...]
    kind: str
    false_alarms: int
    attitude_sigmas: float
    flight_s: float
    failure: str = ""
    attitude_cost_sigmas: float = np.nan


def trial_fault(
    kind: str, run: int, n_channels: int, start_from_s: float, start_to_s: float, size: float
) -> ChannelFault:
    """Run ``run``'s fault: channel ``run mod N + 1``, its start drawn for the run alone."""
    start = start_from_s + (start_to_s - start_from_s) * np.random.default_rng([7, run]).random()
    return ChannelFault(run % n_channels + 1, kind, float(round(start, 3)), size)


def attitude_cost_sigmas(faulted, clean, truth, t_s: float) -> float:
    """What a fault cost the attitude at ``t_s``, over the faulted filter's 1-sigma.

    ``faulted`` and ``clean`` are the estimates (:class:`ngnav.records.Estimates`) of one
    run with and without the fault (the same noise), ``truth`` the run's. The largest per
    axis of ``|e_f - e_c| / sigma_f`` (NED attitude errors at the epoch ``t_s``); NaN when
    either has no epoch there.
    """
    from filters.evaluate import run_errors

    j = int(np.searchsorted(faulted.t_s, t_s - 1e-9))
    k = int(np.searchsorted(clean.t_s, t_s - 1e-9))
    if j >= faulted.t_s.shape[0] or k >= clean.t_s.shape[0]:
        return np.nan
    if abs(faulted.t_s[j] - t_s) > 1e-6 or abs(clean.t_s[k] - t_s) > 1e-6:
        return np.nan
    e_f = run_errors(faulted, truth).att_ned_rad[j]
    e_c = run_errors(clean, truth).att_ned_rad[k]
    sd = np.sqrt(np.diag(faulted.cov_nav[j][ATT, ATT]))
    return float(np.max(np.abs(e_f - e_c) / sd))


def _watched(scn, run: int, faults: tuple[ChannelFault, ...], end_s: float | None):
    """Run ``run`` of ``scn`` with ``faults``: its config, samples, truth and fixes, up to
    ``end_s`` from its first sample (None: the whole flight)."""
    from ngnav.sim.simulate import simulate_flight

    sim = simulate_flight(replace(scn, faults=faults), run)
    samples, truth, fixes = sim.samples, sim.truth, sim.fixes
    if end_s is not None:
        end = truth.t_s[0] + end_s
        keep = truth.t_s <= end
        samples = replace(samples, t_s=samples.t_s[keep], accel_mps2=samples.accel_mps2[keep])
        truth = type(truth)(*(getattr(truth, f.name)[keep] for f in fields(truth)))
        fixes = fixes.select(fixes.t_s <= end)
    return sim.config, samples, truth, fixes


def fault_trial(scn, run: int, fault: ChannelFault | None, watch_s: float) -> TrialOutcome:
    """Simulate run ``run`` of ``scn`` with ``fault`` and watch the tests for ``watch_s``
    after it (the whole flight without a fault)."""
    from filters.evaluate import run_errors
    from filters.pipeline import run_filter

    end_s = None if fault is None else fault.start_s + watch_s
    config, samples, truth, fixes = _watched(scn, run, () if fault is None else (fault,), end_s)
    failure = ""
    try:
        res = run_filter(samples, fixes, config, truth=truth)
    except CovarianceError as exc:
        res = getattr(exc, "partial", None)
        failure = str(exc).splitlines()[0]
        if res is None:
            return TrialOutcome(run, fault, np.nan, np.nan, (), "", 0, np.nan, 0.0, failure)
    t0 = float(samples.t_s[0])
    flight_s = float(res.estimates.t_s[-1] - res.estimates.t_s[0])
    hit = None
    false_alarms = 0
    for ev in res.faults:
        if fault is not None and fault.channel in ev.channels and hit is None:
            if ev.detected_at_s >= t0 + fault.start_s - 1e-9:
                hit = ev
                continue
        false_alarms += 1
    if hit is None:
        nothing = (np.nan, np.nan, (), "", false_alarms, np.nan, flight_s, failure)
        return TrialOutcome(run, fault, *nothing)
    # latencies from the first faulted sample
    start = float(samples.t_s[np.searchsorted(samples.t_s, t0 + fault.start_s - 1e-12)])
    sig = cost = np.nan
    if fault.kind == "drift":
        est = res.estimates
        j = min(int(np.searchsorted(est.t_s, hit.detected_at_s)), est.t_s.shape[0] - 1)
        err = run_errors(est, truth).att_ned_rad[j]
        sd = np.sqrt(np.diag(est.cov_nav[j][ATT, ATT]))
        sig = float(np.max(np.abs(err) / sd))
        c_config, c_samples, c_truth, c_fixes = _watched(scn, run, (), end_s)
        try:
            clean = run_filter(c_samples, c_fixes, c_config, truth=c_truth).estimates
        except CovarianceError:
            pass  # the fault-free twin failed too: no cost to measure (NaN, not counted)
        else:
            cost = attitude_cost_sigmas(est, clean, truth, float(est.t_s[j]))
    return TrialOutcome(
        run,
        fault,
        float(hit.detected_at_s - start),
        float(hit.isolated_at_s - start),
        hit.channels,
        hit.kind,
        false_alarms,
        sig,
        flight_s,
        failure,
        cost,
    )


#: The other kinds' default sizes (``dead`` and ``stuck`` take none).
DEFAULT_SIZES = {"dead": 0.0, "stuck": 0.0, "noisy": 10.0, "saturated": 1.0}


def _task(scn, tasks: list, watch_s: float, index: int) -> TrialOutcome:
    _kind, run, fault = tasks[index]
    return fault_trial(scn, run, fault, watch_s)


def _start_window(scn, watch_s: float) -> tuple[float, float]:
    """The span a trial's fault starts in, s from the run's first sample: from 15 s (a
    quarter of a shorter flight) to ``watch_s`` + 1 s before the flight's end."""
    duration = scn.plan().duration_s
    start_from, start_to = min(15.0, duration / 4), duration - watch_s - 1.0
    if start_to <= start_from:
        raise ValueError(f"the flight ({duration:g} s) is too short to watch {watch_s:g} s")
    return start_from, start_to


def _run_trials(
    task, n_tasks: int, workers: int, scheduler: str | None, progress: bool, desc: str
) -> list:
    """``task(i)`` for ``i`` in ``range(n_tasks)`` on the campaign's workers, in order."""
    from ngnav.campaign import run_campaign

    results: dict = {}
    failures = run_campaign(
        task,
        range(n_tasks),
        results.__setitem__,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        desc=desc,
    )
    if failures:
        raise RuntimeError(f"{len(failures)} trials raised; first: {failures[0].error}")
    return [results[i] for i in range(n_tasks)]


def fault_campaign(
    scn,
    kinds: tuple[str, ...],
    runs: int,
    clean_runs: int,
    *,
    drift_mps2_per_s: float = TRIAL_DRIFT_MPS2_PER_S,
    watch_s: float = 10.0,
    workers: int = 2,
    scheduler: str | None = None,
    progress: bool = False,
) -> dict:
    """Trials of every kind (``runs`` each, channels in turn) and ``clean_runs`` fault-free
    flights; the summary :func:`summarise_trials` gives."""
    from functools import partial

    from ngnav.layout import layout_by_name

    n = layout_by_name(scn.array.layout, scn.array.lever_arm_m).n_sensors
    start_from, start_to = _start_window(scn, watch_s)
    tasks: list[tuple[str, int, ChannelFault | None]] = []
    for kind in kinds:
        size = drift_mps2_per_s if kind == "drift" else DEFAULT_SIZES[kind]
        for run in range(runs):
            tasks.append((kind, run, trial_fault(kind, run, n, start_from, start_to, size)))
    tasks += [("none", run, None) for run in range(clean_runs)]
    trials = _run_trials(
        partial(_task, scn, tasks, watch_s), len(tasks), workers, scheduler, progress, "trials"
    )
    out = summarise_trials(trials, kinds)
    out.update(scenario=scn.name, runs=runs, clean_runs=clean_runs, watch_s=watch_s)
    out["drift_mps2_per_s"] = drift_mps2_per_s
    return out


def _stats(x: list[float]) -> dict:
    a = np.array([v for v in x if np.isfinite(v)])
    if a.size == 0:
        return {"n": 0, "median": None, "worst": None}
    return {"n": int(a.size), "median": float(np.median(a)), "worst": float(np.max(a))}


def summarise_trials(trials: list[TrialOutcome], kinds: tuple[str, ...]) -> dict:
    """Per kind: trials, detected, named right, isolated, latencies (s; median and worst),
    the drift's attitude error and cost at detection in sigmas (``within_3_sigma`` counts
    the cost); fault-free: flight hours and alarms."""
    out: dict = {"kinds": {}}
    for kind in kinds:
        tr = [t for t in trials if t.fault is not None and t.fault.kind == kind]
        det = [t for t in tr if np.isfinite(t.detected_s)]
        row = {
            "trials": len(tr),
            "detected": len(det),
            "isolated_right": sum(
                1 for t in det if np.isfinite(t.isolated_s) and t.named == (t.fault.channel,)
            ),
            "not_isolable": sum(
                1 for t in det if len(t.named) > 1 and not np.isfinite(t.isolated_s)
            ),
            "kind_right": sum(1 for t in det if t.kind == kind),
            "detection_s": _stats([t.detected_s for t in det]),
            "isolation_s": _stats([t.isolated_s for t in det]),
            "other_alarms": sum(t.false_alarms for t in tr),
            "stopped": sum(1 for t in tr if t.failure),
        }
        if kind == "drift":
            row["attitude_sigmas_at_detection"] = _stats([t.attitude_sigmas for t in det])
            cost = [t.attitude_cost_sigmas for t in det]
            row["attitude_cost_sigmas_at_detection"] = _stats(cost)
            row["within_3_sigma"] = sum(1 for s in cost if s <= 3.0)
        out["kinds"][kind] = row
    clean = [t for t in trials if t.fault is None]
    out["fault_free"] = {
        "flights": len(clean),
        "flight_hours": sum(t.flight_s for t in clean) / 3600.0,
        "alarms": sum(t.false_alarms for t in clean),
        "stopped": sum(1 for t in clean if t.failure),
    }
    return out


# ------------------------------------------------------------ two channels at once
@dataclass(frozen=True)
class PairOutcome:
    """One two-channel trial (times in s from the faults' start; NaN when it did not happen).

    Attributes
    ----------
    run : int
    faults : tuple of ChannelFault
        The two faults injected (one kind, one start).
    verdict : str
        What the parity's geometry says of the pair (:func:`filters.faults.pair_isolability`).
    detected_s : float
        Latency of the first event after the start, whichever channels it names.
    isolated : tuple of int
        Every channel an event isolated after the start (1-based, sorted).
    failure : str
        How the run stopped early ("" when it ran to its end).
    """

    run: int
    faults: tuple[ChannelFault, ...]
    verdict: str
    detected_s: float
    isolated: tuple[int, ...]
    failure: str = ""


def channel_pairs(n_channels: int) -> list[tuple[int, int]]:
    """Every pair of channels, 1-based, in order: (1, 2), (1, 3), ..., (N - 1, N)."""
    return [(i, j) for i in range(1, n_channels + 1) for j in range(i + 1, n_channels + 1)]


def pair_trial(
    scn, run: int, faults: tuple[ChannelFault, ...], verdict: str, watch_s: float
) -> PairOutcome:
    """Simulate run ``run`` of ``scn`` with two faults that start together, and watch the
    tests for ``watch_s`` after them."""
    from filters.pipeline import run_filter

    config, samples, truth, fixes = _watched(scn, run, faults, faults[0].start_s + watch_s)
    failure = ""
    try:
        res = run_filter(samples, fixes, config, truth=truth)
    except CovarianceError as exc:
        res = getattr(exc, "partial", None)
        failure = str(exc).splitlines()[0]
        if res is None:
            return PairOutcome(run, faults, verdict, np.nan, (), failure)
    t0 = float(samples.t_s[0])
    t_start = t0 + faults[0].start_s
    start = float(samples.t_s[np.searchsorted(samples.t_s, t_start - 1e-12)])
    after = [ev for ev in res.faults if ev.detected_at_s >= t_start - 1e-9]
    detected = min((ev.detected_at_s for ev in after), default=np.nan) - start
    isolated = sorted({c for ev in after if np.isfinite(ev.isolated_at_s) for c in ev.channels})
    return PairOutcome(run, faults, verdict, float(detected), tuple(isolated), failure)


def _pair_task(scn, tasks: list, watch_s: float, index: int) -> PairOutcome:
    _kind, run, faults, verdict = tasks[index]
    return pair_trial(scn, run, faults, verdict, watch_s)


def pair_campaign(
    scn,
    kinds: tuple[str, ...],
    runs: int,
    *,
    drift_mps2_per_s: float = TRIAL_DRIFT_MPS2_PER_S,
    watch_s: float = 10.0,
    workers: int = 2,
    scheduler: str | None = None,
    progress: bool = False,
) -> dict:
    """Two channels failing together: ``runs`` trials per kind (run ``i`` takes pair
    ``i mod N(N-1)/2`` of :func:`channel_pairs`, its start drawn as a single trial's), each
    with what the parity's geometry says of its pair; the summary
    :func:`summarise_pair_trials` gives."""
    from functools import partial

    from filters.faults import pair_isolability
    from ngnav.frontend import ArraySolver
    from ngnav.layout import layout_by_name

    layout = layout_by_name(scn.array.layout, scn.array.lever_arm_m)
    n = layout.n_sensors
    if n < 2:
        raise ValueError("two-channel trials need at least two channels")
    # the nominal layout's parity signatures: the solve's rate rows
    verdicts = pair_isolability(ArraySolver(layout).solve_matrix[6:])
    pairs = channel_pairs(n)
    start_from, start_to = _start_window(scn, watch_s)
    tasks: list[tuple[str, int, tuple[ChannelFault, ...], str]] = []
    for kind in kinds:
        size = drift_mps2_per_s if kind == "drift" else DEFAULT_SIZES[kind]
        for run in range(runs):
            a, b = pairs[run % len(pairs)]
            first = trial_fault(kind, run, n, start_from, start_to, size)
            faults = (replace(first, channel=a), replace(first, channel=b))
            tasks.append((kind, run, faults, verdicts[(a - 1, b - 1)]))
    trials = _run_trials(
        partial(_pair_task, scn, tasks, watch_s), len(tasks), workers, scheduler, progress,
        "pair trials",
    )  # fmt: skip
    out = summarise_pair_trials(trials, kinds)
    out.update(scenario=scn.name, runs=runs, watch_s=watch_s, drift_mps2_per_s=drift_mps2_per_s)
    out["verdicts"] = {
        v: [f"A{i + 1}+A{j + 1}" for (i, j), x in verdicts.items() if x == v]
        for v in sorted(set(verdicts.values()))
    }
    return out


def summarise_pair_trials(trials: list[PairOutcome], kinds: tuple[str, ...]) -> dict:
    """Per kind and verdict: trials, detected, latency (s; median and worst), both channels
    isolated and nothing else, a channel outside the pair isolated, filter stopped."""
    out: dict = {"pairs": {}}
    for kind in kinds:
        per: dict = {}
        for verdict in sorted({t.verdict for t in trials if t.faults[0].kind == kind}):
            tr = [t for t in trials if t.faults[0].kind == kind and t.verdict == verdict]
            det = [t for t in tr if np.isfinite(t.detected_s)]
            per[verdict] = {
                "trials": len(tr),
                "detected": len(det),
                "detection_s": _stats([t.detected_s for t in det]),
                "both_isolated": sum(
                    1 for t in tr if t.isolated == tuple(sorted(f.channel for f in t.faults))
                ),
                "wrong_isolated": sum(
                    1 for t in tr if set(t.isolated) - {f.channel for f in t.faults}
                ),
                "stopped": sum(1 for t in tr if t.failure),
            }
        out["pairs"][kind] = per
    return out
