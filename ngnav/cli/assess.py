"""Judging the filter on simulated flights: ``ngnav evaluate``, ``consistency``, ``faults``.

The report lines of ``consistency`` are public (:func:`consistency_header`,
:func:`block_line`, :func:`target_line`, :func:`print_run_summary`,
:func:`print_profile`): ``python -m studies.consistency`` prints its research
beside them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ngnav.cli import add_flight_args, flight_scenario, show_progress
from ngnav.sim.faults import TRIAL_DRIFT_MPS2_PER_S


def cmd_evaluate(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from filters.comparison import evaluate_scenario, summary_dict

    scn = flight_scenario(args)
    out = evaluate_scenario(scn, args.run_index, progress=show_progress() and not args.json)
    if args.json:
        print(json.dumps({**out, "rows": [summary_dict(r) for r in out["rows"]]}, indent=2))
        return 0
    print(
        f"{out['scenario']} run {args.run_index}, sensor {out['sensor']}, "
        f"GPS {out['gps_rate_hz']:g} Hz; raw GPS horizontal RMS {out['raw_gps_horiz_rms_m']:.3f} m"
    )
    cols = [
        ("horiz_rms_m", "horiz_max_m", "horiz m"),
        ("vert_rms_m", "vert_max_m", "vert m"),
        ("vel_rms_mps", "vel_max_mps", "vel m/s"),
        ("roll_rms_deg", "roll_max_deg", "roll deg"),
        ("pitch_rms_deg", "pitch_max_deg", "pitch deg"),
        ("yaw_rms_deg", "yaw_max_deg", "yaw deg"),
        ("rate_rms_dps", "rate_max_dps", "rate deg/s"),
    ]
    print(f"  {'RMS / worst':14s}" + "".join(f"{c[2]:>20s}" for c in cols))
    for r in out["rows"]:
        if r.failure:
            print(f"  {r.name:14s}  {r.failure}")
            continue
        d = asdict(r.summary)
        print(f"  {r.name:14s}" + "".join(f"{d[a]:>9.3f} / {d[b]:<8.3f}" for a, b, _ in cols))
        if r.bound:
            print(
                f"  {'  bound (RMS)':14s}"
                + "".join(f"{r.bound[a]:>9.3f}{'':11s}" for a, _, _ in cols)
            )
    for line in evaluation_lines(out):
        print(f"  {line}")
    return 0


def evaluation_lines(out: dict) -> list[str]:
    """The run's events and accuracy figures below the table, as sentences (``--json``
    keeps them as numbers)."""
    lines = []
    for name, ev in out.get("events", {}).items():
        if name == "outage":
            rec = ev["recovered_within_3sigma_after_s"]
            back = (
                f"position and velocity inside 3 sigma again {rec:.1f} s after it"
                if rec is not None
                else "not inside 3 sigma again by the run's end"
            )
            lines.append(
                f"GPS outage to {ev['end_s']:.1f} s: horizontal error {ev['horiz_err_at_end_m']:.2f} m "
                f"at its end, {back}; horizontal RMS outside it "
                f"{ev['horiz_rms_outside_outage_m']:.3f} m"
            )
        else:  # a glitched fix
            verdict = "rejected" if ev["rejected"] else "ACCEPTED"
            lines.append(
                f"{name}: {verdict} (NIS {ev['nis']:.1f}), the estimate moved {ev['moved_m']:.2f} m "
                f"beside a horizontal sigma of {ev['sigma_m']:.2f} m"
            )
    t = out.get("targets", {})
    if "horiz_rms_over_raw_gps" in t:
        outside = t.get("horiz_rms_over_raw_gps_outside_outage")
        lines.append(
            f"gm11 horizontal RMS over the raw GPS's: {t['horiz_rms_over_raw_gps']:.3f}"
            + (f" ({outside:.3f} outside the outage)" if outside is not None else "")
        )
    if "att_rms_over_bound" in t:
        lines.append(f"gm11 attitude RMS over its bound: {t['att_rms_over_bound']:.2f}")
    gap = t.get("gm11_gap_closed")
    if isinstance(gap, str):
        lines.append(
            "no compensation diverged: no whole-run attitude gap between it and the true "
            "geometry (oracle) for gm11 to close"
        )
    elif gap is not None:
        lines.append(
            f"share of the attitude RMS gap between no compensation and the true geometry "
            f"(oracle) that gm11 closes: {gap:.2f}"
        )
    before = t.get("gm11_gap_closed_before_divergence")
    if before is not None:
        (t0, t1), r = before["window_s"], before["att_rms_deg"]
        lines.append(
            f"over {t0:.1f}-{t1:.1f} s, before no compensation diverged, gm11 closes "
            f"{before['closed']:.2f} of that gap (attitude RMS none / gm11 / oracle "
            f"{r['none']:.3f} / {r['gm11']:.3f} / {r['oracle']:.3f} deg)"
        )
    return lines


def consistency_header(out: dict) -> str:
    """The report's first line: scenario, runs averaged, compensation."""
    return (
        f"{out['scenario']}: {out['runs']} Monte Carlo runs"
        + (f" from run {out['first_run']}" if out.get("first_run") else "")
        + f", compensation {out['method']}"
        + (", smoothed estimates" if "smoothed" in out else "")
        + ", two-sided 95 % chi-square bounds on the run-averaged statistic"
    )


