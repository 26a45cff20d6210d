"""Monte Carlo consistency of the filter on a simulated scenario (``ngnav consistency``).

``consistency`` runs R Monte Carlo flights (``default_rng([seed, i])``, through
:func:`ngnav.sim.simulate.simulate_flight`) in parallel with dask and judges each
block's run-averaged NEES, and the NIS, against its two-sided 95 % chi-square
bounds. Its parts are public for the research built on it
(``python -m studies.consistency``): :func:`monte_carlo_runs` (with a hook that adds
to each run's record), :func:`block_series`, :func:`summarise_block`,
:func:`summarise_blocks` and :func:`summarise_runs`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from filters.evaluate import (
    TARGET_SHARE,
    aoa_nees,
    chi2_bounds,
    nees,
    run_errors,
    share_inside,
)
from filters.pipeline import run_filter
from filters.smoother import RESTARTS
from ngnav.errors import CovarianceError
from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.simulate import SimulatedRun, simulate_flight

#: A hook adding entries to a run's record: ``(simulated run, run index) -> dict``. It
#: must be picklable (a module-level function) to run in dask's worker processes.
RunExtras = Callable[[SimulatedRun, int], dict]


def one_run(
    scn: FlightScenario,
    i: int,
    method: str,
    extras: RunExtras | None = None,
    smooth: bool = False,
) -> dict:
    """Run ``i`` of the Monte Carlo set: the filter's NEES per block and NIS per epoch.

    Returns ``{"run": i, "diverged": reason}`` when the covariance check fails;
    otherwise the run's record (``nees`` per block at the epochs ``t_s``; GPS NIS at
    ``t_fix_s``, the glitched fixes NaN; the rate NIS at ``rate_t_s``; ``att_rms_deg``
    and ``rate_rms_dps``), with ``extras(sim, i)``'s entries added when given. With
    ``smooth`` the NEES and RMS are the smoothed estimates' (no angle of attack), and
    ``filter_att_rms_deg`` and ``filter_rate_rms_dps`` the filter's; the NIS stay the
    filter's own.
    """
    sim = simulate_flight(scn, i)
    try:
        res = run_filter(
            sim.samples,
            sim.fixes,
            sim.config,
            compensation=method,
            true_layout=sim.true_layout(),
            truth=sim.truth,
            smooth=smooth,
            lose_track_at_s=scn.lose_track_at_s,
        )
    except CovarianceError as exc:
        return {"run": i, "diverged": str(exc)}
    est = res.smoothed if smooth else res.estimates
    errs = run_errors(est, sim.truth)
    ne = {k: v.astype(np.float32) for k, v in nees(errs, est.cov_nav).items()}
    ne_aoa = aoa_nees(est, sim.truth)
    if ne_aoa is not None:
        ne["aoa"] = ne_aoa.astype(np.float32)
    inn = res.innovations
    keep = np.ones(inn.t_s.shape, dtype=bool)
    for tg in sim.fixes.t_s[sim.glitched]:
        keep &= np.abs(inn.t_s - tg) > 1e-9
    out = {
        "run": i,
        "nees": ne,
        "t_s": res.estimates.t_s,
        "nis_pos": np.where(keep, inn.nis_pos, np.nan),
        "nis_vel": inn.nis_vel,
        "t_fix_s": inn.t_s,
        "rate_nis": _rate_nis_as_full_dim(res),
        "rate_t_s": res.rate_nis_t_s,
        "rate_dim": res.rate_dim,
        **_rms(errs),
    }
    if res.track_losses:
        # each loss: how long until the estimates were valid again, s
        est = res.estimates
        out["valid_again_s"] = [
            float(est.t_s[(est.t_s > loss.lost_at_s) & est.valid][0] - loss.lost_at_s)
            if np.any((est.t_s > loss.lost_at_s) & est.valid)
            else float("nan")
            for loss in res.track_losses
        ]
    if smooth:
        filt = _rms(run_errors(res.estimates, sim.truth))
        out.update({f"filter_{k}": v for k, v in filt.items()})
        out["smoother_restarts"] = res.counts[RESTARTS]
    if extras is not None:
        out.update(extras(sim, i))
    return out


def _rms(errs) -> dict[str, float]:
    """Attitude (deg) and rate (deg/s) RMS of a run's errors, vector norms over the run
    (the empty epochs of a lost track left out)."""
    return {
        "att_rms_deg": float(np.rad2deg(np.sqrt(np.nanmean(np.sum(errs.att_ned_rad**2, axis=1))))),
        "rate_rms_dps": float(np.rad2deg(np.sqrt(np.nanmean(np.sum(errs.rate_b_rps**2, axis=1))))),
    }


def monte_carlo_runs(
    scn: FlightScenario,
    runs: int,
    method: str,
    workers: int = 2,
    progress: bool = False,
    extras: RunExtras | None = None,
    scheduler: str | None = None,
) -> tuple[list[dict], list[dict]]:
    """Runs ``0 .. runs - 1`` (:func:`one_run`) as a campaign (:func:`ngnav.campaign.run_campaign`:
    ``workers`` local processes, 1 here, or the dask cluster at ``scheduler``).

    Returns the records of the runs that did not diverge, in run order, and the
    diverged or failed ones as ``{"run", "reason"}``. Raises ValueError when no run
    finished or the runs' epochs differ (they cannot be averaged).
    """
    from ngnav.campaign import run_campaign

    done: dict[int, dict] = {}
    failures = run_campaign(
        partial(one_run, scn, method=method, extras=extras),
        range(runs),
        done.__setitem__,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        desc=f"consistency {method}",
    )
    records = [done[i] for i in sorted(done)]
    diverged = [{"run": r["run"], "reason": r["diverged"]} for r in records if "diverged" in r]
    diverged += [{"run": f.run, "reason": f"failed: {f.error}"} for f in failures]
    diverged.sort(key=lambda d: d["run"])
    results = [r for r in records if "diverged" not in r]
    if not results:
        raise ValueError(f"no Monte Carlo run finished: {diverged}")
    lengths = {r["t_s"].shape[0] for r in results}
    if len(lengths) != 1:
        raise ValueError("Monte Carlo runs produced different epochs; cannot average")
    return results, diverged


def finite_mean(x: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Mean of the finite values along ``axis``; NaN where there is none (no warning)."""
    ok = np.isfinite(x)
    n = ok.sum(axis=axis)
    total = np.where(ok, x, 0.0).sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _rate_nis_as_full_dim(res) -> np.ndarray:
    """The rate NIS with each value of fewer dof (channels excluded, the aided products out)
    carried to the full dimension's chi-square by its quantile: consistent values stay
    chi-square with ``rate_dim`` dof, so one band judges the whole run."""
    nis = np.asarray(res.rate_nis, dtype=float)
    dof = res.rate_nis_dof
    if dof is None or not np.any(dof != res.rate_dim):
        return nis
    out = nis.copy()
    few = dof != res.rate_dim
    out[few] = chi2.isf(chi2.sf(nis[few], dof[few]), res.rate_dim)
    return out


