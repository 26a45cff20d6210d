"""The ``ngnav`` command: the composition root, the only place that wires modules together."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

import numpy as np

from ngnav import __version__


def _add_scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scenario",
        default="tilt-table",
        help="shipped scenario name or TOML path (default: %(default)s)",
    )
    _add_set_arg(p, "e.g. --set sensor.noise_mv=0.5 ")


def _add_set_arg(p: argparse.ArgumentParser, example: str = "") -> None:
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help=f"override a scenario value, {example}(repeatable)",
    )


def _progress(enabled: bool):
    if not enabled:
        return None

    def show(done: int, total: int) -> None:
        print(
            f"\r  turn {done}/{total}",
            end="" if done < total else "\n",
            file=sys.stderr,
            flush=True,
        )

    return show


def cmd_paper(args: argparse.Namespace) -> int:
    from ngnav.paper import METHODS, run_paper
    from ngnav.scenario import load_tilt_table

    scn = load_tilt_table(args.scenario, args.overrides)
    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    res = run_paper(scn, methods=methods, progress=_progress(not args.json and sys.stderr.isatty()))
    if args.json:
        out = {
            "scenario": scn.name,
            "plane": scn.test.plane,
            "seed": scn.run.seed,
            "rows": [
                {
                    "platform_deg": t.platform_deg,
                    "paper_measured_deg": float(res.paper.measured_deg[i]),
                    "paper_compensated_deg": float(res.paper.compensated_deg[i]),
                    **{f"{m}_deg": t.angle_deg[m] for m in methods},
                }
                for i, t in enumerate(res.turns)
            ],
            "methods": {
                m: {
                    "mean_abs_deg": s.mean_abs_deg,
                    "rms_deg": s.rms_deg,
                    "max_abs_deg": s.max_abs_deg,
                    "beyond_60_mean_abs_deg": s.beyond_60_mean_abs_deg,
                    "gm11_fallbacks": sum(t.n_fallbacks[m] for t in res.turns),
                }
                for m, s in res.summary.items()
            },
            "paper": {
                m: {
                    "mean_abs_deg": s.mean_abs_deg,
                    "rms_deg": s.rms_deg,
                    "max_abs_deg": s.max_abs_deg,
                }
                for m, s in res.paper_summary.items()
            },
        }
        json.dump(out, sys.stdout, indent=2)
        print()
        return 0
    print(f"ngnav paper: the indexing-head test of Ding, Wang & Du (2006), simulated ({scn.name})")
    plane = (
        "horizontal plane (about body z, vertical)"
        if scn.test.plane == "horizontal"
        else "vertical plane (about body x, horizontal)"
    )
    print(f"turns in the {plane}; seed {scn.run.seed}; angles in deg\n")
    head = f"{'platform':>9} {'paper meas':>10} {'paper comp':>10} | " + " ".join(
        f"{m:>8}" for m in methods
    )
    print(head)
    print("-" * len(head))
    for i, t in enumerate(res.turns):
        print(
            f"{t.platform_deg:9.2f} {res.paper.measured_deg[i]:10.2f} {res.paper.compensated_deg[i]:10.2f} | "
            + " ".join(f"{t.angle_deg[m]:8.2f}" for m in methods)
        )
    print("\nerror against the platform angle, deg:")
    print(f"{'method':>22} {'mean abs':>9} {'RMS':>7} {'worst':>7} {'>60 deg':>8}")
    rows = [(f"paper {k}", s) for k, s in res.paper_summary.items()]
    rows += [(m, res.summary[m]) for m in methods]
    for name, s in rows:
        print(
            f"{name:>22} {s.mean_abs_deg:9.2f} {s.rms_deg:7.2f} {s.max_abs_deg:7.2f} {s.beyond_60_mean_abs_deg:8.2f}"
        )
    if "none" in res.summary and "gm11" in res.summary:
        none, gm = res.summary["none"].mean_abs_deg, res.summary["gm11"].mean_abs_deg
        print(
            f"\nGM(1,1) compensation changes the mean absolute error by {100 * (gm / none - 1):+.1f} % "
            f"(paper: {100 * (res.paper_summary['compensated'].mean_abs_deg / res.paper_summary['measured'].mean_abs_deg - 1):+.1f} %)"
        )
        if "oracle" in res.summary:
            print(
                f"GM(1,1) / oracle mean absolute error: {gm / res.summary['oracle'].mean_abs_deg:.2f}"
            )
    return 0


def cmd_grey(args: argparse.Namespace) -> int:
    from ngnav.grey import GreyModel11

    m = GreyModel11(shift=args.shift if args.shift == "auto" else float(args.shift)).fit(
        np.array(args.values)
    )
    q = m.quality()
    print(f"a = {m.a_:.10g}  b = {m.b_:.10g}  shift = {m.shift_:g}")
    print("fitted:   " + " ".join(f"{v:.6g}" for v in m.fitted_))
    print("forecast: " + " ".join(f"{v:.6g}" for v in m.forecast(args.steps)))
    print(
        f"class ratios admissible: {q.ratio_admissible}; C = {q.posterior_variance_ratio:.4g}; "
        f"P = {q.small_error_probability:.3g} ({q.grade})"
    )
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from ngnav.bench import run_bench

    results = run_bench(n_samples=args.samples, repeats=args.repeats)
    print(
        f"front end + compensation loop, nine channels, {args.samples} samples, "
        f"median of {args.repeats}, one core"
    )
    for r in results:
        print(
            f"  {r.name:36s} {r.samples_per_s:12,.0f} samples/s  ({r.samples_per_s / 100:9,.0f}x real time at 100 Hz)"
        )
    return 0


def cmd_bench_filter(args: argparse.Namespace) -> int:
    from filters.bench import run_filter_bench

    b = run_filter_bench(_flight(args), seconds=args.seconds, repeats=args.repeats)
    print(
        f"{b.scenario}: first {args.seconds:g} s, {b.samples} samples at {b.array_rate_hz:g} Hz, "
        f"filter at {b.filter_rate_hz:g} Hz ({b.blocks} blocks), {b.gps_fixes} GPS fixes at "
        f"{b.gps_rate_hz:g} Hz, {b.state_size} error states; median of {args.repeats}, one core"
    )
    rt = b.array_rate_hz
    print(
        f"  full pipeline      {b.pipeline_samples_per_s:10,.0f} samples/s "
        f"({b.pipeline_samples_per_s / rt:6.1f}x real time)"
    )
    print(
        f"  bare filterpy loop {b.bare_samples_per_s:10,.0f} samples/s "
        f"({b.bare_samples_per_s / rt:6.1f}x real time)"
    )
    print(f"  pipeline / bare loop time: {b.slowdown:.2f}x")
    print("  pipeline runs (s): " + ", ".join(f"{t:.2f}" for t in b.pipeline_s))
    return 0


def _flight(args: argparse.Namespace):
    from ngnav.flight_scenario import is_flight_scenario, load_flight

    if not is_flight_scenario(args.scenario):
        raise ValueError(f"scenario {args.scenario!r} is not a flight (it has no [flight] section)")
    return load_flight(args.scenario, args.overrides)


def _print_counts(counts: dict[str, int], indent: str = "  ") -> None:
    for k, v in counts.items():
        print(f"{indent}{k}: {v}")


def cmd_simulate(args: argparse.Namespace) -> int:
    from ngnav.conventions import G0_MPS2
    from ngnav.runio import write_truth_csv
    from ngnav.simulate import simulate_flight
    from telemetry.runfiles import truth_path, write_run

    if args.out is None and args.stream is None:
        raise ValueError("say where the run goes: --out DIR|NAME.tlog and/or --stream udpout:...")
    scn = _flight(args)
    sim = simulate_flight(scn, args.run_index)
    where = []
    if args.out is not None:
        out = write_run(args.out, sim.samples, sim.fixes, sim.config)
        write_truth_csv(truth_path(out), sim.truth)
        where.append(str(out))
    print(
        f"simulated {scn.name} run {args.run_index}: {sim.samples.t_s.shape[0]} array samples "
        f"({sim.samples.n_channels} channels), {len(sim.fixes)} GPS fixes, "
        f"{int(sim.saturated.any(axis=1).sum())} saturated samples -> {', '.join(where) or '-'}",
        flush=True,
    )
    e_pos = sim.unknown_position_error_mps2() / G0_MPS2 * 1e6
    noise = float(np.median(sim.config.noise_sigma_mps2)) / G0_MPS2 * 1e6
    print(
        f"unknown sensor positions ({sim.config.position_sigma_m * 1e3:g} mm 1-sigma): channel "
        f"error {np.sqrt(np.mean(e_pos**2)):.1f} ug rms, {np.abs(e_pos).max():.1f} ug at most, "
        f"beside {noise:.0f} ug of noise per sample; filter position states "
        f"{'on' if sim.config.filter.position_states and sim.config.position_sigma_m > 0 else 'off'}"
    )
    if args.stream is not None:
        from telemetry.inputs import input_frames
        from telemetry.live import parse_endpoint, play_frames
        from telemetry.tlog import FrameWriter, frames_of

        dest = parse_endpoint(args.stream, "udpout")
        frames = frames_of(input_frames(sim.samples, sim.fixes, sim.config), FrameWriter())
        n = play_frames(frames, dest, args.speed)
        print(f"streamed {n} datagrams to {dest} at speed {args.speed:g}")
    return 0


def _print_reports(reports: dict[str, dict[str, int]]) -> None:
    for src, counts in reports.items():
        print(f"  {src}:")
        _print_counts(counts, "    ")


def cmd_run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from filters.evaluate import run_errors, summarise
    from filters.output import write_estimates_csv
    from filters.pipeline import run_filter
    from ngnav.api import pipeline_factory
    from ngnav.cli.stream import run_to_tlog
    from ngnav.errors import CovarianceError
    from ngnav.runio import read_truth_csv
    from telemetry.replay import replay_tlog
    from telemetry.runfiles import is_tlog, read_run, truth_path

    src = Path(args.run)
    if args.out:
        out = Path(args.out)
    else:
        out = src.with_suffix(".estimates.csv") if is_tlog(src) else src / "estimates.csv"
    if args.no_gps and (is_tlog(src) or is_tlog(out)):
        raise ValueError("--no-gps is for CSV runs; a tlog replay uses every input it holds")
    if not src.exists():
        raise ValueError(f"{src}: no such file or directory")
    if not is_tlog(src) and not src.is_dir():
        raise ValueError(f"{src} is not a run: give a directory (config.toml, array.csv, "
                         "gps.csv) or a .tlog")
    _check_writable(out)
    failure = None
    if is_tlog(out):
        # estimates as MAVLink: through the stream path, as a live link would run
        rr, reports = run_to_tlog(src, out, args)
        res, cfg, failure = rr.result, rr.config, rr.failure
        frames = sum(rr.frames_sent.values())
        print(f"run {src}: {res.estimates.t_s.shape[0]} estimates, {frames} frames -> {out}")
    elif is_tlog(src):
        rr = replay_tlog(src, pipeline_factory(args.compensation))
        if rr.result is None:
            raise ValueError(f"{src}: the filter did not run: {rr.failure}")
        res, cfg, failure = rr.result, rr.config, rr.failure
        reports = {str(src): rr.counts}
        write_estimates_csv(out, res.estimates, cfg)
        print(f"run {src}: {res.estimates.t_s.shape[0]} estimates ({res.compensation}) -> {out}")
    else:
        inp = read_run(src)
        cfg, reports = inp.config, inp.reports
        try:
            res = run_filter(
                inp.samples, inp.fixes, cfg, compensation=args.compensation, use_gps=not args.no_gps
            )
        except CovarianceError as exc:
            if exc.partial is None:
                raise
            res, failure = exc.partial, str(exc)
        write_estimates_csv(out, res.estimates, cfg)
        print(f"run {src}: {res.estimates.t_s.shape[0]} estimates ({res.compensation}) -> {out}")
    _print_reports(reports)
    _print_counts(res.counts)
    if truth_path(src).exists():
        s = summarise(run_errors(res.estimates, read_truth_csv(truth_path(src))))
        print(
            f"  against {truth_path(src).name}: horizontal RMS {s.horiz_rms_m:.3f} m, vertical "
            f"{s.vert_rms_m:.3f} m, roll/pitch/yaw RMS {s.roll_rms_deg:.3f}/"
            f"{s.pitch_rms_deg:.3f}/{s.yaw_rms_deg:.3f} deg"
        )
    if failure:
        print(
            f"ngnav run: the filter stopped: {failure}; the {res.estimates.t_s.shape[0]} "
            f"estimates before it are in {out}. Check the run's configuration against its data "
            "(sensor noise, initial attitude and heading, compensation).",
            file=sys.stderr,
        )
        return EXIT_DIVERGED
    return 0


def _check_writable(out) -> None:
    """Refuse an output path that cannot be written before any work is done (one line)."""
    parent = out.parent if str(out.parent) else type(out)(".")
    if out.is_dir():
        raise ValueError(f"--out {out} is a directory; give a file NAME.csv or NAME.tlog")
    if not parent.is_dir():
        raise ValueError(f"--out {out}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        raise ValueError(f"--out {out}: not writable")


def cmd_convert(args: argparse.Namespace) -> int:
    import shutil

    from telemetry.runfiles import read_run, truth_path, write_run

    inp = read_run(args.src)
    out = write_run(args.dst, inp.samples, inp.fixes, inp.config)
    if truth_path(args.src).exists():
        shutil.copyfile(truth_path(args.src), truth_path(out))
    print(
        f"converted {args.src} -> {out}: {inp.samples.t_s.shape[0]} array samples, "
        f"{len(inp.fixes)} GPS fixes"
    )
    _print_reports(inp.reports)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from filters.experiments import evaluate_scenario, summary_dict

    scn = _flight(args)
    out = evaluate_scenario(scn, args.run_index)
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
    for k, v in out.get("events", {}).items():
        print(f"  {k}: {v}")
    for k, v in out.get("targets", {}).items():
        print(f"  {k}: {v}")
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


def cmd_consistency(args: argparse.Namespace) -> int:
    from filters.experiments import consistency

    scn = _flight(args)
    out = consistency(
        scn,
        args.runs,
        args.method,
        args.workers,
        progress=not args.json,
        profile_s=args.profile,
        from_s=args.from_s,
        reference=args.reference,
        sets=args.sets,
        cycle_s=args.cycle,
        tails_s=args.tails,
    )
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(
        f"{out['scenario']}: {out['runs']} Monte Carlo runs, compensation {out['method']}, "
        "two-sided 95 % chi-square bounds on the run-averaged statistic"
    )
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
            print(
                f"  {name:14s} dim {b['dim']:2d}  bounds [{b['lower']:.2f}, {b['upper']:.2f}]  "
                f"mean {b['mean']:7.2f} +-{b['mean_se']:5.2f}  inside {100 * b['share_inside']:5.1f} % of epochs "
                f"(below {100 * b['share_below']:4.1f} %, above {100 * b['share_above']:4.1f} %)"
            )
            ref = b.get("consistent_share")
            if ref is not None:
                print(
                    f"  {'':14s} a consistent filter: median {100 * ref['median']:5.1f} %, "
                    f"5th percentile {100 * ref['p05']:5.1f} %, below 90 % in "
                    f"{100 * ref['prob_below_90']:4.1f} % of {ref['replicas']} run sets"
                )
    print(
        "  control pos/vel: NEES of a perfect-array filter on the same fixes (filters.control), "
        "consistent by construction; -pn: with process noise, a navigation filter's time course"
    )
    verdict = out["target"]
    misses = ", ".join(f"{k} {100 * v:.1f} %" for k, v in verdict["misses"].items())
    print(
        f"  target (every NEES block and NIS inside on >= {100 * verdict['share']:.0f} % of "
        f"epochs, whole run, {out['runs']} runs): "
        + ("met" if verdict["met"] else f"not met: {misses}")
    )
    if "sets" in out:
        _print_sets(out["sets"], out["sets_meeting_target"])
    print(f"  median attitude RMS over runs: {out['att_rms_deg_median']:.3f} deg")
    for d in out["diverged"]:
        print(f"  run {d['run']} diverged and is left out: {d['reason']}")
    if "profile" in out:
        aoa = "aoa" in out["profile"][0]
        print(
            "  run-averaged NEES by window (3 dof blocks, all: 12 dof"
            + (", aoa: 1 dof)" if aoa else ")")
        )
        print("    window s        pos    vel    att   rate     all" + ("    aoa" if aoa else ""))
        for row in out["profile"]:
            print(
                f"    {row['t0_s']:6.1f}-{row['t1_s']:6.1f}  {row['pos']:6.2f} {row['vel']:6.2f} "
                f"{row['att']:6.2f} {row['rate']:6.2f} {row['all']:7.2f}"
                + (f" {row['aoa']:6.2f}" if aoa else "")
            )
    if "cycle" in out:
        _print_cycle(out["cycle"])
    if "tails" in out:
        _print_tails(out["tails"]["all"])
    return 0


def _print_tails(rows: list[dict]) -> None:
    print(
        "  the joint NEES's spread over runs by window (filters.experiments.nees_tails): "
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


def _add_flight_args(p: argparse.ArgumentParser, default: str = "uav-survey") -> None:
    p.add_argument(
        "--scenario",
        default=default,
        help="shipped flight scenario (static, uav-survey, tactical) or TOML path "
        "(default: %(default)s)",
    )
    _add_set_arg(p)


def build_parser() -> argparse.ArgumentParser:
    from ngnav.cli.stream import add_output_args, add_stream_parser

    parser = argparse.ArgumentParser(
        prog="ngnav", description="GPS-aided navigation with a gyro-free nine-accelerometer IMU."
    )
    parser.add_argument("--version", action="version", version=f"ngnav {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("paper", help="reproduce the paper's Table 1 (indexing-head test)")
    _add_scenario_args(p)
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--methods", help="comma-separated subset of none,gm11,last,line,oracle")
    p.set_defaults(func=cmd_paper)

    p = sub.add_parser("grey", help="fit GM(1,1) to a sequence and forecast")
    p.add_argument("values", nargs="+", type=float, help="the sequence x0, oldest first (n >= 4)")
    p.add_argument("--steps", type=int, default=1, help="values to forecast (default: 1)")
    p.add_argument("--shift", default="auto", help="'auto' or a number (default: auto)")
    p.set_defaults(func=cmd_grey)

    p = sub.add_parser(
        "simulate", help="simulate a flight run (CSV + TOML directory, or a .tlog), with truth"
    )
    _add_flight_args(p)
    p.add_argument(
        "--run-index", type=int, default=0, help="Monte Carlo index i of default_rng([seed, i])"
    )
    p.add_argument("--out", help="output directory, or a file NAME.tlog (MAVLink inputs)")
    p.add_argument(
        "--stream",
        metavar="udpout:HOST:PORT",
        help="also play the inputs as MAVLink over UDP (see --speed)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="run seconds per wall second for --stream; 0 = unpaced (default: 1, real time)",
    )
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("convert", help="convert a run between a CSV directory and a .tlog")
    p.add_argument("src", help="run directory or .tlog")
    p.add_argument("dst", help="run directory or .tlog")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser(
        "run", help="run the filter on a run directory (config.toml, array.csv, gps.csv) or tlog"
    )
    p.add_argument("run", help="directory with config.toml, array.csv, gps.csv; or a .tlog")
    p.add_argument(
        "--out",
        help="estimates: NAME.csv, or NAME.tlog for MAVLink estimates "
        "(default: RUN/estimates.csv, or NAME.estimates.csv)",
    )
    p.add_argument(
        "--compensation", choices=["gm11", "none", "line", "last"], help="override the config"
    )
    p.add_argument("--no-gps", action="store_true", help="array alone after initialisation")
    add_output_args(p)
    p.set_defaults(func=cmd_run)

    add_stream_parser(sub, _add_flight_args)

    p = sub.add_parser(
        "evaluate", help="errors of GM(1,1)/none/oracle/array-alone/GPS-alone on a simulated flight"
    )
    _add_flight_args(p)
    p.add_argument("--run-index", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "consistency", help="NEES/NIS over Monte Carlo runs against chi-square bounds"
    )
    _add_flight_args(p)
    p.add_argument("--runs", type=int, default=50)
    p.add_argument(
        "--workers", type=int, default=2, help="dask worker processes (default: %(default)s)"
    )
    p.add_argument("--method", choices=["gm11", "none", "line", "last", "oracle"])
    p.add_argument(
        "--profile",
        type=float,
        metavar="S",
        help="also print each NEES block's run average over windows of S seconds",
    )
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
        "--from",
        dest="from_s",
        type=float,
        metavar="S",
        help="also print every block's statistics over the epochs from S seconds on",
    )
    p.add_argument(
        "--reference",
        action="store_true",
        help="also print the share a consistent filter would reach on each block, from the "
        "statistic's correlation in time (filters.share_reference; slower)",
    )
    p.add_argument(
        "--sets",
        type=int,
        default=1,
        metavar="K",
        help="run K disjoint sets of --runs runs and also print each set's shares on its "
        "own: how often the target holds on a fresh draw (default: %(default)s)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_consistency)

    p = sub.add_parser("bench", help="speed of the front end + compensation loop")
    p.add_argument("--samples", type=int, default=20_000)
    p.add_argument("--repeats", type=int, default=5)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser(
        "bench-filter", help="speed of the whole GPS/array pipeline beside a bare filterpy loop"
    )
    _add_flight_args(p)
    p.add_argument(
        "--seconds", type=float, default=120.0, help="flight seconds timed (default: %(default)s)"
    )
    p.add_argument("--repeats", type=int, default=5)
    p.set_defaults(func=cmd_bench_filter)
    return parser


#: Exit status of a run whose filter diverged or lost its track (estimates up to it kept).
EXIT_DIVERGED = 3


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``ngnav`` command; user errors end in one line on stderr, never a traceback.

    Exit status: 0 done, 2 a bad argument, file or configuration, 3 the filter
    diverged (:data:`EXIT_DIVERGED`), 130 interrupted (Ctrl-C).
    """
    from ngnav.errors import CovarianceError

    where = "ngnav"
    try:
        args = build_parser().parse_args(argv)
        where = f"ngnav {args.command}"
        return args.func(args)
    except ValueError as exc:
        print(f"{where}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        name = f": {exc.filename}" if exc.filename else ""
        print(f"{where}: error: {exc.strerror or exc}{name}", file=sys.stderr)
        return 2
    except CovarianceError as exc:
        print(f"{where}: the filter diverged: {exc}", file=sys.stderr)
        return EXIT_DIVERGED
    except KeyboardInterrupt:
        print(f"{where}: interrupted", file=sys.stderr)
        return 130