def block_line(name: str, b: dict) -> str:
    """One block's line: dof, bounds, mean and its standard error, shares inside/below/above."""
    return (
        f"  {name:14s} dim {b['dim']:2d}  bounds [{b['lower']:.2f}, {b['upper']:.2f}]  "
        f"mean {b['mean']:7.2f} +-{b['mean_se']:5.2f}  inside {100 * b['share_inside']:5.1f} % of epochs "
        f"(below {100 * b['share_below']:4.1f} %, above {100 * b['share_above']:4.1f} %)"
    )


def target_line(out: dict) -> str:
    """The target's verdict on the whole run's blocks (the blocks under it named)."""
    verdict = out["target"]
    misses = ", ".join(f"{k} {100 * v:.1f} %" for k, v in verdict["misses"].items())
    return (
        f"  target (every NEES block and NIS inside on >= {100 * verdict['share']:.0f} % of "
        f"epochs, whole run, {out['runs']} runs): "
        + ("met" if verdict["met"] else f"not met: {misses}")
    )


def print_run_summary(out: dict) -> None:
    """The median attitude RMS over the runs and each diverged run."""
    print(f"  median attitude RMS over runs: {out['att_rms_deg_median']:.3f} deg")
    sm = out.get("smoothed")
    if sm:
        print(
            f"  smoothed RMS over the filter's, median (worst) over runs: attitude "
            f"{sm['att_rms_ratio_median']:.3f} ({sm['att_rms_ratio_max']:.3f}), rate "
            f"{sm['rate_rms_ratio_median']:.3f} ({sm['rate_rms_ratio_max']:.3f}); "
            f"{sm['restarts']} restarts (a posterior not positive definite)"
        )
    tl = out.get("track_losses")
    if tl:
        print(
            f"  track losses: {tl['count']}; estimates valid again after "
            f"{tl['valid_again_s_median']:.2f} s (median), {tl['valid_again_s_max']:.2f} s (worst)"
        )
    for d in out["diverged"]:
        what = "" if d["reason"].startswith("failed:") else "diverged: "
        print(f"  run {d['run']} is left out: {what}{d['reason']}")


def print_profile(rows: list[dict]) -> None:
    """The run-averaged NEES blocks by window (``--profile``)."""
    aoa = "aoa" in rows[0]
    print(
        "  run-averaged NEES by window (3 dof blocks, all: 12 dof"
        + (", aoa: 1 dof)" if aoa else ")")
    )
    print("    window s        pos    vel    att   rate     all" + ("    aoa" if aoa else ""))
    for row in rows:
        print(
            f"    {row['t0_s']:6.1f}-{row['t1_s']:6.1f}  {row['pos']:6.2f} {row['vel']:6.2f} "
            f"{row['att']:6.2f} {row['rate']:6.2f} {row['all']:7.2f}"
            + (f" {row['aoa']:6.2f}" if aoa else "")
        )