def _mean_se(run_means: np.ndarray) -> float:
    """Standard error of a block's mean statistic from its runs' own means over their
    epochs (R,): their spread over sqrt(R); NaN below two runs. The runs are
    independent, their epochs not: this counts each run once."""
    per_run = np.asarray(run_means)
    per_run = per_run[np.isfinite(per_run)]
    if per_run.shape[0] < 2:
        return float("nan")
    return float(np.std(per_run, ddof=1) / np.sqrt(per_run.shape[0]))


def summarise_block(per_run: list[np.ndarray], dim: int, runs: int) -> tuple[dict, np.ndarray]:
    """Run-averaged statistic of one block against its two-sided 95 % bounds.

    Returns the summary (with the shares below and above the bounds: a
    pessimistic filter falls below, an optimistic one above; ``mean_se``, the
    standard error of ``mean`` from the runs' spread) and the per-epoch
    average (E,).
    """
    stacked = np.vstack(per_run)
    avg = finite_mean(stacked, axis=0)
    return summarise_average(avg, finite_mean(stacked, axis=1), dim, runs), avg


def summarise_average(avg: np.ndarray, run_means: np.ndarray, dim: int, runs: int) -> dict:
    """:func:`summarise_block`'s summary from the per-epoch average (E,) over the runs
    and each run's own mean (R,): all it needs, so runs need not be kept."""
    lo, hi = chi2_bounds(dim, runs)
    ok = np.isfinite(avg)
    return {
        "dim": dim,
        "lower": lo,
        "upper": hi,
        "mean": float(finite_mean(avg)),
        "mean_se": _mean_se(run_means),
        "share_inside": share_inside(avg, dim, runs),
        "share_below": float(np.mean(avg[ok] < lo)),
        "share_above": float(np.mean(avg[ok] > hi)),
    }


