"""Load benchmark of the live link: a simulated vehicle streamed through ``ngnav stream``.

``ngnav bench-stream`` simulates a flight (``uav-survey``: 1 kHz array; GPS
raised to 10 Hz), keeps its first ``seconds``, and streams the input frames
over loopback UDP at ``speed`` times real time to a real ``ngnav stream``
process, while a collector in this process receives the estimates. It
reports:

- input: datagrams sent, those the stream process did not read (lost in the socket's
  buffer), and the sequence gaps it counted;
- output: estimate frames the stream process sent and the collector
  received, and the sequence gaps the collector saw (lost estimates);
- latency: for every input datagram that produced estimates, the wall time
  from ``recvfrom`` returning in the stream process to its last estimate
  frame leaving ``sendto`` (measured there), p50/p99/max;
- the wall time and the speed reached;
- the stream process's resident size, sampled every ``rss_every_s`` of wall time, and its
  least-squares slope (a soak: is memory flat).

A flight longer than the scenario repeats its manoeuvres (:func:`extended`), so an hour
of ``uav-survey``-like flight is ``--seconds 3600``.

Only the stream process's own figures are latencies; queueing in the
kernel's socket buffer before ``recvfrom`` is not in them, which is why the
target (p99 < 5 ms) is judged at the real-time rate (``--speed 1``), where
nothing queues unless the estimator falls behind.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.simulate import simulate_flight
from telemetry.frames import FrameDecoder
from telemetry.inputs import input_frames
from telemetry.live import Endpoint, _socket, free_udp_port, play_frames
from telemetry.tlog import FrameWriter, frames_of


@dataclass(frozen=True)
class StreamBench:
    """Figures of one load run (see the module docstring)."""

    flight_s: float
    speed: float
    wall_s: float
    input_datagrams: int
    #: datagrams sent less those the stream process read: lost in the kernel's socket
    #: buffer (exact on loopback; a stall that drops 256 frames hides from the 8-bit
    #: sequence gaps below)
    input_datagrams_lost: int
    #: MAVLink sequence gaps in the input (modulo 256 per gap)
    input_frames_lost: int
    estimate_frames_sent: int
    estimate_frames_received: int
    estimate_frames_lost: int
    epochs: int
    latency_p50_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    stream_summary: dict
    #: (wall s, resident MiB) of the stream process, every ``rss_every_s``
    rss_mib: list[tuple[float, float]] = field(default_factory=list)
    #: least-squares slope of the resident size over the run, MiB per wall hour
    rss_slope_mib_per_h: float = float("nan")


def extended(scn: FlightScenario, seconds: float) -> FlightScenario:
    """``scn`` flown for at least ``seconds``: its legs from the first turn on repeat until
    the flight is that long (take-off and climb once; the survey lines and turns again)."""
    legs = list(scn.legs)
    total = sum(leg.duration_s for leg in legs)
    if total >= seconds:
        return scn
    first_turn = next((i for i, leg in enumerate(legs) if leg.bank_deg), 0)
    cycle = legs[first_turn:]
    cycle_s = sum(leg.duration_s for leg in cycle)
    while total < seconds:
        legs += cycle
        total += cycle_s
    return replace(scn, legs=tuple(legs))


def _rss_mib(pid: int) -> float:
    """Resident size of process ``pid``, MiB (Linux /proc; NaN elsewhere)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def run_stream_bench(
    scn: FlightScenario,
    seconds: float,
    speed: float,
    out_rate_hz: float = 50.0,
    busy_poll: bool = False,
    rss_every_s: float = 60.0,
) -> StreamBench:
    """Stream ``seconds`` of ``scn`` through a real ``ngnav stream`` process (see module doc)."""
    sim = simulate_flight(extended(scn, seconds), 0)
    t = sim.samples.t_s
    keep = t <= t[0] + seconds
    samples = type(sim.samples)(t[keep], sim.samples.accel_mps2[keep])
    fixes = sim.fixes.select(sim.fixes.t_s <= t[keep][-1])
    frames = list(frames_of(input_frames(samples, fixes, sim.config), FrameWriter()))

    p_in, p_out = free_udp_port(), free_udp_port()
    rx = _socket()
    rx.bind(("127.0.0.1", p_out))
    rx.settimeout(0.5)
    dec = FrameDecoder()
    got = {"frames": 0}
    done = threading.Event()

    def collect() -> None:
        while not done.is_set():
            try:
                data = rx.recv(65535)
            except (TimeoutError, OSError):
                continue
            got["frames"] += len(dec.decode_buffer(data))

    th = threading.Thread(target=collect, daemon=True)
    th.start()
    rates = [
        f"{k}={out_rate_hz:g}"
        for k in (
            "attitude_quaternion",
            "attitude",
            "local_position_ned",
            "global_position_int",
            "odometry",
        )
    ]
    cmd = [
        sys.executable,
        "-m",
        "ngnav.cli",
        "stream",
        "--in",
        f"udpin:127.0.0.1:{p_in}",
        "--out",
        f"udpout:127.0.0.1:{p_out}",
        "--idle-exit",
        "2",
        "--json",
    ]
    for r in rates:
        cmd += ["--rate", r]
    if busy_poll:
        cmd.append("--busy-poll")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        if "ngnav stream:" not in line:
            raise RuntimeError(f"ngnav stream did not start: {line!r} {proc.stderr.read()}")
        wall0 = time.perf_counter()
        rss: list[tuple[float, float]] = [(0.0, _rss_mib(proc.pid))]

        def sample_rss() -> None:
            while not done.wait(rss_every_s):
                rss.append((time.perf_counter() - wall0, _rss_mib(proc.pid)))

        sampler = threading.Thread(target=sample_rss, daemon=True)
        sampler.start()
        n_dgrams = play_frames(frames, Endpoint("udpout", "127.0.0.1", p_in), speed)
        rss.append((time.perf_counter() - wall0, _rss_mib(proc.pid)))
        out, err = proc.communicate(timeout=24 * 3600)
        wall = time.perf_counter() - wall0
    finally:
        if proc.poll() is None:
            proc.kill()
    time.sleep(0.5)
    done.set()
    th.join()
    rx.close()
    if proc.returncode != 0:
        raise RuntimeError(f"ngnav stream failed: {err}")
    summary = json.loads(out[out.index("{") :])
    sent = sum(summary["frames sent"].values())
    rss = sorted(r for r in rss if np.isfinite(r[1]))
    slope = float("nan")
    if len(rss) >= 3:
        t_h, mib = np.array(rss).T
        slope = float(np.polyfit(t_h / 3600.0, mib, 1)[0])
    return StreamBench(
        flight_s=float(samples.t_s[-1] - samples.t_s[0]),
        speed=speed,
        wall_s=wall,
        input_datagrams=n_dgrams,
        input_datagrams_lost=n_dgrams - summary["datagrams"],
        input_frames_lost=summary["input"].get("sequence gap (frames lost)", 0),
        estimate_frames_sent=sent,
        estimate_frames_received=got["frames"],
        estimate_frames_lost=dec.counts.as_dict().get("sequence gap (frames lost)", 0),
        epochs=summary["estimate epochs"],
        latency_p50_ms=summary["latency p50 ms"],
        latency_p99_ms=summary["latency p99 ms"],
        latency_max_ms=summary["latency max ms"],
        stream_summary=summary,
        rss_mib=[(round(t, 1), round(m, 1)) for t, m in rss],
        rss_slope_mib_per_h=slope,
    )
