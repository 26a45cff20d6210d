"""Live MAVLink over UDP: play a run's inputs onto a link, and estimate from a link.

Endpoints are written as pymavlink writes them: ``udpin:HOST:PORT`` binds and
receives, ``udpout:HOST:PORT`` sends to that address.

- :func:`play_frames` sends input frames at their run-clock times, in real
  time (``speed=1``), faster (``speed=N``) or as fast as the socket takes
  them (``speed=0``); frames due at the same time share a datagram of at most
  :data:`MAX_DATAGRAM` bytes.
- :func:`serve` reads datagrams from ``udpin``, decodes each on its own
  (:meth:`telemetry.session.StreamSession.feed_datagram`), and sends every
  estimate frame to ``udpout`` as soon as it exists. A HEARTBEAT goes out every
  second of wall time with no other heartbeat (a silent input link included),
  with ``MAV_STATE_STANDBY`` before the filter starts. It stops on
  ``duration_s``, on ``idle_exit_s`` of silence after the first datagram, or
  on SIGINT/SIGTERM, then flushes the filter. What ground stations send back to the
  output socket is read every pass of the loop and answered or counted
  (:meth:`telemetry.session.StreamSession.feed_command`), so its queue never fills.
"""

from __future__ import annotations

import gc
import math
import signal
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ngnav.records import RunResult
from ngnav.runconfig import RunConfig
from telemetry.outputs import OutputSettings
from telemetry.session import EstimatorFactory, OutputFrame, StreamSession
from telemetry.tlog import tlog_record

#: Largest datagram :func:`play_frames` builds from frames due together, bytes.
MAX_DATAGRAM = 1400
#: Datagrams read from the output socket per pass of the serve loop (a pass takes at most
#: the input socket's 0.2 s timeout): far above what a ground station sends.
COMMANDS_PER_PASS = 64
#: Socket buffer asked for on both ends (the kernel may cap it), bytes.
SOCKET_BUFFER = 8 * 1024 * 1024


@dataclass(frozen=True)
class Endpoint:
    """A UDP endpoint: ``mode`` is ``"udpin"`` (bind) or ``"udpout"`` (send to)."""

    mode: str
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.mode}:{self.host}:{self.port}"


def parse_endpoint(text: str, mode: str) -> Endpoint:
    """Parse ``udpin:HOST:PORT`` / ``udpout:HOST:PORT``; ``mode`` is the one required."""
    parts = text.split(":")
    if len(parts) != 3 or parts[0] not in ("udpin", "udpout"):
        raise ValueError(f"endpoint {text!r} is not udpin:HOST:PORT or udpout:HOST:PORT")
    if parts[0] != mode:
        raise ValueError(f"endpoint {text!r}: expected {mode}:HOST:PORT here")
    try:
        port = int(parts[2])
    except ValueError:
        raise ValueError(f"endpoint {text!r}: port {parts[2]!r} is not a number") from None
    if not 0 < port < 65536:
        raise ValueError(f"endpoint {text!r}: port {port} out of range")
    return Endpoint(parts[0], parts[1], port)


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port free on ``host`` just now (the OS picks it; another process may take it)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((host, 0))
        return int(s.getsockname()[1])
    finally:
        s.close()


def _socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for opt in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        try:
            s.setsockopt(socket.SOL_SOCKET, opt, SOCKET_BUFFER)
        except OSError:
            pass
    return s


def _datagrams(frames: Iterable[tuple[int, bytes]]):
    """Group consecutive frames with one send time into datagrams (<= MAX_DATAGRAM)."""
    t_cur, buf = None, b""
    for t_us, frame in frames:
        if buf and (t_us != t_cur or len(buf) + len(frame) > MAX_DATAGRAM):
            yield t_cur, buf
            buf = b""
        t_cur = t_us
        buf += frame
    if buf:
        yield t_cur, buf


def play_frames(frames: Iterable[tuple[int, bytes]], dest: Endpoint, speed: float = 1.0) -> int:
    """Send ``(run-clock time_usec, frame)`` pairs to ``dest``; returns datagrams sent.

    ``speed`` is run seconds per wall second (0: no pacing).
    """
    if dest.mode != "udpout":
        raise ValueError(f"play needs a udpout endpoint, got {dest}")
    if speed < 0 or not np.isfinite(speed):
        raise ValueError(f"speed must be >= 0, got {speed}")
    sock = _socket()
    addr = (dest.host, dest.port)
    n = 0
    t_first = None
    wall0 = time.perf_counter()
    try:
        for t_us, data in _datagrams(frames):
            if t_first is None:
                t_first = t_us
            if speed > 0:
                due = wall0 + (t_us - t_first) * 1e-6 / speed
                wait = due - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            sock.sendto(data, addr)
            n += 1
    finally:
        sock.close()
    return n


class LatencyHistogram:
    """Latencies (s) in fixed logarithmic bins: memory stays flat over a run of any length.

    100 bins a decade from 1 us to 100 s (each 2.3 % wide); a percentile is its bin's
    upper edge (at most 2.3 % high), the maximum is exact. A list of every latency grew
    by 5.8 MB an hour of a 50 Hz link (`ngnav bench-stream --seconds 3600`).
    """

    LO_S = 1e-6
    PER_DECADE = 100
    DECADES = 8

    def __init__(self) -> None:
        self.counts = np.zeros(self.PER_DECADE * self.DECADES + 2, dtype=np.int64)
        self.n = 0
        self.max_s = float("nan")

    def add(self, latency_s: float) -> None:
        """Count one latency, s."""
        if latency_s > 0:
            i = math.floor(math.log10(latency_s / self.LO_S) * self.PER_DECADE) + 1
            i = min(max(i, 0), self.counts.shape[0] - 1)
        else:
            i = 0
        self.counts[i] += 1
        self.n += 1
        if not latency_s <= self.max_s:
            self.max_s = float(latency_s)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (0-100), s: its bin's upper edge; NaN when empty."""
        if self.n == 0:
            return float("nan")
        i = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.n))
        edge = self.LO_S * 10.0 ** (i / self.PER_DECADE)
        return min(edge, self.max_s)


