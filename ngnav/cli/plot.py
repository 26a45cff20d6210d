"""``ngnav plot``: a run's figures and its HTML report."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_plot(args: argparse.Namespace) -> int:
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

    src = Path(args.run)
    if not src.is_dir():
        raise ValueError(f"{src}: not a run directory (config.toml, gps.csv, estimates.csv)")
    est_path = Path(args.estimates) if args.estimates else src / "estimates.csv"
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
    errors = None
    truth_csv = src / "truth.csv"
    if truth_csv.is_file():
        err = run_errors(est, read_truth_csv(truth_csv))
        errors = err.stacked()
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
        errors=errors,
    )
    out = Path(args.out) if args.out else src / "plots"
    files = plot_run(data, out)
    report = write_report(out, files, f"ngnav: {src.name}", summary)
    print("\n".join(summary))
    print(f"{len(files)} figures -> {out}; report: {report}")
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
