"""Runs as files: ``ngnav simulate``, ``ngnav convert`` and ``ngnav run``."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from ngnav.cli import EXIT_DIVERGED, FractionBar, add_flight_args, flight_scenario

#: The run summary's groups: a counter goes to the first group one of whose prefixes it
#: starts with (the rest to "filter").
COUNT_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "inputs",
        (
            "samples held",
            "samples before",
            "gps fixes outside",
            "gps fixes before",
            "gps fixes later",
            "gps fixes after",
            "gps fixes ignored",
            "gps fix that started",
            "gps fixes through",
        ),
    ),
    ("GPS", ("gps ",)),
    ("array", ("blocks", "samples used", "rate updates", "grey forecasts")),
    ("vehicle models", ("sideslip", "angle-of-attack", "vehicle-model")),
    ("rest", ("zero-rate",)),
    ("recovery", ("heading resets", "attitude reopened")),
    ("smoother", ("smoother",)),
)


def count_lines(counts: dict[str, int]) -> list[str]:
    """The counters that are not zero, one line per group (:data:`COUNT_GROUPS`)."""
    groups: dict[str, list[str]] = {}
    for key, value in counts.items():
        if not value:
            continue
        group = next((g for g, pre in COUNT_GROUPS if key.startswith(pre)), "filter")
        groups.setdefault(group, []).append(f"{key} {value}")
    order = [g for g, _ in COUNT_GROUPS] + ["filter"]
    return [f"{g}: {', '.join(groups[g])}" for g in order if g in groups]


def _print_counts(counts: dict[str, int], indent: str = "  ") -> None:
    for line in count_lines(counts):
        print(f"{indent}{line}")


def default_estimates_path(run: Path) -> Path:
    """Where ``ngnav run`` writes a run's estimates by default: ``RUN/estimates.csv``, or
    ``NAME.estimates.csv`` beside ``NAME.tlog``."""
    from telemetry.runfiles import is_tlog

    return run.with_suffix(".estimates.csv") if is_tlog(run) else run / "estimates.csv"


def _earlier_outputs(out: Path) -> list[Path]:
    """What ``ngnav run`` (its default estimates, with their NIS, NPZ and smoothed files) and
    ``ngnav plot`` (``plots/``) write for the run at ``out``, a directory or a tlog."""
    from filters.output import nis_path, npz_path
    from ngnav.plots import RUN_PLOT_FILES
    from telemetry.runfiles import is_tlog

    est = default_estimates_path(out)
    smoothed = smoothed_path(est)
    files = [est, npz_path(est), nis_path(est), smoothed, npz_path(smoothed)]
    if not is_tlog(out):
        files += [out / "plots" / name for name in RUN_PLOT_FILES]
    return files


def _refuse_file_name_for_a_run(dst: str | Path) -> None:
    """A run is a directory or ``NAME.tlog``: ``NAME.csv`` would become a directory."""
    if Path(dst).suffix.lower() in (".csv", ".toml", ".npz"):
        raise ValueError(
            f"{dst}: a run is a directory (array.csv, gps.csv, config.toml) or NAME.tlog"
        )


def cmd_simulate(args: argparse.Namespace) -> int:
    from ngnav.conventions import G0_MPS2
    from ngnav.runio import write_truth_csv
    from ngnav.sim.simulate import simulate_flight
    from telemetry.runfiles import truth_path, write_run

    if args.calibration_recordings is not None:
        from ngnav.sim.bench_recordings import bench_session, write_bench_session

        scn = flight_scenario(args)
        session = bench_session(scn, args.run_index, continuous=args.continuous)
        out = write_bench_session(session, args.calibration_recordings)
        what = "one recording (array.csv)" if args.continuous else "18 poses (static/*.csv)"
        print(
            f"simulated the bench session of {scn.name} run {args.run_index}'s array: {what}, "
            f"{len(session.spins)} rate-table poses (spin/*.csv, *.toml), config.toml and "
            f"truth_calibration.toml -> {out}"
        )
        if args.out is None and args.stream is None:
            return 0
    if args.out is None and args.stream is None:
        raise ValueError("say where the run goes: --out DIR|NAME.tlog and/or --stream udpout:...")
    if args.out is not None:
        _refuse_file_name_for_a_run(args.out)
    if args.stream is not None:
        from telemetry.live import parse_endpoint

        dest = parse_endpoint(args.stream, "udpout")  # refused before the simulation
    scn = flight_scenario(args)
    with FractionBar("simulate") as bar:
        sim = simulate_flight(scn, args.run_index, progress=bar)
    where = []
    removed = []
    if args.out is not None:
        out = write_run(args.out, sim.samples, sim.fixes, sim.config)
        write_truth_csv(truth_path(out), sim.truth)
        where.append(str(out))
        # read beside the new truth, an earlier flight's estimates were judged against a
        # flight they never saw (`ngnav plot` reported a yaw RMS of 125 deg)
        removed = [f for f in _earlier_outputs(out) if f.is_file()]
        for f in removed:
            f.unlink()
        plots = out / "plots"
        if removed and plots.is_dir() and not any(plots.iterdir()):
            plots.rmdir()
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
        f"{'on' if sim.config.position_sigma_m > 0 else 'off'}"
    )
    e_cal = sim.calibration_residual_error_mps2() / G0_MPS2 * 1e6
    walk = float(np.median(sim.config.bias_rw_mps2_rts)) / G0_MPS2 * 1e6
    walk *= np.sqrt(sim.truth.t_s[-1] - sim.truth.t_s[0])
    print(
        f"the calibration's scale and axis residual: channel error moves by "
        f"{np.abs(e_cal).max():.1f} ug at most with the load, beside a bias walk of "
        f"{walk:.1f} ug over the flight; filter axis states "
        f"{'on' if sim.config.carries_calibration_error else 'off'}"
    )
    if removed:
        print(f"removed {len(removed)} outputs of an earlier flight (estimates, figures) at {out}")
    if args.stream is not None:
        from telemetry.inputs import input_frames
        from telemetry.live import play_frames
        from telemetry.tlog import FrameWriter, frames_of

        frames = frames_of(input_frames(sim.samples, sim.fixes, sim.config), FrameWriter())
        n = play_frames(frames, dest, args.speed)
        print(f"streamed {n} datagrams to {dest} at speed {args.speed:g}")
    return 0


def _print_reports(reports: dict[str, dict[str, int]]) -> None:
    for src, counts in reports.items():
        told = [f"{k} {v}" for k, v in counts.items() if v]
        if told:
            print(f"  {src}: {', '.join(told)}")


def cmd_run(args: argparse.Namespace) -> int:
    from filters.evaluate import run_errors, summarise
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
        out = default_estimates_path(src)
    if args.smooth and is_tlog(out):
        raise ValueError("--smooth writes CSV and NPZ estimates; give --out NAME.csv")
    if args.no_gps and (is_tlog(src) or is_tlog(out)):
        raise ValueError("--no-gps is for CSV runs; a tlog replay uses every input it holds")
    if not src.exists():
        raise ValueError(f"{src}: no such file or directory")
    if not is_tlog(src) and not src.is_dir():
        raise ValueError(
            f"{src} is not a run: give a directory (config.toml, array.csv, gps.csv) or a .tlog"
        )
    _check_writable(out)
    from ngnav.cli.stream import output_settings

    output_settings(args)  # the MAVLink options checked whatever the output (used by a tlog's)
    failure = None
    if is_tlog(out):
        # estimates as MAVLink: through the stream path, as a live link would run
        rr, reports = run_to_tlog(src, out, args)
        res, cfg, failure = rr.result, rr.config, rr.failure
        frames = sum(rr.frames_sent.values())
        print(f"run {src}: {res.estimates.t_s.shape[0]} estimates, {frames} frames -> {out}")
    elif is_tlog(src):
        rr = replay_tlog(src, pipeline_factory(args.compensation, smooth=args.smooth))
        if rr.result is None:
            raise ValueError(f"{src}: the filter did not run: {rr.failure}")
        res, cfg, failure = rr.result, rr.config, rr.failure
        reports = {str(src): rr.counts}
        _write_estimates(out, res, cfg)
        print(f"run {src}: {res.estimates.t_s.shape[0]} estimates ({res.compensation}) -> {out}")
    else:
        inp = read_run(src)
        cfg, reports = inp.config, inp.reports
        try:
            with FractionBar("filter") as bar:
                res = run_filter(
                    inp.samples,
                    inp.fixes,
                    cfg,
                    compensation=args.compensation,
                    use_gps=not args.no_gps,
                    progress=bar,
                    smooth=args.smooth,
                )
        except CovarianceError as exc:
            if exc.partial is None:
                raise
            res, failure = exc.partial, str(exc)
        _write_estimates(out, res, cfg)
        print(f"run {src}: {res.estimates.t_s.shape[0]} estimates ({res.compensation}) -> {out}")
    _print_reports(reports)
    _print_counts(res.counts)
    for ev in res.faults:
        print(f"  channel fault: {ev.describe()}")
    for loss in res.track_losses:
        print(f"  track {loss.describe()}")
    if res.smoothed is not None:
        print(f"  smoothed -> {smoothed_path(out)} (and .npz)")
    elif args.smooth and failure:
        print("  not smoothed: the filter stopped before the run's end")
    if truth_path(src).exists():
        truth = read_truth_csv(truth_path(src))
        for what, est in (("filter", res.estimates), ("smoothed", res.smoothed)):
            if est is None:
                continue
            s = summarise(run_errors(est, truth))
            print(
                f"  {what} against {truth_path(src).name}: horizontal RMS {s.horiz_rms_m:.3f} m, "
                f"vertical {s.vert_rms_m:.3f} m, roll/pitch/yaw RMS {s.roll_rms_deg:.3f}/"
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


def smoothed_path(estimates_path) -> Path:
    """Where ``--smooth`` writes beside the estimates ``NAME.csv``: ``NAME.smoothed.csv``."""
    p = Path(estimates_path)
    return p.with_name(f"{p.stem}.smoothed.csv")


def _write_estimates(out: Path, res, cfg) -> None:
    """The run's estimates, NIS and NPZ beside them; the smoothed ones when there are."""
    from dataclasses import replace

    from filters.output import (
        nis_path,
        npz_path,
        write_estimates_csv,
        write_estimates_npz,
        write_nis_csv,
    )

    write_estimates_csv(out, res.estimates, cfg)
    write_nis_csv(nis_path(out), res.innovations)
    write_estimates_npz(npz_path(out), res)
    if res.smoothed is not None:
        sm = smoothed_path(out)
        write_estimates_csv(sm, res.smoothed, cfg)
        write_estimates_npz(npz_path(sm), replace(res, estimates=res.smoothed))


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

    _refuse_file_name_for_a_run(args.dst)
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


def add_parsers(sub) -> None:
    """Register ``ngnav simulate``, ``ngnav convert`` and ``ngnav run``."""
    from ngnav.cli.stream import add_output_args

    p = sub.add_parser(
        "simulate", help="simulate a flight run (CSV + TOML directory, or a .tlog), with truth"
    )
    add_flight_args(p)
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
    p.add_argument(
        "--calibration-recordings",
        metavar="DIR",
        help="also write the array's bench session for ngnav calibrate: DIR/config.toml and "
        "18 still poses (static/*.csv), or one recording with --continuous, and 9 rate-table "
        "poses (spin/*.csv)",
    )
    p.add_argument(
        "--continuous",
        action="store_true",
        help="with --calibration-recordings: one array.csv, turning between the poses",
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
    p.add_argument(
        "--smooth",
        action="store_true",
        help="also smooth the run (Rauch-Tung-Striebel): NAME.smoothed.csv and .npz",
    )
    add_output_args(p)
    p.set_defaults(func=cmd_run)
