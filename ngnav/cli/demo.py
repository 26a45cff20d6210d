"""``ngnav demo``: the whole chain on built-in defaults (what ``make run`` shows).

The paper's Table 1, then a short simulated flight through the filter with its accuracy
beside the bound (the same filter's covariance linearised at the truth), then its figures
and HTML report.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

#: The flight the demo flies: ``tactical`` (60 s, rolls and 2 g turns, 10 Hz GPS) with its
#: array at 200 Hz, which keeps the demo's filter run to seconds.
DEMO_SCENARIO = "tactical"
DEMO_OVERRIDES = ("run.rate_hz=200",)


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def cmd_demo(args: argparse.Namespace) -> int:
    from filters.evaluate import bound_summary, run_errors, summarise
    from filters.output import nis_path, write_estimates_csv, write_nis_csv
    from filters.pipeline import run_filter
    from ngnav.api import simulate, write_run
    from ngnav.cli.paper import cmd_paper
    from ngnav.cli.plot import cmd_plot
    from ngnav.runio import write_truth_csv

    out = Path(args.out)
    print("1. The paper's indexing-head test (Table 1), simulated", flush=True)
    cmd_paper(
        argparse.Namespace(
            scenario="tilt-table", overrides=[], json=False, methods=None, plot=str(out / "paper")
        )
    )
    sets = " ".join(f"--set {o}" for o in DEMO_OVERRIDES)
    print(f"\n2. A simulated flight through the filter (ngnav simulate --scenario {DEMO_SCENARIO} "
          f"{sets}; ngnav run)", flush=True)  # fmt: skip
    sim = simulate(DEMO_SCENARIO, 0, DEMO_OVERRIDES)
    run = write_run(out / "run", sim.samples, sim.fixes, sim.config)
    write_truth_csv(run / "truth.csv", sim.truth)
    res = run_filter(sim.samples, sim.fixes, sim.config, truth=sim.truth, bound=True)
    write_estimates_csv(run / "estimates.csv", res.estimates, sim.config)
    write_nis_csv(nis_path(run / "estimates.csv"), res.innovations)
    err = run_errors(res.estimates, sim.truth)
    s = summarise(err)
    b = bound_summary(res.estimates.bound_nav)
    # the attitude as the NED error the covariance describes: tilt (north and east) and heading
    att = np.rad2deg(err.att_ned_rad)
    p_att = np.rad2deg(np.sqrt(np.einsum("eii->ei", res.estimates.bound_nav[:, 6:9, 6:9])))
    rows = [
        ("horizontal, m", s.horiz_rms_m, b["horiz_rms_m"]),
        ("vertical, m", s.vert_rms_m, b["vert_rms_m"]),
        ("velocity, m/s", s.vel_rms_mps, b["vel_rms_mps"]),
        ("tilt, deg", _rms(np.hypot(att[:, 0], att[:, 1])), _rms(np.hypot(*p_att[:, :2].T))),
        ("heading, deg", _rms(att[:, 2]), _rms(p_att[:, 2])),
        ("rate, deg/s", s.rate_rms_dps, b["rate_rms_dps"]),
    ]
    print(f"   {res.estimates.t_s.size} estimates of a {sim.truth.t_s[-1]:.0f} s flight -> {run}")
    print(f"   {'RMS error':16s}{'filter':>9s}{'bound':>9s}")
    for name, got, bound in rows:
        print(f"   {name:16s}{got:9.3f}{bound:9.3f}")
    print("   (the bound: the RMS the same filter's covariance predicts when linearised at the "
          "truth)")  # fmt: skip
    print("\n3. Its figures (ngnav plot)", flush=True)
    cmd_plot(argparse.Namespace(run=str(run), estimates=None, out=None))
    print(f"\nOpen {run / 'plots' / 'report.html'} in a browser.", file=sys.stdout)
    return 0


def add_parsers(sub) -> None:
    """Register ``ngnav demo``."""
    p = sub.add_parser(
        "demo",
        help="the whole chain on built-in defaults: Table 1, a simulated flight through the "
        "filter beside its bound, its figures and report",
    )
    p.add_argument("--out", default="demo", help="output folder (default: %(default)s)")
    p.set_defaults(func=cmd_demo)
