"""The ``ngnav`` command: the composition root, the only place that wires modules together.

This module holds :func:`main` (its error handling and exit codes), :func:`build_parser`
and the argument helpers the commands share; the commands live by topic:
:mod:`ngnav.cli.paper` (``paper``, ``grey``), :mod:`ngnav.cli.flight` (``simulate``,
``convert``, ``run``), :mod:`ngnav.cli.stream` (``stream``, ``bench-stream``, the
MAVLink output options), :mod:`ngnav.cli.assess` (``evaluate``, ``consistency``) and
:mod:`ngnav.cli.bench` (``bench``, ``bench-filter``).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from ngnav import __version__

# The filter's linear algebra is on matrices of tens of rows, where BLAS threads gain nothing
# and on a busy machine cost many times the work (`ngnav run --smooth` on `tactical`: 6 s
# alone; beside a two-worker campaign 16-37 s, 9-10 s on one thread): one thread unless
# the user's environment says otherwise. Set here, before anything imports numpy.
_BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
if not any(v in os.environ for v in _BLAS_THREADS):
    os.environ.update(dict.fromkeys(_BLAS_THREADS, "1"))

#: Exit status of a run whose filter diverged or lost its track (estimates up to it kept).
EXIT_DIVERGED = 3


def add_set_arg(p: argparse.ArgumentParser, example: str = "") -> None:
    """``--set SECTION.KEY=VALUE`` (repeatable) into ``args.overrides``."""
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a scenario value"
        + (f", {example.strip()}" if example else "")
        + " (repeatable)",
    )


def add_scenario_args(p: argparse.ArgumentParser) -> None:
    """``--scenario`` (a tilt-table scenario) and ``--set``."""
    p.add_argument(
        "--scenario",
        default="tilt-table",
        help="shipped scenario name or TOML path (default: %(default)s)",
    )
    add_set_arg(p, "e.g. --set sensor.noise_mv=0.5 ")


def add_flight_args(p: argparse.ArgumentParser, default: str = "uav-survey") -> None:
    """``--scenario`` (a flight scenario) and ``--set``."""
    p.add_argument(
        "--scenario",
        default=default,
        help="shipped flight scenario (static, uav-survey, tactical, projectile, multirotor, "
        "ground) or TOML path "
        "(default: %(default)s)",
    )
    add_set_arg(p)


def flight_scenario(args: argparse.Namespace):
    """The flight scenario of :func:`add_flight_args`'s options (ValueError if not a flight)."""
    from ngnav.sim.flight_scenario import is_flight_scenario, load_flight

    if getattr(args, "run_index", 0) < 0:
        raise ValueError(f"--run-index must be 0 or more, got {args.run_index}")
    if not is_flight_scenario(args.scenario):
        raise ValueError(f"scenario {args.scenario!r} is not a flight (it has no [flight] section)")
    return load_flight(args.scenario, args.overrides)


def show_progress() -> bool:
    """Whether to draw progress bars: only for a person watching stderr (a terminal, and
    not CI, whose runners set ``CI``); piped or logged output stays clean."""
    return sys.stderr.isatty() and not os.environ.get("CI")


class FractionBar:
    """A tqdm bar on stderr driven by the fraction done (0-1), as ``run_filter`` reports it;
    nothing is drawn unless :func:`show_progress`. Use as a context manager."""

    def __init__(self, desc: str) -> None:
        from tqdm import tqdm

        self._bar = tqdm(total=100, desc=desc, unit="%", disable=not show_progress())

    def __call__(self, fraction: float) -> None:
        done = min(100, int(100 * fraction))
        if done > self._bar.n:
            self._bar.update(done - self._bar.n)

    def __enter__(self) -> FractionBar:
        return self

    def __exit__(self, *exc) -> None:
        self._bar.close()


def build_parser() -> argparse.ArgumentParser:
    from ngnav.cli import assess, bench, calibrate, demo, flight, paper, plot
    from ngnav.cli.stream import add_stream_parser

    parser = argparse.ArgumentParser(
        prog="ngnav", description="GPS-aided navigation with a gyro-free nine-accelerometer IMU."
    )
    parser.add_argument("--version", action="version", version=f"ngnav {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo.add_parsers(sub)
    paper.add_parsers(sub)
    flight.add_parsers(sub)
    add_stream_parser(sub, add_flight_args)
    assess.add_parsers(sub)
    plot.add_parsers(sub)
    calibrate.add_parsers(sub)
    bench.add_parsers(sub)
    return parser


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
