"""The MAVLink commands of ``ngnav``: output options, ``stream``, ``bench-stream``, replays."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from telemetry import ngnav_mavlink as mavlink
from telemetry.outputs import DEFAULT_RATES_HZ, OutputSettings, parse_rates


def _enum_value(enum: str, text: str) -> int:
    """An enum entry by number or name (``1``, ``MAV_TYPE_FIXED_WING`` or ``FIXED_WING``)."""
    entries = mavlink.enums[enum]
    try:
        v = int(text)
    except ValueError:
        name = text.upper()
        if not name.startswith(enum + "_"):
            name = f"{enum}_{name}"
        for k, e in entries.items():
            if e.name == name:
                return int(k)
        raise ValueError(f"unknown {enum} {text!r}") from None
    if v not in entries:
        raise ValueError(f"unknown {enum} {v}")
    return v


def add_output_args(p: argparse.ArgumentParser) -> None:
    """Options that say who the estimates come from and how often each stream goes."""
    g = p.add_argument_group("MAVLink output")
    g.add_argument("--sysid", type=int, default=1, help="system id, 1-254 (default: 1)")
    g.add_argument("--compid", type=int, default=1, help="component id (default: 1)")
    g.add_argument(
        "--vehicle-type", default="FIXED_WING", help="MAV_TYPE name or number (default: FIXED_WING)"
    )
    g.add_argument(
        "--autopilot", default="GENERIC", help="MAV_AUTOPILOT name or number (default: GENERIC)"
    )
    g.add_argument(
        "--rate",
        action="append",
        default=[],
        metavar="STREAM=HZ",
        help="output rate, repeatable; streams and defaults: "
        + ", ".join(f"{k}={v:g}" for k, v in DEFAULT_RATES_HZ.items()),
    )


def output_settings(args: argparse.Namespace) -> OutputSettings:
    """The :class:`OutputSettings` of parsed :func:`add_output_args` options."""
    return OutputSettings(
        system_id=args.sysid,
        component_id=args.compid,
        vehicle_type=_enum_value("MAV_TYPE", args.vehicle_type),
        autopilot=_enum_value("MAV_AUTOPILOT", args.autopilot),
        rates_hz=parse_rates(args.rate),
    )


def parse_allow(items: list[str]) -> set[tuple[int, int]] | None:
    """``["1:1", "2:200"]`` to ``{(1, 1), (2, 200)}``; empty means every source."""
    if not items:
        return None
    out = set()
    for item in items:
        a, sep, b = item.partition(":")
        try:
            if not sep:
                raise ValueError
            out.add((int(a), int(b)))
        except ValueError:
            raise ValueError(f"--allow {item!r} is not SYSID:COMPID") from None
    return out


def cmd_stream(args: argparse.Namespace) -> int:
    """``ngnav stream``: estimate from a live UDP link, send MAVLink estimates."""
    from filters.output import write_estimates_csv
    from ngnav.api import pipeline_factory, warm_up
    from telemetry.live import parse_endpoint, serve

    src = parse_endpoint(args.inp, "udpin")
    dst = parse_endpoint(args.out, "udpout")
    settings = output_settings(args)
    warm_up()  # the filter compiled or loaded before the link is read

    def ready() -> None:
        print(f"ngnav stream: {src} -> {dst} (system {settings.system_id})", flush=True)

    st = serve(
        src,
        dst,
        pipeline_factory(keep_estimates=args.csv is not None),
        settings,
        allow=parse_allow(args.allow),
        duration_s=args.duration,
        idle_exit_s=args.idle_exit,
        out_tlog=args.tlog,
        ready=ready,
        busy_poll=args.busy_poll,
    )
    from dataclasses import asdict

    p50, p99, pmax = st.latency_percentiles()
    if args.csv is not None and st.result is not None:
        write_estimates_csv(args.csv, st.result.estimates, st.config)
    summary = {
        "datagrams": st.datagrams,
        "estimate epochs": st.epochs,
        "frames sent": st.frames_sent,
        "latency p50 ms": p50 * 1e3,
        "latency p99 ms": p99 * 1e3,
        "latency max ms": pmax * 1e3,
        "input": st.counts,
        "filter": {} if st.result is None else st.result.counts,
        "faults": [] if st.result is None else [asdict(e) for e in st.result.faults],
        "track_losses": [] if st.result is None else [asdict(e) for e in st.result.track_losses],
        "failure": st.failure,
    }
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        latency = (
            f"latency input -> estimate p50 {p50 * 1e3:.3f} ms, p99 {p99 * 1e3:.3f} ms, "
            f"max {pmax * 1e3:.3f} ms"
            if st.epochs
            else "no estimate made"
        )
        print(
            f"  {st.datagrams} datagrams in, {sum(st.frames_sent.values())} frames out; {latency}"
        )
        from ngnav.cli.flight import _print_counts, _print_reports

        # the counters that are not zero (--json keeps every one)
        _print_reports({"input": st.counts, "frames sent": st.frames_sent})
        if st.result is not None:
            _print_counts(st.result.counts)
            for ev in st.result.faults:
                print(f"  channel fault: {ev.describe()}")
            for loss in st.result.track_losses:
                print(f"  track {loss.describe()}")
        if st.failure:
            print(f"  filter stopped: {st.failure}")
    return 0


def run_to_tlog(src: Path, out: Path, args: argparse.Namespace):
    """``ngnav run SRC --out OUT.tlog``: replay through the stream path.

    The result's ``failure`` says why the filter stopped early (its frames up to
    then are in the tlog); a filter that never started is a ``ValueError``.
    """
    from ngnav.api import pipeline_factory
    from telemetry.replay import replay_inputs, replay_tlog
    from telemetry.runfiles import is_tlog, read_run

    settings = output_settings(args)
    make = pipeline_factory(args.compensation)
    if is_tlog(src):
        rr = replay_tlog(src, make, settings, out_tlog=out)
        reports = {str(src): rr.counts}
    else:
        inp = read_run(src)
        rr = replay_inputs(inp, make, settings, out_tlog=out)
        reports = dict(inp.reports)
        reports["MAVLink"] = rr.counts
    if rr.result is None:
        raise ValueError(f"{src}: the filter did not run: {rr.failure}")
    return rr, reports


def cmd_bench_stream(args: argparse.Namespace) -> int:
    """``ngnav bench-stream``: the live link under load (see :mod:`telemetry.bench`)."""
    from ngnav.sim.flight_scenario import load_flight
    from telemetry.bench import run_stream_bench

    overrides = list(args.overrides)
    if not any(o.startswith("gps.rate_hz=") for o in overrides):
        overrides.append("gps.rate_hz=10")
    scn = load_flight(args.scenario, overrides)
    b = run_stream_bench(
        scn, args.seconds, args.speed, args.out_rate, args.busy_poll, args.rss_every
    )
    if args.json:
        from dataclasses import asdict

        print(json.dumps(asdict(b), indent=1))
        return 0
    print(
        f"{scn.name}: {b.flight_s:.1f} s of flight at {scn.run.rate_hz:g} Hz array, "
        f"{scn.gps.rate_hz:g} Hz GPS, estimates at {args.out_rate:g} Hz; "
        f"speed {b.speed:g}x, wall {b.wall_s:.1f} s ({b.flight_s / b.wall_s:.1f}x real time)"
    )
    print(
        f"  input: {b.input_datagrams} datagrams sent, {b.input_datagrams_lost} lost in the "
        f"socket, {b.input_frames_lost} frames lost (sequence gaps)"
    )
    print(
        f"  estimates: {b.epochs} epochs, {b.estimate_frames_sent} frames sent, "
        f"{b.estimate_frames_received} received, {b.estimate_frames_lost} lost (sequence gaps)"
    )
    print(
        f"  latency input arrival -> estimate sent: p50 {b.latency_p50_ms:.3f} ms, "
        f"p99 {b.latency_p99_ms:.3f} ms, max {b.latency_max_ms:.3f} ms"
    )
    f = b.stream_summary["filter"]
    print(
        f"  filter: {f.get('samples held (non-finite)', 0)} samples held, "
        f"{f.get('gps positions rejected (gate)', 0)} GPS positions rejected, "
        f"{f.get('gps fixes later than the fusion lag', 0)} fixes later than the fusion lag"
        + (f"; FAILED: {b.stream_summary['failure']}" if b.stream_summary["failure"] else "")
    )
    from ngnav.records import FaultEvent, TrackLoss

    for ev in b.stream_summary["faults"]:
        ev = FaultEvent(**{**ev, "channels": tuple(ev["channels"])})
        print(f"  channel fault: {ev.describe()}")
    for loss in b.stream_summary["track_losses"]:
        print(f"  track {TrackLoss(**loss).describe()}")
    if b.rss_mib:
        mib = [m for _, m in b.rss_mib]
        print(
            f"  stream process resident size: {mib[0]:.1f} MiB at the start, {min(mib):.1f}-"
            f"{max(mib):.1f} MiB over {len(mib)} samples, slope {b.rss_slope_mib_per_h:+.2f} "
            "MiB per wall hour"
        )
    return 0


def add_stream_parser(sub, add_flight_args) -> None:
    """Register ``ngnav stream`` and ``ngnav bench-stream`` (``add_flight_args``: the
    CLI's ``--scenario``/``--set`` options)."""
    p = sub.add_parser(
        "stream", help="estimate from a live MAVLink UDP link and send the estimates"
    )
    p.add_argument(
        "--in", dest="inp", required=True, metavar="udpin:HOST:PORT", help="input link (bind)"
    )
    p.add_argument(
        "--out", required=True, metavar="udpout:HOST:PORT", help="where estimates are sent"
    )
    p.add_argument("--duration", type=float, help="stop after this many wall seconds")
    p.add_argument(
        "--idle-exit", type=float, help="stop after this many silent seconds once input came"
    )
    p.add_argument(
        "--allow", action="append", default=[], metavar="SYSID:COMPID", help="accepted sources"
    )
    p.add_argument(
        "--busy-poll",
        action="store_true",
        help="spin on the input socket instead of sleeping (one core busy, lower latency)",
    )
    p.add_argument("--csv", help="also write every estimate as estimates.csv at the end")
    p.add_argument("--tlog", help="also log the estimate frames sent as a tlog")
    p.add_argument("--json", action="store_true", help="summary as JSON")
    add_output_args(p)
    p.set_defaults(func=cmd_stream)

    p = sub.add_parser(
        "bench-stream", help="load benchmark: a flight streamed through ngnav stream over UDP"
    )
    add_flight_args(p)
    p.add_argument(
        "--seconds",
        type=float,
        default=600.0,
        help="flight seconds; beyond the scenario its manoeuvres repeat (default: 600)",
    )
    p.add_argument(
        "--speed", type=float, default=10.0, help="times real time; 1 = real time (default: 10)"
    )
    p.add_argument("--out-rate", type=float, default=50.0, help="estimate rate, Hz (default: 50)")
    p.add_argument("--busy-poll", action="store_true", help="run ngnav stream --busy-poll")
    p.add_argument(
        "--rss-every",
        type=float,
        default=60.0,
        metavar="S",
        help="sample the stream process's resident size every S wall seconds (default: 60)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bench_stream)