def cmd_consistency(args: argparse.Namespace) -> int:
    from filters.consistency import consistency_series

    scn = flight_scenario(args)
    out, t_s, averages = consistency_series(
        scn,
        args.runs,
        args.method,
        args.workers,
        progress=show_progress() and not args.json,
        profile_s=args.profile,
        from_s=args.from_s,
        scheduler=args.scheduler,
        save_dir=args.save,
        smooth=args.smooth,
        first=args.first,
    )
    if args.plot:
        from ngnav.plots import plot_nees

        blocks = out["blocks"]
        bounds = {n: (blocks[f"NEES {n}"]["lower"], blocks[f"NEES {n}"]["upper"]) for n in averages}
        title = f"{out['scenario']}: NEES averaged over {out['runs']} runs ({out['method']})"
        path = plot_nees(t_s, averages, bounds, Path(args.plot) / "nees.png", title)
        print(f"NEES figure -> {path}", file=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(consistency_header(out))
    sections = [("", out["blocks"])]
    if "blocks_from" in out:
        sections.append((f"  from {out['from_s']:g} s on:", out["blocks_from"]))
    for title, blocks in sections:
        if title:
            print(title)
        for name, b in blocks.items():
            print(block_line(name, b))
    print(target_line(out))
    print_run_summary(out)
    if "profile" in out:
        print_profile(out["profile"])
    return 0


def _latency_ms(st: dict) -> str:
    """Median / worst of a trial statistic in s, as ms ("-" without one)."""
    if not st["n"]:
        return "-"
    return f"{1000 * st['median']:.0f} / {1000 * st['worst']:.0f} ms"


def cmd_faults(args: argparse.Namespace) -> int:
    from filters.fault_trials import fault_campaign, pair_campaign
    from ngnav.sim.faults import FAULT_KINDS

    kinds = tuple(args.kinds.split(",")) if args.kinds else FAULT_KINDS
    bad = [k for k in kinds if k not in FAULT_KINDS]
    if bad:
        raise ValueError(f"--kinds: {bad[0]!r} is not one of {', '.join(FAULT_KINDS)}")
    if args.runs < 0 or args.clean_runs < 0:
        raise ValueError("--runs and --clean-runs must be >= 0")
    if args.pairs and args.clean_runs:
        raise ValueError("--pairs runs two-channel trials only: drop --clean-runs")
    scn = flight_scenario(args)
    common = dict(
        drift_mps2_per_s=args.drift,
        watch_s=args.watch,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=show_progress() and not args.json,
    )
    if args.pairs:
        out = pair_campaign(scn, kinds, args.runs, **common)
    else:
        out = fault_campaign(scn, kinds, args.runs, args.clean_runs, **common)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    if args.pairs:
        _print_pair_trials(out)
        return 0
    print(
        f"{out['scenario']}: {out['runs']} trials per kind (channel i mod N + 1), watched "
        f"{out['watch_s']:g} s after the fault; drift {out['drift_mps2_per_s']:g} m/s^2/s"
    )
    for kind, r in out["kinds"].items():
        line = (
            f"  {kind:9s} detected {r['detected']}/{r['trials']} (median / worst "
            f"{_latency_ms(r['detection_s'])}), isolated to the right channel in "
            f"{r['isolated_right']} ({_latency_ms(r['isolation_s'])}), to its pair only "
            f"{r['not_isolable']}; alarms on other channels {r['other_alarms']}"
        )
        if kind == "drift":
            a = r["attitude_sigmas_at_detection"]
            c = r["attitude_cost_sigmas_at_detection"]
            if a["n"] and c["n"]:
                line += (
                    f"; at detection the drift had cost the attitude {c['median']:.2f} / "
                    f"{c['worst']:.2f} sigma, within 3 sigma {r['within_3_sigma']}/{r['detected']} "
                    f"(its error {a['median']:.2f} / {a['worst']:.2f} sigma)"
                )
        if r["stopped"]:
            line += f"; filter stopped in {r['stopped']} runs"
        print(line)
    ff = out["fault_free"]
    if ff["flights"]:
        print(
            f"  fault-free: {ff['flights']} flights, {ff['flight_hours']:.2f} flight-hours, "
            f"{ff['alarms']} alarms"
            + (f", filter stopped in {ff['stopped']}" if ff["stopped"] else "")
        )
    return 0


def _print_pair_trials(out: dict) -> None:
    """``ngnav faults --pairs``: two channels failing together, by what the parity's
    geometry says of each pair."""
    print(
        f"{out['scenario']}: {out['runs']} two-channel trials per kind (pair i in order), "
        f"watched {out['watch_s']:g} s after the faults; drift {out['drift_mps2_per_s']:g} m/s^2/s"
    )
    for verdict, pairs in out["verdicts"].items():
        print(f"  the parity's geometry: {verdict} {len(pairs)} pairs: {', '.join(pairs)}")
    for kind, per in out["pairs"].items():
        for verdict, r in per.items():
            print(
                f"  {kind:9s} {verdict:9s} detected {r['detected']}/{r['trials']} (median / "
                f"worst {_latency_ms(r['detection_s'])}), both isolated {r['both_isolated']}, "
                f"a channel outside the pair isolated {r['wrong_isolated']}, filter stopped "
                f"{r['stopped']}"
            )


def add_campaign_args(p: argparse.ArgumentParser) -> None:
    """Where a campaign's runs go: ``--workers`` (a local cluster) or ``--scheduler``."""
    p.add_argument(
        "--workers",
        type=int,
        default=2,
        help="worker processes of a local dask cluster; 1 runs here (default: %(default)s)",
    )
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:8786",
        help="run on an existing dask cluster (its workers need ngnav installed)",
    )


