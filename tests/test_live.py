"""Live MAVLink over loopback UDP, as real processes, against a tlog replay of the same run.

Three processes: ``ngnav stream`` (the estimator), ``ngnav simulate --stream``
(the vehicle), and ``tests/mav_client.py`` (a pymavlink ``mavutil`` client that
knows only common.xml, as a ground station). The live estimates must equal
those of ``ngnav run run.tlog`` on the same inputs, no estimate frame may be
lost, and the common-only client must see the vehicle, its attitude and its
position.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from filters.output import ESTIMATE_COLUMNS
from telemetry import ngnav_mavlink as mavlink
from telemetry.frames import FrameDecoder
from telemetry.live import free_udp_port
from telemetry.tlog import EPOCH_BASE_US, read_tlog

ROOT = Path(__file__).resolve().parents[1]
NGNAV = [sys.executable, "-m", "ngnav.cli"]
#: Channel 6 dies at 30 s: found, excluded and reported live as in the replay.
DEAD = 'faults.inject=[{channel=6, kind="dead", start_s=30.0}]'
SCENARIO = ["--scenario", "tactical", "--set", "run.rate_hz=200", "--set", DEAD]
#: Messages whose content follows the wall clock on a live link.
WALL_CLOCK = {"SYSTEM_TIME", "HEARTBEAT"}


def _wait_line(proc: subprocess.Popen, text: str) -> None:
    line = proc.stdout.readline()
    assert text in line, f"expected {text!r}, got {line!r}; stderr: {proc.stderr.read()}"


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("live")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    tl = tmp / "run.tlog"
    subprocess.run(
        [*NGNAV, "simulate", *SCENARIO, "--out", str(tl)],
        check=True,
        cwd=ROOT,
        env=env,
        capture_output=True,
    )
    p_in, p_out = free_udp_port(), free_udp_port()
    client_out = tmp / "client.jsonl"
    client = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "mav_client.py"), str(p_out), str(client_out), "4"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
    )
    _wait_line(client, "listening")
    stream = subprocess.Popen(
        [
            *NGNAV,
            "stream",
            "--in",
            f"udpin:127.0.0.1:{p_in}",
            "--out",
            f"udpout:127.0.0.1:{p_out}",
            "--idle-exit",
            "2",
            "--csv",
            str(tmp / "live.csv"),
            "--tlog",
            str(tmp / "live.tlog"),
            "--json",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
    )
    _wait_line(stream, "ngnav stream:")
    sim = subprocess.Popen(
        [*NGNAV, "simulate", *SCENARIO, "--stream", f"udpout:127.0.0.1:{p_in}", "--speed", "20"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # the vehicle has simulated its flight and is about to stream: the bad datagrams go first
    _wait_line(sim, "simulated")
    _send_garbage(p_in)
    _, sim_err = sim.communicate(timeout=300)
    assert sim.returncode == 0, sim_err
    out, err = stream.communicate(timeout=300)
    assert stream.returncode == 0, err
    summary = json.loads(out[out.index("{") :])
    c_out, c_err = client.communicate(timeout=60)
    assert client.returncode == 0, c_err
    rep = subprocess.run(
        [*NGNAV, "run", str(tl), "--out", str(tmp / "replay.tlog")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    assert rep.returncode == 0, rep.stderr
    rep_csv = subprocess.run(
        [*NGNAV, "run", str(tl), "--out", str(tmp / "replay.csv")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    assert rep_csv.returncode == 0, rep_csv.stderr
    client_msgs = [json.loads(line) for line in client_out.read_text().splitlines()]
    return tmp, summary, client_msgs, c_out


def _send_garbage(port: int) -> None:
    """Datagrams a bad link delivers: random bytes, a corrupt frame, a truncated one."""
    from telemetry.tlog import FrameWriter

    rng = np.random.default_rng(11)
    frame = FrameWriter(7, 1).pack(
        mavlink.MAVLink_gps_input_message(
            1, 0, 0, 0, 0, 3, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 1.0, 2.0, 0
        )
    )
    bad_crc = bytearray(frame)
    bad_crc[12] ^= 0xFF
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for data in (
        rng.integers(0, 256, 300, dtype=np.uint8).tobytes(),
        bytes(bad_crc),
        frame[: len(frame) // 2],
        b"\xfd" + rng.integers(0, 256, 40, dtype=np.uint8).tobytes(),
    ):
        s.sendto(data, ("127.0.0.1", port))
    s.close()


def _estimate_frames(path: Path) -> list[tuple[str, dict]]:
    out = []
    for _, msg in read_tlog(path, FrameDecoder()):
        if msg.get_type() in WALL_CLOCK:
            continue
        out.append((msg.get_type(), msg.to_dict()))
    return out


def test_live_link_gives_the_estimates_of_the_tlog_replay(live_run):
    tmp, summary, _, _ = live_run
    assert summary["failure"] is None
    assert summary["input"].get("sequence gap (frames lost)", 0) == 0
    # the bad datagrams sent before the run were counted and cost nothing else
    assert summary["input"]["bad crc"] >= 1 and summary["input"]["truncated frame"] >= 1
    assert summary["input"]["bytes skipped (no frame start)"] > 0
    live = np.loadtxt(tmp / "live.csv", delimiter=",", skiprows=1)
    replay = np.loadtxt(tmp / "replay.csv", delimiter=",", skiprows=1)
    assert live.shape == replay.shape and live.shape[0] > 5000
    # same frames in the same order through the same code: identical, not just close
    np.testing.assert_array_equal(live, replay)
    a = _estimate_frames(tmp / "live.tlog")
    b = _estimate_frames(tmp / "replay.tlog")
    assert len(a) == len(b) > 10000
    assert a == b


def test_a_dead_channel_is_reported_live(live_run):
    """Channel 6 reads 0 from 30 s. The parity sees the first block: A6 or A9 (the pair
    that alone carries wdot_x) is suspected; 25 equal readings at 200 Hz (120 ms, the tests
    run the 100 ms fusion lag ahead of the filter) name A6 dead, and it is out from the
    block at 30.02 s on. The live summary says so, the health message and estimates.csv
    mark the pair, then A6 alone, and the filter runs on."""
    tmp, summary, _, _ = live_run
    assert summary["failure"] is None
    (ev,) = summary["faults"]
    assert ev["channels"] == [6] and ev["kind"] == "dead"
    assert ev["detected_at_s"] == pytest.approx(30.0) and ev["isolated_at_s"] == pytest.approx(
        30.12
    )
    health = [
        m.to_dict()
        for _, m in read_tlog(tmp / "live.tlog", FrameDecoder())
        if m.get_type() == "NGNAV_ARRAY_HEALTH"
    ]
    t = np.array([h["time_usec"] for h in health]) * 1e-6
    bits = np.array([h["faulty_channels"] for h in health])
    pair = (1 << 5) | (1 << 8)
    assert np.all(bits[t < 29.995] == 0) and np.all(bits[(t > 29.995) & (t < 30.015)] == pair)
    assert np.all(bits[t > 30.015] == 1 << 5)
    live = np.loadtxt(tmp / "live.csv", delimiter=",", skiprows=1)
    col = ESTIMATE_COLUMNS.index("faulty_channels")
    assert np.all(live[live[:, 0] > 30.015, col] == 1 << 5)
    # the heartbeat says so: ACTIVE while every channel is healthy, CRITICAL after
    hb = [
        ((t_us - EPOCH_BASE_US) * 1e-6, m.system_status)
        for t_us, m in read_tlog(tmp / "live.tlog", FrameDecoder())
        if m.get_type() == "HEARTBEAT"
    ]
    first_est = live[0, 0]
    before = [st for t, st in hb if first_est < t < 29.99]
    after = [st for t, st in hb if t > 30.02]
    assert before and set(before) == {mavlink.MAV_STATE_ACTIVE}
    assert after and set(after) == {mavlink.MAV_STATE_CRITICAL}


def test_common_only_client_sees_every_estimate_frame_of_the_vehicle(live_run):
    tmp, summary, msgs, client_stdout = live_run
    # pymavlink reports system 0 and sequence 0 for a message it cannot decode (the
    # dialect's NGNAV_ARRAY_HEALTH, unknown to common.xml); the link carries one sender
    ours = [m for m in msgs if (m["sys"], m["comp"]) == (1, 1) or m["type"].startswith("UNKNOWN")]
    assert ours, "the client received nothing from system 1"
    # no estimate lost: the sender's sequence numbers run without a gap (an unknown
    # message takes the next number)
    seqs = []
    for m in ours:
        seqs.append((seqs[-1] + 1) % 256 if m["type"].startswith("UNKNOWN") else m["seq"])
    assert np.all(np.diff(seqs) % 256 == 1)
    assert len(ours) == sum(summary["frames sent"].values())
    types = {m["type"] for m in ours}
    assert {"HEARTBEAT", "ATTITUDE", "GLOBAL_POSITION_INT", "ODOMETRY"} <= types
    assert "UNKNOWN_54004" in types  # the dialect's health message, unknown to common.xml
    hbs = [m["fields"] for m in ours if m["type"] == "HEARTBEAT"]
    assert hbs[0]["type"] == 1 and hbs[0]["autopilot"] == 0  # fixed wing, generic: a vehicle
    # the link was silent before the vehicle started: standby heartbeats went out anyway
    assert hbs[0]["system_status"] == mavlink.MAV_STATE_STANDBY
    assert any(h["system_status"] == mavlink.MAV_STATE_ACTIVE for h in hbs)
    assert "target_system 1" in client_stdout  # mavutil adopted the vehicle
    # the attitude and position the client decoded are the replay's
    replay = _estimate_frames(tmp / "replay.tlog")
    att_r = [d for t, d in replay if t == "ATTITUDE"]
    att_c = [m["fields"] for m in ours if m["type"] == "ATTITUDE"]
    assert len(att_c) == len(att_r)
    assert all(abs(x["roll"] - y["roll"]) == 0 for x, y in zip(att_c, att_r, strict=True))
    pos_c = [m["fields"] for m in ours if m["type"] == "GLOBAL_POSITION_INT"]
    pos_r = [d for t, d in replay if t == "GLOBAL_POSITION_INT"]
    assert [(p["lat"], p["lon"], p["alt"]) for p in pos_c] == [
        (p["lat"], p["lon"], p["alt"]) for p in pos_r
    ]


def test_mavlogdump_reads_the_estimate_tlog(live_run):
    tmp = live_run[0]
    env = dict(os.environ, MAVLINK20="1")
    tool = Path(sys.executable).with_name("mavlogdump.py")
    out = subprocess.run(
        [
            sys.executable,
            str(tool),
            "--types",
            "HEARTBEAT,ATTITUDE,GLOBAL_POSITION_INT",
            str(tmp / "replay.tlog"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert any("HEARTBEAT {type : 1, autopilot : 0" in x for x in lines)
    assert sum("ATTITUDE {" in x for x in lines) > 1000
    assert sum("GLOBAL_POSITION_INT {" in x for x in lines) > 1000


def test_a_slow_step_does_not_read_as_the_link_gone():
    """``idle_exit_s`` counts silence while waiting for input, not while the filter works:
    a step that takes longer than it (one epoch's reader stalls 1.5 s, as a first step
    that compiles the filter would) leaves the link open, and what queued meanwhile is
    processed (tactical's first 12 s at 2x real time over loopback UDP, idle exit 1 s)."""
    import time

    from filters.bench import _first_seconds
    from filters.pipeline import Pipeline
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight
    from telemetry.inputs import input_frames
    from telemetry.live import Endpoint, free_udp_port, play_frames, serve
    from telemetry.outputs import OutputSettings
    from telemetry.tlog import FrameWriter, frames_of

    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    samples, fixes = _first_seconds(sim.samples, sim.fixes, 12.0)
    frames = list(frames_of(input_frames(samples, fixes, sim.config), FrameWriter()))
    p_in = free_udp_port()

    def ready() -> None:
        dest = Endpoint("udpout", "127.0.0.1", p_in)
        threading.Thread(target=play_frames, args=(frames, dest, 2.0), daemon=True).start()

    stalled = []

    def factory(cfg, on_epoch):
        def slow_once(est):
            if not stalled:
                stalled.append(est.t_s)
                time.sleep(1.5)
            on_epoch(est)

        return Pipeline(cfg, on_epoch=slow_once)

    stats = serve(
        Endpoint("udpin", "127.0.0.1", p_in),
        Endpoint("udpout", "127.0.0.1", free_udp_port()),
        factory,
        OutputSettings(),
        idle_exit_s=1.0,
        duration_s=60.0,
        ready=ready,
    )
    assert stalled, "the filter never started"
    t_end = stats.result.estimates.t_s[-1] - samples.t_s[0]
    assert t_end > 11.5, f"the link closed at {t_end:.1f} s of 12 s of flight"