@dataclass
class ServeStats:
    """What :func:`serve` did: counts, frames sent per message, latencies."""

    counts: dict[str, int]
    frames_sent: dict[str, int]
    datagrams: int
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)
    result: RunResult | None = None
    failure: str | None = None
    config: RunConfig | None = None
    epochs: int = 0

    def latency_percentiles(self) -> tuple[float, float, float]:
        """p50, p99 and max of the input-to-estimate latency, s (NaN with no samples)."""
        h = self.latency
        return h.percentile(50.0), h.percentile(99.0), h.max_s


def serve(
    source: Endpoint,
    dest: Endpoint,
    make_estimator: EstimatorFactory,
    settings: OutputSettings | None = None,
    *,
    allow: set[tuple[int, int]] | None = None,
    duration_s: float | None = None,
    idle_exit_s: float | None = None,
    out_tlog: str | Path | None = None,
    ready=None,
    busy_poll: bool = False,
) -> ServeStats:
    """Estimate from a live input link and send the estimates (see the module docstring).

    ``make_estimator(config, on_epoch)`` builds the estimator once the link's
    configuration has arrived (:class:`telemetry.session.StreamSession`).
    ``latency`` holds, for every datagram that produced estimate frames,
    the wall time from its arrival (``recvfrom`` returning) to its last
    estimate frame leaving ``sendto``. ``ready`` is called once the input
    socket is bound (tests use it to start the sender). ``busy_poll`` spins on a
    non-blocking socket instead of sleeping in ``recvfrom``: it keeps one core busy
    and the process's caches warm, which cuts the latency at real-time rates.
    """
    if source.mode != "udpin" or dest.mode != "udpout":
        raise ValueError(
            f"stream needs --in udpin:HOST:PORT and --out udpout:HOST:PORT, got {source} {dest}"
        )
    session = StreamSession(
        make_estimator, settings, allow=allow, wall_clock=lambda: time.time_ns() // 1000
    )
    rx = _socket()
    try:
        rx.bind((source.host, source.port))
    except OSError as exc:
        rx.close()
        raise ValueError(f"cannot bind {source}: {exc}") from None
    if busy_poll:
        rx.setblocking(False)
    else:
        rx.settimeout(0.2)
    tx = _socket()
    addr = (dest.host, dest.port)
    sent: Counter[str] = Counter()
    latencies = LatencyHistogram()
    fh = Path(out_tlog).open("wb") if out_tlog is not None else None
    stop = {"flag": False}

    def on_signal(signum, frame) -> None:
        stop["flag"] = True

    old = {}
    if threading.current_thread() is threading.main_thread():
        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    last_hb = -1.0
    t_start = time.monotonic()
    t_last_rx = None
    n_dgrams = 0

    def send(frames: list[OutputFrame], to: tuple = addr) -> None:
        nonlocal last_hb
        for f in frames:
            try:
                tx.sendto(f.frame, to)
            except OSError:
                session.counts.add("estimate frames not sent (socket error)")
                continue
            sent[f.name] += 1
            if f.name == "HEARTBEAT":
                last_hb = time.monotonic()
            if fh is not None:
                fh.write(tlog_record(f.t_us, f.frame))

    def read_commands() -> None:
        """Answer what ground stations sent to the output socket (at most a queue's worth)."""
        for _ in range(COMMANDS_PER_PASS):
            try:
                # without blocking; the socket stays blocking for the estimates' sends
                data, peer = tx.recvfrom(65535, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                # an ICMP port-unreachable from the destination, say: nothing to read
                return
            send(session.feed_command(data), peer)

    # what exists now (the generated dialect's tables, above all) lives for the whole
    # run: keep it out of the garbage collector's sweeps, which otherwise cost tens of ms
    gc.collect()
    gc.freeze()
    if ready is not None:
        ready()
    try:
        while not stop["flag"]:
            now = time.monotonic()
            if duration_s is not None and now - t_start >= duration_s:
                break
            if idle_exit_s is not None and t_last_rx is not None and now - t_last_rx >= idle_exit_s:
                break
            if now - last_hb >= 1.0:
                send([session.heartbeat()])
            read_commands()
            try:
                data, _ = rx.recvfrom(65535)
            except (TimeoutError, BlockingIOError):
                continue
            except OSError:
                continue
            t_rx = time.perf_counter()
            t_last_rx = time.monotonic()
            n_dgrams += 1
            session.feed_datagram(data)
            frames = session.take()
            if frames:
                send(frames)
                latencies.add(time.perf_counter() - t_rx)
            # silence is counted while waiting, not while the filter works (a long step
            # would otherwise read as the link gone and drop what queued meanwhile)
            t_last_rx = time.monotonic()
        result = session.finish()
        send(session.take())
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        rx.close()
        tx.close()
        if fh is not None:
            fh.close()
    counts = session.counts.as_dict()
    for kind, n in session.command_decoder.counts.as_dict().items():
        counts[f"return link: {kind}"] = n
    return ServeStats(
        counts,
        dict(sent),
        n_dgrams,
        latencies,
        result,
        session.failure,
        session.config,
        session.estimator.n_epochs if session.estimator is not None else 0,
    )
