"""``ngnav bench-stream``: a flight longer than its scenario, and the stream process's
resident size sampled (what a soak reads)."""

from __future__ import annotations

import json
import subprocess
import sys

from ngnav.sim.flight_scenario import load_flight
from telemetry.bench import extended


def test_a_longer_flight_repeats_the_manoeuvres_not_the_take_off():
    scn = load_flight("uav-survey")
    base = scn.legs
    base_s = sum(leg.duration_s for leg in base)
    long = extended(scn, 3600.0)
    assert sum(leg.duration_s for leg in long.legs) >= 3600.0
    assert long.legs[: len(base)] == base
    first_turn = next(i for i, leg in enumerate(base) if leg.bank_deg)
    cycle = base[first_turn:]
    extra = long.legs[len(base) :]
    assert extra == cycle * (len(extra) // len(cycle)) and len(extra) % len(cycle) == 0
    assert sum(leg.duration_s for leg in long.legs) - base_s < 3600.0 - base_s + sum(
        leg.duration_s for leg in cycle
    )
    assert extended(scn, 10.0) is scn


def _bench_stream(*args: str) -> str:
    """``ngnav bench-stream`` on 200 Hz `tactical` at 10x real time, as a user runs it."""
    cmd = [sys.executable, "-m", "ngnav.cli", "bench-stream", "--scenario", "tactical"]
    cmd += ["--set", "run.rate_hz=200", "--speed", "10", *args]
    got = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert got.returncode == 0, got.stderr
    return got.stdout


def test_bench_stream_samples_the_stream_process_memory():
    b = json.loads(_bench_stream("--seconds", "70", "--rss-every", "1", "--json"))
    assert b["flight_s"] >= 69.9  # beyond tactical's 60 s: its manoeuvres again
    assert b["epochs"] > 0 and b["estimate_frames_received"] > 0
    rss = b["rss_mib"]
    assert len(rss) >= 3 and all(m > 10.0 for _, m in rss)
    assert [t for t, _ in rss] == sorted(t for t, _ in rss)
    assert b["rss_slope_mib_per_h"] == b["rss_slope_mib_per_h"]  # a number, not NaN


def test_bench_stream_prints_the_channel_faults_the_stream_found():
    dead = 'faults.inject=[{channel=6, kind="dead", start_s=20.0}]'
    out = _bench_stream("--set", dead, "--seconds", "30")
    line = next(x for x in out.splitlines() if "channel fault" in x)
    assert line.strip().startswith("channel fault: channel 6 dead: detected 20.")
    assert "not isolated" not in line


def test_latency_histogram_percentiles_within_a_bin_of_the_exact_ones():
    import numpy as np

    from telemetry.live import LatencyHistogram

    rng = np.random.default_rng(5)
    x = rng.lognormal(np.log(1e-3), 0.8, 20000)  # around 1 ms, with a long tail
    h = LatencyHistogram()
    for v in x:
        h.add(float(v))
    for q in (50.0, 99.0):
        exact = float(np.percentile(x, q))
        # the bin's upper edge: never below, at most one bin (2.3 %) above
        assert exact <= h.percentile(q) <= exact * 10 ** (1 / LatencyHistogram.PER_DECADE) * 1.0001
    assert h.max_s == x.max() and h.n == x.size
    assert np.isnan(LatencyHistogram().percentile(50.0))
