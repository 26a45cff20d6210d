"""What served tuning the filter's consistency: controls, references, tails, cycles, sets.

``ngnav consistency`` (:mod:`filters.consistency`) judges the run-averaged NEES and
NIS against their 95 % chi-square bounds. This study runs the same Monte Carlo
runs (the same seeds, the same per-run statistics, so the same blocks) and adds
what told a fault in the filter from the criterion's own spread:

* the perfect-array and process-noise controls on each run's own fixes
  (:mod:`studies.control`), always: ``control`` (and ``control_from``);
* ``--reference``: the share a filter consistent by construction reaches on each
  block, from the statistic's correlation in time (:mod:`studies.share_reference`;
  measured with other jobs on the 2 cores: about 6 min added to ``tactical``'s 50 runs
  with ``--from``, 13 min to ``uav-survey``'s);
* ``--tails S``: the runs' own NEES values against chi-square's quantiles by window
  (:func:`nees_tails`): a scale error or a heavy tail;
* ``--cycle S``: the NEES blocks by phase within a repeating cycle (:func:`nees_cycle`);
* ``--sets K``: K disjoint sets of ``--runs`` runs, each judged on its own as the
  50-run target judges one (:func:`set_shares`): how often the target holds on a
  fresh draw of runs.

Run from the repository root: ``python -m studies.consistency --scenario tactical
--runs 50 --from 10 --reference``.
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from filters.consistency import (
    block_series,
    finite_mean,
    monte_carlo_runs,
    nees_dims,
    summarise_block,
    summarise_blocks,
    summarise_runs,
)
from filters.evaluate import TARGET_SHARE, chi2_bounds
from ngnav.sim.flight_scenario import FlightScenario
from studies.control import control_extras
from studies.share_reference import consistent_share


def control_series(
    results: list[dict], from_s: float | None = None
) -> dict[str, tuple[list[np.ndarray], int]]:
    """The controls' per-run NEES from ``from_s`` s on (all fixes if None), with their dof.

    ``pos`` and ``vel`` (the perfect-array control) and ``pos-pn``, ``vel-pn`` (with
    process noise, :func:`studies.control.process_noise_control`) when every run
    carries them.
    """
    names = ["pos", "vel"] + [
        k for k in ("pos-pn", "vel-pn") if all(f"control_{k}" in r for r in results)
    ]
    out = {}
    for name in names:
        key = f"control_{name}"
        per_run = [
            r[key] if from_s is None else r[key][r["control_t_s"] >= from_s] for r in results
        ]
        out[name] = (per_run, 3)
    return out


def control_blocks(results: list[dict], runs: int, from_s: float | None = None) -> dict:
    """The controls' NEES over the runs (:func:`control_series`), each summarised as
    :func:`filters.consistency.summarise_block` summarises a block."""
    return {
        name: summarise_block(per_run, dim, runs)[0]
        for name, (per_run, dim) in control_series(results, from_s).items()
    }


def add_reference(blocks: dict, series: dict[str, tuple[list[np.ndarray], int]]) -> None:
    """Add ``consistent_share`` to each block (:func:`studies.share_reference.consistent_share`
    on its per-run series), given two or more runs."""
    for name, (per_run, dim) in series.items():
        if len(per_run) >= 2:
            blocks[name]["consistent_share"] = asdict(consistent_share(np.vstack(per_run), dim))


#: Quantiles :func:`nees_tails` compares with chi-square's.
TAIL_QUANTILES = (0.5, 0.95, 0.99)


def nees_tails(t_s: np.ndarray, per_run: np.ndarray, dim: int, window_s: float) -> list[dict]:
    """How the runs' own NEES values spread, window by window, against chi-square's.

    The share criterion reads the run average at each epoch; it cannot tell a
    covariance too large or too small by a factor (every run's NEES scaled) from a
    covariance right for most runs but far too small for a few (a heavy tail: the
    average pushed up by those few while the typical run reads low). This tells
    them apart. ``per_run`` (R, E) holds each run's NEES of a ``dim``-dof block at
    the epochs ``t_s`` (E,); over each window of ``window_s`` s the values of all
    runs and epochs are pooled (a sample of the window's marginal distribution;
    the epochs are correlated in time, which widens its sampling error but does
    not bias it), and each row holds ``t0_s``, ``t1_s``, ``n`` (finite values),
    ``mean_ratio`` (their mean over ``dim``), ``q<p>_ratio`` for each of
    :data:`TAIL_QUANTILES` (their quantile over chi-square's with ``dim`` dof) and
    ``var_ratio`` (their variance over ``2 dim``). A consistent filter reads 1
    throughout; a scale error moves every ratio alike; a heavy tail reads a median
    ratio below 1 with the 0.99 ratio and the variance ratio above it.
    """
    from scipy.stats import chi2

    if not (np.isfinite(window_s) and window_s > 0):
        raise ValueError(f"tails window must be a positive number of seconds, got {window_s}")
    per_run = np.asarray(per_run, dtype=float)
    if per_run.ndim != 2 or per_run.shape[1] != t_s.shape[0]:
        raise ValueError(
            f"per_run must be (runs, {t_s.shape[0]} epochs), got shape {per_run.shape}"
        )
    ref = {q: float(chi2.ppf(q, dim)) for q in TAIL_QUANTILES}
    rows = []
    for t0 in np.arange(t_s[0], t_s[-1] + 1e-9, window_s):
        m = (t_s >= t0) & (t_s < t0 + window_s)
        vals = per_run[:, m].ravel()
        vals = vals[np.isfinite(vals)]
        if vals.size < 2:
            continue
        row = {
            "t0_s": float(t0),
            "t1_s": float(t0 + window_s),
            "n": int(vals.size),
            "mean_ratio": float(vals.mean() / dim),
        }
        qs = np.quantile(vals, list(TAIL_QUANTILES))
        for q, v in zip(TAIL_QUANTILES, qs, strict=True):
            row[f"q{q:g}_ratio"] = float(v / ref[q])
        row["var_ratio"] = float(vals.var(ddof=1) / (2.0 * dim))
        rows.append(row)
    return rows


def nees_cycle(
    t_s: np.ndarray,
    averages: dict[str, np.ndarray],
    cycle_s: float,
    bounds: dict[str, tuple[float, float]],
) -> list[dict]:
    """The run-averaged NEES blocks by phase within a repeating cycle of ``cycle_s`` s.

    Epochs ``t_s`` (E,) are grouped by ``(t - t_s[0]) mod cycle_s``, on the epoch
    grid (the median epoch spacing); each row holds the phase ``phase_s``, every
    block's mean over the epochs at that phase and, for each block in ``bounds``
    (name to its ``(lower, upper)``), the shares of those epochs below and above
    (``<name>_below``, ``<name>_above``). A filter whose statistic dips or peaks at
    one phase of its measurement cycle (``filters.pipeline`` makes the body-velocity
    updates at 5 Hz: a 0.2 s cycle) shows where within the cycle its covariance and
    its errors part.
    """
    if not (np.isfinite(cycle_s) and cycle_s > 0):
        raise ValueError(f"cycle must be a positive number of seconds, got {cycle_s}")
    if t_s.shape[0] < 2:
        raise ValueError("a cycle profile needs at least two epochs")
    dt = float(np.median(np.diff(t_s)))
    n = round(cycle_s / dt)
    if n < 2 or abs(n * dt - cycle_s) > 1e-6 * cycle_s + 1e-9:
        raise ValueError(
            f"cycle {cycle_s:g} s is not a whole number (>= 2) of the {dt:g} s epoch spacing"
        )
    phase = np.rint((t_s - t_s[0]) / dt).astype(int) % n
    rows = []
    for k in range(n):
        m = phase == k
        row: dict = {"phase_s": k * dt}
        for name, v in averages.items():
            row[name] = float(finite_mean(v[m]))
            if name in bounds:
                lo, hi = bounds[name]
                vals = v[m][np.isfinite(v[m])]
                row[f"{name}_below"] = float(np.mean(vals < lo)) if vals.size else float("nan")
                row[f"{name}_above"] = float(np.mean(vals > hi)) if vals.size else float("nan")
        rows.append(row)
    return rows


def set_shares(
    results: list[dict],
    dims: dict[str, int],
    per_set: int,
    sets: int,
    from_s: float | None = None,
) -> list[dict]:
    """Each disjoint set's share of epochs inside the bounds, block by block.

    Set ``j`` holds the runs with indices ``j * per_set .. (j + 1) * per_set - 1``
    that did not diverge (``runs`` says how many), judged against the bounds for its
    own run count. Each row: ``set``, ``first_run``, ``last_run`` (the set's index
    range), ``runs`` (those averaged), ``share_inside``
    (block name to share, 0-1), ``control_share_inside`` (the perfect-array control's
    ``pos`` and ``vel``, :mod:`studies.control`) and, with ``from_s``, both again
    from then on (``share_inside_from``, ``control_share_inside_from``).
    """
    rows = []
    for j in range(sets):
        lo, hi = j * per_set, (j + 1) * per_set
        members = [r for r in results if lo <= r["run"] < hi]
        row: dict = {"set": j, "first_run": lo, "last_run": hi - 1, "runs": len(members)}
        if not members:
            rows.append(row)
            continue
        for key, since in (("", None), ("_from", from_s)):
            if key and from_s is None:
                continue
            blocks = summarise_blocks(members, dims, len(members), since)[0]
            row[f"share_inside{key}"] = {k: v["share_inside"] for k, v in blocks.items()}
            control = control_blocks(members, len(members), since)
            row[f"control_share_inside{key}"] = {k: v["share_inside"] for k, v in control.items()}
        rows.append(row)
    return rows


def consistency_study(
    scn: FlightScenario,
    runs: int,
    method: str | None = None,
    workers: int = 2,
    progress: bool = False,
    profile_s: float | None = None,
    from_s: float | None = None,
    reference: bool = False,
    sets: int = 1,
    cycle_s: float | None = None,
    tails_s: float | None = None,
    scheduler: str | None = None,
) -> dict:
    """:func:`filters.consistency.consistency`'s report with the study's additions.

    The runs carry the controls (:func:`studies.control.control_extras`); the report
    adds ``control`` (and with ``from_s`` ``control_from``): the controls' NEES as a
    block is summarised, the criterion's reading, on this draw, of a filter consistent
    by construction.
    ``reference`` adds to every block (the controls' too) ``consistent_share``
    (:func:`add_reference`).
    ``tails_s`` adds ``tails``: per NEES block, :func:`nees_tails` over windows of that
    many seconds.
    ``cycle_s`` adds ``cycle``: :func:`nees_cycle` with the joint's bounds.
    ``sets`` > 1 runs ``sets`` disjoint sets of ``runs`` runs (run indices
    ``0 .. sets * runs - 1``, set ``j`` the ``j``-th ``runs`` of them) and adds
    ``sets`` (:func:`set_shares`) and ``sets_meeting_target``, how many have every
    block and NIS inside on >= 90 % of epochs. ``blocks`` and the rest then cover all
    the runs.
    """
    method = method or scn.compensation.method
    if runs < 1:
        raise ValueError(f"runs must be at least 1, got {runs}")
    if sets < 1:
        raise ValueError(f"sets must be at least 1, got {sets}")
    if tails_s is not None and not (np.isfinite(tails_s) and tails_s > 0):
        raise ValueError(f"tails window must be a positive number of seconds, got {tails_s}")
    if cycle_s is not None and not (np.isfinite(cycle_s) and cycle_s > 0):
        raise ValueError(f"cycle must be a positive number of seconds, got {cycle_s}")
    results, diverged = monte_carlo_runs(
        scn, runs * sets, method, workers, progress, extras=control_extras, scheduler=scheduler
    )
    out, averages = summarise_runs(scn.name, method, results, diverged, profile_s, from_s)
    out["first_run"] = 0  # the study splits runs 0 .. runs * sets - 1 into its sets
    n = out["runs"]
    dims = nees_dims(results)
    out["control"] = control_blocks(results, n)
    if from_s is not None:
        out["control_from"] = control_blocks(results, n, from_s)
    if reference:
        add_reference(out["blocks"], block_series(results, dims))
        add_reference(out["control"], control_series(results))
        if from_s is not None:
            add_reference(out["blocks_from"], block_series(results, dims, from_s))
            add_reference(out["control_from"], control_series(results, from_s))
    t0 = results[0]["t_s"]
    if tails_s is not None:
        out["tails"] = {
            name: nees_tails(t0, np.stack([r["nees"][name] for r in results]), dim, tails_s)
            for name, dim in dims.items()
        }
    if cycle_s is not None:
        out["cycle"] = nees_cycle(t0, averages, cycle_s, {"all": chi2_bounds(dims["all"], n)})
    if sets > 1:
        out["sets"] = set_shares(results, dims, runs, sets, from_s)
        out["sets_meeting_target"] = sum(
            "share_inside" in row and all(v >= TARGET_SHARE for v in row["share_inside"].values())
            for row in out["sets"]
        )
    return out


# ---------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> int:
    """``python -m studies.consistency`` with ``ngnav consistency``'s options and the study's."""
    import argparse
    import sys

    from ngnav.cli import add_flight_args
    from ngnav.cli.assess import add_consistency_args

    p = argparse.ArgumentParser(
        prog="python -m studies.consistency",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_flight_args(p)
    add_consistency_args(p, first=False)
    p.add_argument(
        "--tails",
        type=float,
        metavar="S",
        help="also print, over windows of S seconds, the runs' own joint NEES against "
        "chi-square's quantiles: a covariance off by a scale or right but for a few runs",
    )
    p.add_argument(
        "--cycle",
        type=float,
        metavar="S",
        help="also print each NEES block's run average by phase within a cycle of S seconds "
        "(0.2: the 5 Hz body-velocity updates), with the joint's shares below and above",
    )
    p.add_argument(
        "--reference",
        action="store_true",
        help="also print the share a consistent filter would reach on each block, from the "
        "statistic's correlation in time (studies.share_reference; slower)",
    )
    p.add_argument(
        "--sets",
        type=int,
        default=1,
        metavar="K",
        help="run K disjoint sets of --runs runs and also print each set's shares on its "
        "own: how often the target holds on a fresh draw (default: %(default)s)",
    )
    args = p.parse_args(argv)
    try:
        return _report(args)
    except ValueError as exc:
        print(f"studies.consistency: error: {exc}", file=sys.stderr)
        return 2


def _report(args) -> int:
    import json

    from ngnav.cli import flight_scenario, show_progress
    from ngnav.cli.assess import (
        block_line,
        consistency_header,
        print_profile,
        print_run_summary,
        target_line,
    )

    out = consistency_study(
        flight_scenario(args),
        args.runs,
        args.method,
        args.workers,
        progress=show_progress() and not args.json,
        profile_s=args.profile,
        from_s=args.from_s,
        reference=args.reference,
        sets=args.sets,
        cycle_s=args.cycle,
        scheduler=args.scheduler,
        tails_s=args.tails,
    )
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(consistency_header(out))
    sections = [("", out["blocks"], out["control"])]
    if "blocks_from" in out:
        sections.append(
            (f"  from {out['from_s']:g} s on:", out["blocks_from"], out["control_from"])
        )
    for title, blocks, control in sections:
        if title:
            print(title)
        control_rows = {f"control {k}": v for k, v in control.items()}
        for name, b in {**blocks, **control_rows}.items():
            print(block_line(name, b))
            ref = b.get("consistent_share")
            if ref is not None:
                print(
                    f"  {'':14s} a consistent filter: median {100 * ref['median']:5.1f} %, "
                    f"5th percentile {100 * ref['p05']:5.1f} %, below 90 % in "
                    f"{100 * ref['prob_below_90']:4.1f} % of {ref['replicas']} run sets"
                )
    print(
        "  control pos/vel: NEES of a perfect-array filter on the same fixes (studies.control), "
        "consistent by construction; -pn: with process noise, a navigation filter's time course"
    )
    print(target_line(out))
    if "sets" in out:
        _print_sets(out["sets"], out["sets_meeting_target"])
    print_run_summary(out)
    if "profile" in out:
        print_profile(out["profile"])
    if "cycle" in out:
        _print_cycle(out["cycle"])
    if "tails" in out:
        _print_tails(out["tails"]["all"])
    return 0


def _print_sets(rows: list[dict], meeting: int) -> None:
    """The disjoint run sets' shares inside, one line per set (``--sets``)."""
    names = next((list(r["share_inside"]) for r in rows if "share_inside" in r), [])
    print(
        f"  each set of runs on its own: % of epochs inside; {meeting} of {len(rows)} sets "
        "have every block >= 90 % (whole run; ctl: the control's)"
    )
    heads = [n.replace("NEES ", "").replace("NIS ", "") for n in names] + ["ctl pos", "ctl vel"]
    print("    runs      " + " ".join(f"{h:>9s}" for h in heads))

    def cells(r: dict, key: str) -> str:
        vals = [r[f"share_inside{key}"][n] for n in names]
        vals += [r[f"control_share_inside{key}"][k] for k in ("pos", "vel")]
        return " ".join(f"{100 * v:9.1f}" for v in vals)

    for r in rows:
        if not r["runs"]:
            print(f"    set {r['set']}: every run diverged")
            continue
        short = "" if r["runs"] == r["last_run"] - r["first_run"] + 1 else f" ({r['runs']} runs)"
        print(f"    {r['first_run']:4d}-{r['last_run']:<4d} " + cells(r, "") + short)
        if "share_inside_from" in r:
            print("      from    " + cells(r, "_from"))


def _print_tails(rows: list[dict]) -> None:
    print(
        "  the joint NEES's spread over runs by window (studies.consistency.nees_tails): "
        "the runs' values against chi-square's (12 dof), 1 when consistent; every ratio "
        "alike: a scale error; median below 1 with the 0.99 quantile and variance above: "
        "a heavy tail (--json: every block)"
    )
    print("    window s          mean  median   q0.95   q0.99     var")
    for r in rows:
        print(
            f"    {r['t0_s']:6.1f}-{r['t1_s']:6.1f}  {r['mean_ratio']:6.2f}  {r['q0.5_ratio']:6.2f}"
            f"  {r['q0.95_ratio']:6.2f}  {r['q0.99_ratio']:6.2f}  {r['var_ratio']:6.2f}"
        )


def _print_cycle(rows: list[dict]) -> None:
    aoa = "aoa" in rows[0]
    print(
        "  run-averaged NEES by phase in the cycle (3 dof blocks, all: 12 dof"
        + (", aoa: 1 dof" if aoa else "")
        + "; all's share of those epochs below / above its bounds)"
    )
    print(
        "    phase s    pos    vel    att   rate     all"
        + ("    aoa" if aoa else "")
        + "   below  above"
    )
    for row in rows:
        print(
            f"    {row['phase_s']:7.3f} {row['pos']:6.2f} {row['vel']:6.2f} {row['att']:6.2f} "
            f"{row['rate']:6.2f} {row['all']:7.2f}"
            + (f" {row['aoa']:6.2f}" if aoa else "")
            + f"  {100 * row['all_below']:5.1f}% {100 * row['all_above']:5.1f}%"
        )


if __name__ == "__main__":
    raise SystemExit(main())