#: The NEES blocks judged, name to degrees of freedom (``aoa``, 1, is added when the
#: runs carry the angle-of-attack state).
NEES_DIMS: dict[str, int] = {"pos": 3, "vel": 3, "att": 3, "rate": 3, "all": 12}


def nees_dims(results: list[dict]) -> dict[str, int]:
    """The NEES blocks of these runs, name to dof (:data:`NEES_DIMS`, ``aoa`` if present)."""
    dims = dict(NEES_DIMS)
    if "aoa" in results[0]["nees"]:
        dims["aoa"] = 1  # the angle-of-attack state (NaN where the truth has none)
    return dims


def block_series(
    results: list[dict], dims: dict[str, int], from_s: float | None = None
) -> dict[str, tuple[list[np.ndarray], int]]:
    """Every block's per-run series from ``from_s`` s on (all epochs if None) and its dof.

    The NEES blocks (``dims``: name to dof) as ``NEES <name>``, then ``NIS gps pos``,
    ``NIS gps vel`` and, when the runs have rate products, ``NIS rate``.
    """

    def since(values: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        return values if from_s is None else values[t_s >= from_s]

    out = {}
    for name, d in dims.items():
        out[f"NEES {name}"] = ([since(r["nees"][name], r["t_s"]) for r in results], d)
    for key, d in (("nis_pos", 3), ("nis_vel", 3)):
        out[f"NIS gps {key[4:]}"] = ([since(r[key], r["t_fix_s"]) for r in results], d)
    nq = results[0]["rate_dim"]
    if nq:
        out["NIS rate"] = ([since(r["rate_nis"], r["rate_t_s"]) for r in results], nq)
    return out


def summarise_blocks(
    results: list[dict], dims: dict[str, int], runs: int, from_s: float | None = None
) -> tuple[dict, dict[str, np.ndarray]]:
    """Every block of :func:`block_series` summarised by :func:`summarise_block`; and the
    NEES blocks' per-epoch averages (by their names in ``dims``)."""
    blocks, averages = {}, {}
    for name, (per_run, d) in block_series(results, dims, from_s).items():
        blocks[name], avg = summarise_block(per_run, d, runs)
        if name.startswith("NEES "):
            averages[name[5:]] = avg
    return blocks, averages


def nees_profile(t_s: np.ndarray, averages: dict[str, np.ndarray], window_s: float) -> list[dict]:
    """Mean of each run-averaged NEES block over consecutive windows of ``window_s`` s.

    ``averages`` maps block names to per-epoch averages (E,) at the times
    ``t_s`` (E,). Each row holds the window ``[t0_s, t1_s)`` and the block means:
    where in a flight a filter is optimistic or pessimistic.
    """
    if not (np.isfinite(window_s) and window_s > 0):
        raise ValueError(f"profile window must be a positive number of seconds, got {window_s}")
    rows = []
    for t0 in np.arange(t_s[0], t_s[-1] + 1e-9, window_s):
        m = (t_s >= t0) & (t_s < t0 + window_s)
        if np.any(m):
            rows.append(
                {
                    "t0_s": float(t0),
                    "t1_s": float(t0 + window_s),
                    **{k: float(finite_mean(v[m])) for k, v in averages.items()},
                }
            )
    return rows


def target_verdict(blocks: dict[str, dict]) -> dict:
    """Issue 3's consistency target on one set of blocks: every NEES block and NIS inside
    its bounds on >= :data:`TARGET_SHARE` of epochs.

    Returns ``{"share": TARGET_SHARE, "met": bool, "misses": {name: share_inside}}``,
    ``misses`` holding the blocks below the share (empty when met).
    """
    misses = {
        name: b["share_inside"] for name, b in blocks.items() if b["share_inside"] < TARGET_SHARE
    }
    return {"share": TARGET_SHARE, "met": not misses, "misses": misses}


def summarise_runs(
    scenario: str,
    method: str,
    results: list[dict],
    diverged: list[dict],
    profile_s: float | None = None,
    from_s: float | None = None,
) -> tuple[dict, dict[str, np.ndarray]]:
    """The report of :func:`consistency` on runs of :func:`monte_carlo_runs`, and the NEES
    blocks' per-epoch averages over the whole run."""
    runs = len(results)
    out: dict = {
        "scenario": scenario,
        "runs": runs,
        "method": method,
        "from_s": from_s,
        "diverged": diverged,
    }
    dims = nees_dims(results)
    out["blocks"], averages = summarise_blocks(results, dims, runs)
    if from_s is not None:
        out["blocks_from"] = summarise_blocks(results, dims, runs, from_s)[0]
    if profile_s is not None:
        out["profile"] = nees_profile(results[0]["t_s"], averages, profile_s)
    out["target"] = target_verdict(out["blocks"])
    out["att_rms_deg_median"] = float(np.median([r["att_rms_deg"] for r in results]))
    return out, averages


class RunningSummary:
    """:func:`summarise_runs`'s report built as runs arrive, without keeping them.

    Each block keeps its per-epoch sum and count of finite values (float64) and each
    run's own mean: a campaign of thousands of runs holds one run at a time. With
    ``save_dir`` each run's record is written there as it arrives
    (``run_NNNNN.npz``: its NEES blocks, NIS and times), so the raw series stay for
    later study.
    """

    def __init__(self, from_s: float | None = None, save_dir: str | Path | None = None):
        self.from_s = from_s
        self.save_dir = None if save_dir is None else Path(save_dir)
        if self.save_dir is not None:
            self.save_dir.mkdir(parents=True, exist_ok=True)
        self.t_s: np.ndarray | None = None
        self.dims: dict[str, int] | None = None
        self._sums: dict[str, np.ndarray] = {}
        self._counts: dict[str, np.ndarray] = {}
        self._means: dict[str, dict[int, float]] = {}
        self._means_from: dict[str, dict[int, float]] = {}
        self._kept_from: dict[str, np.ndarray] = {}
        self._att: dict[int, float] = {}
        self._smoothing: dict[int, tuple[float, float, int]] = {}  # att, rate ratio; restarts
        self._valid_again: list[float] = []  # per track loss: s until valid again
        self._rate_dim = 0
        self.diverged: list[dict] = []

    def add(self, i: int, rec: dict) -> None:
        """Take run ``i``'s record (:func:`one_run`)."""
        if "diverged" in rec:
            self.diverged.append({"run": i, "reason": rec["diverged"]})
            return
        if self.t_s is None:
            self.t_s, self.dims, self._rate_dim = rec["t_s"], nees_dims([rec]), rec["rate_dim"]
            if self.from_s is not None:
                # the epochs from from_s on, by each block's own times (as block_series)
                times = {"NIS gps pos": rec["t_fix_s"], "NIS gps vel": rec["t_fix_s"]}
                times["NIS rate"] = rec["rate_t_s"]
                for name in block_series([rec], self.dims):
                    self._kept_from[name] = times.get(name, rec["t_s"]) >= self.from_s
        elif rec["t_s"].shape != self.t_s.shape:
            raise ValueError("Monte Carlo runs produced different epochs; cannot average")
        for name, ([values], _) in block_series([rec], self.dims).items():
            v = np.asarray(values, dtype=np.float64)
            ok = np.isfinite(v)
            if name not in self._sums:
                self._sums[name] = np.zeros(v.shape)
                self._counts[name] = np.zeros(v.shape, dtype=np.int64)
                self._means[name], self._means_from[name] = {}, {}
            self._sums[name] += np.where(ok, v, 0.0)
            self._counts[name] += ok
            self._means[name][i] = float(finite_mean(values))
            if self.from_s is not None:
                self._means_from[name][i] = float(finite_mean(values[self._kept_from[name]]))
        self._att[i] = rec["att_rms_deg"]
        self._valid_again += rec.get("valid_again_s", [])
        if "filter_att_rms_deg" in rec:
            self._smoothing[i] = (
                rec["att_rms_deg"] / rec["filter_att_rms_deg"],
                rec["rate_rms_dps"] / rec["filter_rate_rms_dps"],
                rec["smoother_restarts"],
            )
        if self.save_dir is not None:
            flat = {f"nees_{k}": v for k, v in rec["nees"].items()}
            for key in ("t_s", "nis_pos", "nis_vel", "t_fix_s", "rate_nis", "rate_t_s"):
                flat[key] = rec[key]
            flat["att_rms_deg"] = np.array(rec["att_rms_deg"])
            np.savez_compressed(self.save_dir / f"run_{i:05d}.npz", **flat)

    def fail(self, failures: list) -> None:
        """Record runs that raised (:class:`ngnav.campaign.RunFailure`)."""
        self.diverged += [{"run": f.run, "reason": f"failed: {f.error}"} for f in failures]

    def _blocks(self, from_epochs: bool) -> tuple[dict, dict[str, np.ndarray]]:
        runs = len(self._att)
        blocks, averages = {}, {}
        for name, total in self._sums.items():
            count = self._counts[name]
            with np.errstate(invalid="ignore", divide="ignore"):
                avg = np.where(count > 0, total / np.maximum(count, 1), np.nan)
            means = self._means_from[name] if from_epochs else self._means[name]
            if from_epochs:
                avg = avg[self._kept_from[name]]
            run_means = np.array([means[i] for i in sorted(means)])
            blocks[name] = summarise_average(avg, run_means, self._dim(name), runs)
            if name.startswith("NEES "):
                averages[name[5:]] = avg
        return blocks, averages

    def _dim(self, name: str) -> int:
        if name.startswith("NEES "):
            return self.dims[name[5:]]
        return 3 if name.startswith("NIS gps") else self._rate_dim

    def summary(
        self, scenario: str, method: str, profile_s: float | None = None
    ) -> tuple[dict, dict[str, np.ndarray]]:
        """The report of :func:`summarise_runs` and the NEES blocks' per-epoch averages."""
        if not self._att:
            raise ValueError(f"no Monte Carlo run finished: {sorted(self.diverged, key=_run)}")
        out: dict = {
            "scenario": scenario,
            "runs": len(self._att),
            "method": method,
            "from_s": self.from_s,
            "diverged": sorted(self.diverged, key=_run),
        }
        out["blocks"], averages = self._blocks(False)
        if self.from_s is not None:
            out["blocks_from"] = self._blocks(True)[0]
        if profile_s is not None:
            out["profile"] = nees_profile(self.t_s, averages, profile_s)
        out["target"] = target_verdict(out["blocks"])
        out["att_rms_deg_median"] = float(np.median([self._att[i] for i in sorted(self._att)]))
        if self._valid_again:
            va = np.array(self._valid_again)
            out["track_losses"] = {
                "count": int(va.size),
                "valid_again_s_median": float(np.nanmedian(va)),
                "valid_again_s_max": float(np.max(va)),
            }
        if self._smoothing:
            att, rate, restarts = np.array(list(self._smoothing.values())).T
            out["smoothed"] = {
                "att_rms_ratio_median": float(np.median(att)),
                "att_rms_ratio_max": float(np.max(att)),
                "rate_rms_ratio_median": float(np.median(rate)),
                "rate_rms_ratio_max": float(np.max(rate)),
                "restarts": int(restarts.sum()),
            }
        return out, averages


def _run(d: dict) -> int:
    return d["run"]


def consistency(
    scn: FlightScenario,
    runs: int,
    method: str | None = None,
    workers: int = 2,
    progress: bool = False,
    profile_s: float | None = None,
    from_s: float | None = None,
    scheduler: str | None = None,
    save_dir: str | Path | None = None,
    smooth: bool = False,
    first: int = 0,
) -> dict:
    """NEES/NIS over ``runs`` Monte Carlo runs (``first`` to ``first + runs - 1``: another
    ``first`` is another draw of the same scenario); share of epochs inside the 95 % bounds.

    Runs execute as a campaign on dask.distributed (:func:`monte_carlo_runs`: ``workers``
    local processes, 1 in this process, or the cluster at ``scheduler``). Glitched fixes
    are left out of the NIS (they are meant to fail it). A run whose covariance check fails
    is listed under ``diverged`` and left out of the averages (``runs`` counts
    the runs averaged): a divergence is a result to report, not a crash.
    ``blocks`` holds each NEES block and NIS (:func:`summarise_block`).
    ``from_s`` adds ``blocks_from``: every block's statistics over the epochs from
    that time (s) on (to judge a filter after a start-up transient); ``blocks`` and
    the profile cover the whole run.
    ``profile_s`` adds ``profile``: the NEES blocks' means over windows of that
    many seconds (:func:`nees_profile`).
    ``target`` is the target's verdict on ``blocks`` (:func:`target_verdict`).
    ``smooth`` judges the smoothed estimates (:func:`one_run`) and adds ``smoothed``:
    the median and worst ratios of their attitude and rate RMS to the filter's.
    """
    return consistency_series(
        scn, runs, method, workers, progress, profile_s, from_s, scheduler, save_dir, smooth, first
    )[0]


def consistency_series(
    scn: FlightScenario,
    runs: int,
    method: str | None = None,
    workers: int = 2,
    progress: bool = False,
    profile_s: float | None = None,
    from_s: float | None = None,
    scheduler: str | None = None,
    save_dir: str | Path | None = None,
    smooth: bool = False,
    first: int = 0,
) -> tuple[dict, np.ndarray, dict[str, np.ndarray]]:
    """:func:`consistency`'s report, the epochs' times (E,) and each NEES block's
    per-epoch average over the runs (E,): what ``ngnav consistency --plot`` draws.

    The runs are summarised as they arrive (:class:`RunningSummary`), one at a time in
    memory; ``save_dir`` also writes each run's record there.
    """
    from ngnav.campaign import run_campaign

    method = method or scn.compensation.method
    if runs < 1:
        raise ValueError(f"runs must be at least 1, got {runs}")
    if first < 0:
        raise ValueError(f"the first run's index must be at least 0, got {first}")
    acc = RunningSummary(from_s, save_dir)
    failures = run_campaign(
        partial(one_run, scn, method=method, smooth=smooth),
        range(first, first + runs),
        acc.add,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        desc=f"consistency {method}",
    )
    acc.fail(failures)
    out, averages = acc.summary(scn.name, method, profile_s)
    out["first_run"] = first
    return out, acc.t_s, averages
