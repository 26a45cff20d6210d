"""MAVLink telemetry: the dialect, tlog round trips, and bad bytes (real pymavlink, real files)."""

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from telemetry import ngnav_mavlink as mavlink
from telemetry.frames import FrameDecoder
from telemetry.generate import DIALECT_XML, GENERATED, generate
from telemetry.inputs import InputAssembler, input_frames
from telemetry.runfiles import read_run, write_run
from telemetry.tlog import FrameWriter, read_tlog

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def short_run():
    return simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)


@pytest.fixture(scope="module")
def frames(short_run):
    w = FrameWriter()
    return [
        w.pack(m) for _, m in input_frames(short_run.samples, short_run.fixes, short_run.config)
    ]


def test_generated_module_is_mavgen_output_of_the_dialect(tmp_path):
    out = generate(tmp_path / "fresh.py")
    assert out.read_bytes() == GENERATED.read_bytes(), "run: python -m telemetry.generate"
    assert mavlink.WIRE_PROTOCOL_VERSION == "2.0"


def test_dialect_ids_are_free_in_common_and_ardupilotmega():
    from pymavlink.dialects.v20 import ardupilotmega, common

    ours = [int(m.get("id")) for m in ET.parse(DIALECT_XML).getroot().iter("message")]
    assert len(ours) == 5 and all(i > 255 for i in ours)
    for i in ours:
        assert i in mavlink.mavlink_map
        assert i not in common.mavlink_map and i not in ardupilotmega.mavlink_map


def test_tlog_round_trip_of_a_run(tmp_path, short_run):
    path = write_run(tmp_path / "run.tlog", short_run.samples, short_run.fixes, short_run.config)
    inp = read_run(path)
    n_frames = sum(1 for _ in read_tlog(path))
    assert inp.reports[str(path)] == {"frames decoded": n_frames}
    a0, a1 = short_run.samples.accel_mps2, inp.samples.accel_mps2
    # float32 on the wire: half an ulp of float32 relative
    assert np.all(np.abs(a1 - a0) <= np.abs(a0) * 2.0**-24 + 1e-30)
    assert np.allclose(inp.samples.t_s, short_run.samples.t_s, rtol=0, atol=1e-12)
    f0, f1 = short_run.fixes, inp.fixes
    assert np.all(np.abs(f1.lat_deg - f0.lat_deg) <= 0.5e-7 + 1e-12)
    assert np.allclose(f1.vel_ned_mps, f0.vel_ned_mps, rtol=2.0**-23, atol=0)
    assert inp.config.filter == short_run.config.filter
    assert np.array_equal(
        inp.config.known_errors.axis_error_rad, short_run.config.known_errors.axis_error_rad
    )
    # and on to CSV: the same records to the CSV's 10 significant digits
    d = write_run(tmp_path / "csv", inp.samples, inp.fixes, inp.config)
    back = read_run(d)
    assert np.allclose(back.samples.accel_mps2, inp.samples.accel_mps2, rtol=5e-10, atol=0)


def test_corrupt_tlog_loses_only_the_bad_frames(tmp_path, frames):
    rng = np.random.default_rng(4)
    ts = 1_767_225_600_000_000
    parts, bad = [], set()
    for k, fr in enumerate(frames):
        b = bytearray(fr)
        if k % 97 == 5:  # one flipped payload byte: fails its CRC
            b[12] ^= 0x5A
            bad.add(k)
        parts.append((ts + k).to_bytes(8, "big") + bytes(b))
        if k % 131 == 7:  # garbage between records
            parts.append(bytes(rng.integers(0, 256, 23, dtype=np.uint8)))
    blob = b"".join(parts)
    path = tmp_path / "bad.tlog"
    path.write_bytes(blob[:-5])  # truncated tail: the last frame is cut
    dec = FrameDecoder()
    got = list(read_tlog(path, dec))
    c = dec.counts.as_dict()
    assert c["bad crc"] >= len(bad)
    assert c["truncated frame"] == 1
    assert c["frames decoded"] == len(frames) - len(bad) - 1
    assert len(got) == len(frames) - len(bad) - 1


def test_one_corrupt_datagram_does_not_cost_the_next(frames):
    dec = FrameDecoder()
    good = frames[10]
    cut = good[: len(good) // 2]  # a truncated frame ends its datagram
    assert dec.decode_buffer(cut) == []
    assert len(dec.decode_buffer(good)) == 1
    assert dec.counts.as_dict()["truncated frame"] == 1


def test_allowlist_and_sequence_gaps(frames):
    other = FrameWriter(system_id=42, component_id=1).pack(
        mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)
    )
    dec = FrameDecoder(allow={(1, 1)})
    buf = frames[0] + other + frames[3]  # frames 1 and 2 lost
    msgs = dec.decode_buffer(buf)
    assert len(msgs) == 2
    c = dec.counts.as_dict()
    assert c["rejected source (allowlist)"] == 1 and c["sequence gap (frames lost)"] == 2


