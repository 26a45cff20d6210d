"""Speed: ``ngnav bench`` (front end + compensation) and ``ngnav bench-filter``."""

from __future__ import annotations

import argparse

from ngnav.cli import add_flight_args, flight_scenario


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

    b = run_filter_bench(flight_scenario(args), seconds=args.seconds, repeats=args.repeats)
    if args.json:
        import json

        print(json.dumps(b.as_dict(), indent=2))
        return 0
    print(
        f"{b.scenario}: first {args.seconds:g} s, {b.samples} samples at {b.array_rate_hz:g} Hz, "
        f"filter at {b.filter_rate_hz:g} Hz ({b.blocks} blocks), {b.gps_fixes} GPS fixes at "
        f"{b.gps_rate_hz:g} Hz, {b.model_updates} vehicle-model and {b.rest_updates} rest "
        f"updates, {b.state_size} error states; median of {args.repeats}, one core"
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
    print(
        f"  per filter step    {b.pipeline_step_us:10,.0f} us (bare loop {b.bare_step_us:,.0f} us)"
    )
    print(f"  pipeline / bare loop time: {b.slowdown:.2f}x")
    print("  pipeline runs (s): " + ", ".join(f"{t:.2f}" for t in b.pipeline_s))
    return 0


def add_parsers(sub) -> None:
    """Register ``ngnav bench`` and ``ngnav bench-filter``."""
    p = sub.add_parser("bench", help="speed of the front end + compensation loop")
    p.add_argument("--samples", type=int, default=20_000)
    p.add_argument("--repeats", type=int, default=5)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser(
        "bench-filter", help="speed of the whole GPS/array pipeline beside a bare filterpy loop"
    )
    add_flight_args(p)
    p.add_argument(
        "--seconds", type=float, default=120.0, help="flight seconds timed (default: %(default)s)"
    )
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument(
        "--json", action="store_true", help="print the figures as JSON, to compare machines"
    )
    p.set_defaults(func=cmd_bench_filter)
