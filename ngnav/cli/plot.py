"""``ngnav plot``: a run's figures and its HTML report."""

from __future__ import annotations

import argparse


def cmd_plot(args: argparse.Namespace) -> int:
    from ngnav.api import plot

    got = plot(args.run, out=args.out, estimates=args.estimates)
    print("\n".join(got.summary))
    print(f"{len(got.figures)} figures -> {got.figures[0].parent}; report: {got.report}")
    return 0


def add_parsers(sub) -> None:
    """Register ``ngnav plot``."""
    p = sub.add_parser(
        "plot",
        help="figures of a run (trajectory, states with 3-sigma bands, errors, GPS NIS) "
        "and one HTML report",
    )
    p.add_argument("run", help="run directory with config.toml, gps.csv and estimates.csv")
    p.add_argument("--estimates", help="estimates file (default: RUN/estimates.csv)")
    p.add_argument("--out", help="folder for the PNGs and report.html (default: RUN/plots)")
    p.set_defaults(func=cmd_plot)