def add_consistency_args(p: argparse.ArgumentParser, first: bool = True) -> None:
    """The options of ``ngnav consistency`` (``python -m studies.consistency`` adds its own,
    and splits runs 0 .. RUNS - 1 into draws itself: no ``--first``)."""
    p.add_argument("--runs", type=int, default=50)
    if first:
        p.add_argument(
            "--first",
            type=int,
            default=0,
            metavar="K",
            help="index of the first run: runs K .. K + RUNS - 1, another draw (default: 0)",
        )
    add_campaign_args(p)
    p.add_argument("--method", choices=["gm11", "none", "line", "last", "oracle"])
    p.add_argument(
        "--profile",
        type=float,
        metavar="S",
        help="also print each NEES block's run average over windows of S seconds",
    )
    p.add_argument(
        "--from",
        dest="from_s",
        type=float,
        metavar="S",
        help="also print every block's statistics over the epochs from S seconds on",
    )
    p.add_argument("--json", action="store_true")


def add_parsers(sub) -> None:
    """Register ``ngnav evaluate``, ``ngnav consistency`` and ``ngnav faults``."""
    p = sub.add_parser(
        "evaluate", help="errors of GM(1,1)/none/oracle/array-alone/GPS-alone on a simulated flight"
    )
    add_flight_args(p)
    p.add_argument("--run-index", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "consistency", help="NEES/NIS over Monte Carlo runs against chi-square bounds"
    )
    add_flight_args(p)
    add_consistency_args(p)
    p.add_argument(
        "--smooth",
        action="store_true",
        help="judge the smoothed estimates (ngnav run --smooth) instead of the filter's",
    )
    p.add_argument(
        "--plot", metavar="DIR", help="also draw each NEES block against its band: DIR/nees.png"
    )
    p.add_argument(
        "--save", metavar="DIR", help="also write each run's NEES and NIS series as it arrives"
    )
    p.set_defaults(func=cmd_consistency)

    p = sub.add_parser(
        "faults",
        help="channel-fault trials: detection and isolation latency, and fault-free alarms",
    )
    add_flight_args(p)
    p.add_argument("--runs", type=int, default=9, help="trials per kind (default: %(default)s)")
    p.add_argument(
        "--kinds",
        metavar="K1,K2",
        help="kinds to inject (default: dead,stuck,drift,noisy,saturated)",
    )
    p.add_argument(
        "--clean-runs", type=int, default=0, help="fault-free flights for false alarms (default: 0)"
    )
    p.add_argument(
        "--drift",
        type=float,
        default=TRIAL_DRIFT_MPS2_PER_S,
        metavar="MPS2_PER_S",
        help="the drift's rate, m/s^2 per s (default: 1 milli-g per second)",
    )
    p.add_argument(
        "--watch", type=float, default=10.0, metavar="S", help="seconds watched after the fault"
    )
    p.add_argument(
        "--pairs",
        action="store_true",
        help="two channels failing together (run i takes the i-th pair), by what the "
        "parity's geometry says of each pair",
    )
    add_campaign_args(p)
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.set_defaults(func=cmd_faults)
