"""The paper's commands: ``ngnav paper`` (the indexing-head test) and ``ngnav grey``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ngnav.cli import add_scenario_args, show_progress


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
    from ngnav.sim.tilt_table import load_tilt_table

    scn = load_tilt_table(args.scenario, args.overrides)
    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    res = run_paper(scn, methods=methods, progress=_progress(not args.json and show_progress()))
    if args.plot:
        from pathlib import Path

        from ngnav.plots import plot_paper_table

        series = {
            "paper measured": res.paper.measured_deg,
            "paper compensated": res.paper.compensated_deg,
            **{m: np.array([t.angle_deg[m] for t in res.turns]) for m in methods},
        }
        platform = np.array([t.platform_deg for t in res.turns])
        path = plot_paper_table(platform, series, Path(args.plot) / "table1.png")
        print(f"Table 1 figure -> {path}", file=sys.stderr if args.json else sys.stdout)
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


def add_parsers(sub) -> None:
    """Register ``ngnav paper`` and ``ngnav grey``."""
    p = sub.add_parser("paper", help="reproduce the paper's Table 1 (indexing-head test)")
    add_scenario_args(p)
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--methods", help="comma-separated subset of none,gm11,last,line,oracle")
    p.add_argument("--plot", metavar="DIR", help="also draw Table 1: DIR/table1.png")
    p.set_defaults(func=cmd_paper)

    p = sub.add_parser("grey", help="fit GM(1,1) to a sequence and forecast")
    p.add_argument("values", nargs="+", type=float, help="the sequence x0, oldest first (n >= 4)")
    p.add_argument("--steps", type=int, default=1, help="values to forecast (default: 1)")
    p.add_argument("--shift", default="auto", help="'auto' or a number (default: auto)")
    p.set_defaults(func=cmd_grey)
