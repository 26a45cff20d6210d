"""The ``ngnav`` command: the composition root, the only place that wires modules together."""

from __future__ import annotations

import argparse
import json
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
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a scenario value, e.g. --set sensor.noise_mv=0.5 (repeatable)",
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


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ngnav.calibration_study import run_calibration_study
    from ngnav.scenario import load_tilt_table

    scn = load_tilt_table(args.scenario, args.overrides)
    st = run_calibration_study(scn, args.runs)
    s = scn.sensor.sensitivity_mv_per_g
    print(f"axis-error calibration, {st.runs} simulated cubes x 9 channels ({scn.name})")
    print(f"  true misalignment (cone angle), RMS        {st.true_cone_rms_deg:8.3f} deg")
    print(f"  eq. 27 cone-angle error, RMS              {st.eq27_cone_rms_deg:8.3f} deg")
    print(f"  multi-position cone-angle error, RMS      {st.multipos_cone_rms_deg:8.3f} deg")
    print(f"  multi-position signed-angle error, RMS    {st.multipos_angle_rms_deg:8.3f} deg")
    print(f"  multi-position |error| <= 2 sigma         {100 * st.multipos_within_2sigma:8.1f} %")
    print(f"  multi-position scale error, RMS           {st.multipos_scale_rms:8.5f}")
    print("eq. 27 conditioning at this sensitivity:")
    print(
        f"  a 1 deg axis error changes V2 by          {s * (1 - np.cos(np.deg2rad(1.0))):8.4f} mV"
    )
    print(
        f"  a 0.1 mV reading error alone reads as     {np.rad2deg(np.arccos(1 - 0.1 / s)):8.3f} deg"
    )
    better = (
        "multi-position least squares"
        if st.multipos_cone_rms_deg < st.eq27_cone_rms_deg
        else "eq. 27"
    )
    print(f"use: {better}")
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


def build_parser() -> argparse.ArgumentParser:
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

    p = sub.add_parser("calibrate", help="eq. 27 against multi-position calibration, measured")
    _add_scenario_args(p)
    p.add_argument("--runs", type=int, default=50, help="simulated cubes (default: %(default)s)")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("grey", help="fit GM(1,1) to a sequence and forecast")
    p.add_argument("values", nargs="+", type=float, help="the sequence x0, oldest first (n >= 4)")
    p.add_argument("--steps", type=int, default=1, help="values to forecast (default: 1)")
    p.add_argument("--shift", default="auto", help="'auto' or a number (default: auto)")
    p.set_defaults(func=cmd_grey)

    p = sub.add_parser("bench", help="speed of the front end + compensation loop")
    p.add_argument("--samples", type=int, default=20_000)
    p.add_argument("--repeats", type=int, default=5)
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"ngnav {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