def test_assembler_counts_bad_inputs():
    asm = InputAssembler()
    nan = float("nan")
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(1000, [1.0] * 9 + [0.0] * 7, 0x1FF, 0, 9))
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(1000, [1.0] * 9 + [0.0] * 7, 0x1FF, 0, 9))
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(500, [1.0] * 9 + [0.0] * 7, 0x1FF, 0, 9))
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(2000, [nan] + [1.0] * 15, 0x1FF, 0, 9))
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(3000, [1.0] * 16, 0x3FF, 0, 10))
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(4000, [1.0] * 16, 0x1FF, 0, 9))
    asm.add(mavlink.MAVLink_ngnav_array_sample_message(5000, [1.0] * 16, 0x1FE, 0, 9))
    no_fix = mavlink.MAVLink_gps_input_message(
        1000, 0, 0, 0, 0, 1, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 1.0, 2.0, 0
    )
    asm.add(no_fix)
    c = asm.counts.as_dict()
    assert c == {
        "array sample duplicate time": 1,
        "array sample out of order": 1,
        "non-finite field": 1,
        "wrong channel count": 1,
        "gps without fix": 1,
    }
    s = asm.samples()
    assert s.t_s.shape == (5,) and np.isnan(s.accel_mps2[1, 0]) and np.isnan(s.accel_mps2[2]).all()
    assert np.isnan(s.accel_mps2[4, 0]) and np.isfinite(s.accel_mps2[4, 1:]).all()
    assert asm.counts.as_dict()["missing samples filled"] == 1


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_fuzz_random_and_mutated_streams(frames, data):
    """No exception escapes; every message returned is an intact frame of the source."""
    k = data.draw(st.integers(0, len(frames) - 8))
    stream = bytearray(b"".join(frames[k : k + 8]))
    n_mut = data.draw(st.integers(0, 12))
    for _ in range(n_mut):
        op = data.draw(st.sampled_from(["flip", "insert", "delete"]))
        pos = data.draw(st.integers(0, max(0, len(stream) - 1)))
        if op == "flip" and stream:
            stream[pos] ^= data.draw(st.integers(1, 255))
        elif op == "insert":
            stream[pos:pos] = data.draw(st.binary(min_size=1, max_size=20))
        elif stream:
            del stream[pos : pos + data.draw(st.integers(1, 20))]
    if data.draw(st.booleans()):
        stream = bytearray(data.draw(st.binary(max_size=400)))
    dec = FrameDecoder()
    asm = InputAssembler()
    originals = {bytes(f) for f in frames}
    for msg in dec.decode_buffer(bytes(stream)):
        assert bytes(msg.get_msgbuf()) in originals or msg.get_type() == "BAD_DATA" or _crc_ok(msg)
        asm.add(msg)


def _crc_ok(msg) -> bool:
    # a random byte string can form a valid frame by chance (CRC-16): re-decode it
    return FrameDecoder().decode_frame(bytes(msg.get_msgbuf())) is not None


def test_cli_simulate_convert_and_run_a_tlog(tmp_path):
    run = (sys.executable, "-m", "ngnav.cli")
    tl = tmp_path / "run.tlog"
    sim = subprocess.run(
        [*run, "simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--out", str(tl)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert sim.returncode == 0, sim.stderr
    assert tl.is_file() and (tmp_path / "run.truth.csv").is_file()
    conv = subprocess.run(
        [*run, "convert", str(tl), str(tmp_path / "dir")], capture_output=True, text=True, cwd=ROOT
    )
    assert conv.returncode == 0, conv.stderr
    out = subprocess.run([*run, "run", str(tl)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "against run.truth.csv" in out.stdout
    a = np.loadtxt(tmp_path / "run.estimates.csv", delimiter=",", skiprows=1)
    # the CLI's tlog path is the library's stream replay: the same estimates, bit for bit
    from filters.output import write_estimates_csv
    from filters.pipeline import run_filter
    from ngnav.api import pipeline_factory
    from telemetry.replay import replay_tlog

    rr = replay_tlog(tl, pipeline_factory())
    write_estimates_csv(tmp_path / "lib.csv", rr.result.estimates, rr.config)
    b = np.loadtxt(tmp_path / "lib.csv", delimiter=",", skiprows=1)
    assert a.shape == b.shape and np.array_equal(a, b)
    # and the batch run of the assembled samples gives them to rounding (the stream
    # takes its sample interval from the first samples, the batch from all of them)
    inp = read_run(tl)
    res = run_filter(inp.samples, inp.fixes, inp.config)
    np.testing.assert_allclose(rr.result.estimates.pos_ned_m, res.estimates.pos_ned_m, atol=1e-6)
    np.testing.assert_allclose(rr.result.estimates.q_nb, res.estimates.q_nb, atol=1e-9)
    # a tlog without a configuration: a clear error
    (tmp_path / "empty.tlog").write_bytes(b"")
    bad = subprocess.run(
        [*run, "run", str(tmp_path / "empty.tlog")], capture_output=True, text=True, cwd=ROOT
    )
    assert bad.returncode == 2 and "no complete NGNAV_CONFIG_TEXT" in bad.stderr
