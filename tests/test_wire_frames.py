"""The frame layer by construction: allowlist, CRC, message ids, sequence gaps, corrupt streams.

Every frame here is built without ngnav's encoder: with pymavlink's ``common``
dialect or by hand (:mod:`tests.wire_reference`). Pairs of frames differ in
exactly the bytes under test (checked), and every expected count follows from
how the input was built (which frames were corrupted, dropped, cut, how much
garbage went in), never from running a decoder.
"""

from __future__ import annotations

import socket

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common

from filters.pipeline import Pipeline
from ngnav.cli.stream import parse_allow
from telemetry.frames import REJECTED, UNKNOWN, FrameDecoder
from telemetry.live import Endpoint, free_udp_port, serve
from telemetry.outputs import OutputSettings
from telemetry.session import StreamSession
from telemetry.tlog import read_tlog
from tests.wire_reference import (
    DIALECT,
    EPOCH_2026_US,
    frame_crc,
    pack_custom,
    parse_header,
)

A, B = (7, 42), (9, 1)
#: Every byte but the two MAVLink start bytes.
CLEAN = tuple(b for b in range(256) if b not in (0xFD, 0xFE))
UNKNOWN_ID = 54999  # not in common.xml nor in ngnav.xml (54000-54004)


def _factory(cfg, on_epoch):
    return Pipeline(cfg, on_epoch=on_epoch)


def make_session(**kw) -> StreamSession:
    """A StreamSession running the real filter."""
    return StreamSession(_factory, **kw)


def common_frame(msg, src: tuple[int, int] = A, seq: int = 0, v1: bool = False) -> bytes:
    """Pack with pymavlink's common dialect."""
    mav = common.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    mav.seq = seq
    return bytes(msg.pack(mav, force_mavlink1=v1))


def gps_input(t_us: int = 1_000_000, lat: int = 341_000_000):
    return common.MAVLink_gps_input_message(
        t_us, 0, 6, 0, 0, 3, lat, -1_065_000_000, 1500.0, 0.0, 0.0, 1.0, 60.0, 0.5, 0.1, 1.5,
        3.0, 10,
    )  # fmt: skip


def heartbeat():
    return common.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)


def _clean(frame: bytes) -> bool:
    """No MAVLink start byte after the frame's first."""
    return all(b in CLEAN for b in frame[1:])


def differing(a: bytes, b: bytes) -> list[int]:
    assert len(a) == len(b)
    return [i for i in range(len(a)) if a[i] != b[i]]


def with_crc(frame: bytearray | bytes, crc_extra: int) -> bytes:
    """``frame`` with its two CRC bytes recomputed (MAVLink 2, unsigned)."""
    body = bytes(frame[:-2])
    return body + frame_crc(body, crc_extra)


GPS_INPUT_CRC_EXTRA = 151  # common.xml GPS_INPUT (id 232)


# ============================================================ pairs: one field differs
def _variants(lat: int) -> dict[str, bytes]:
    base = common_frame(gps_input(lat=lat), A, seq=5)
    out = {"base": base}
    out["sysid"] = common_frame(gps_input(lat=lat), (8, 42), seq=5)
    out["compid"] = common_frame(gps_input(lat=lat), (7, 43), seq=5)
    lo = bytearray(base)
    lo[-2] ^= 0x01
    out["crc_lo"] = bytes(lo)
    hi = bytearray(base)
    hi[-1] ^= 0x80
    out["crc_hi"] = bytes(hi)
    pl = bytearray(base)
    pl[14] ^= 0x01  # lat, least significant byte (lat follows time_usec on the wire)
    out["payload"] = bytes(pl)
    unk = bytearray(base)
    unk[7:10] = UNKNOWN_ID.to_bytes(3, "little")
    out["msgid_unknown"] = bytes(unk)
    other = bytearray(base)
    other[7:10] = (24).to_bytes(3, "little")  # GPS_RAW_INT: known id, other CRC_EXTRA
    out["msgid_known"] = bytes(other)
    return out


@pytest.fixture(scope="module")
def pair() -> dict:
    """A GPS_INPUT frame of source A and its variants, each differing in one field only.

    The latitude is chosen so that no frame holds a start byte after its first: a
    rejected frame was once rescanned byte by byte (see
    test_rejected_source_frame_costs_only_itself), and a start byte inside it added
    counts that are not the allowlist's.
    """
    for lat in range(341_000_000, 341_100_000):
        out = _variants(lat)
        if all(_clean(fr) for fr in out.values()):
            break
    else:
        raise AssertionError("no clean frame")
    base = out["base"]
    # the pairs differ where they must, and only there
    n = len(base)
    assert base[-2:] == frame_crc(base[:-2], GPS_INPUT_CRC_EXTRA)
    assert differing(base, out["sysid"]) == [5, n - 2, n - 1]
    assert differing(base, out["compid"]) == [6, n - 2, n - 1]
    assert differing(base, out["crc_lo"]) == [n - 2]
    assert differing(base, out["crc_hi"]) == [n - 1]
    assert differing(base, out["payload"]) == [14]
    assert differing(base, out["msgid_unknown"]) == [7, 8]
    assert differing(base, out["msgid_known"]) == [7]
    return {**out, "lat": lat}


@pytest.mark.parametrize(
    ("variant", "allow", "kind"),
    [
        ("base", {A}, "frames decoded"),
        ("base", None, "frames decoded"),
        ("sysid", {A}, "rejected source (allowlist)"),
        ("compid", {A}, "rejected source (allowlist)"),
        ("sysid", None, "frames decoded"),
        ("compid", None, "frames decoded"),
        ("sysid", {(8, 42)}, "frames decoded"),
        ("compid", {(7, 43)}, "frames decoded"),
        ("crc_lo", None, "bad crc"),
        ("crc_hi", None, "bad crc"),
        ("payload", None, "bad crc"),
        ("msgid_known", None, "bad crc"),
        ("msgid_unknown", None, "unknown message id"),
    ],
)
def test_one_field_decides(pair, variant: str, allow, kind: str):
    """A frame differing from a good one in one field (source system, component, a CRC byte,
    a payload byte, the message id) moves exactly its own counter, by one."""
    dec = FrameDecoder(allow)
    got = dec.decode_frame(pair[variant])
    assert dec.counts.as_dict() == {kind: 1}
    if kind == "frames decoded":
        assert got.get_type() == "GPS_INPUT" and got.lat == pair["lat"]
        assert (got.get_srcSystem(), got.get_srcComponent()) == (
            parse_header(pair[variant]).sysid,
            parse_header(pair[variant]).compid,
        )
    elif kind == "unknown message id":
        assert got is UNKNOWN
    elif kind == "rejected source (allowlist)":
        assert got is REJECTED  # intact: a scan steps over it whole
    else:
        assert got is None


def test_allowlist_is_on_the_pair_not_on_each_id():
    """Allowing (7, 42) and (9, 1) does not allow (7, 1) nor (9, 42): the pair decides."""
    frames = {src: common_frame(heartbeat(), src) for src in (A, B, (7, 1), (9, 42))}
    for src, fr in frames.items():
        dec = FrameDecoder({A, B})
        dec.decode_frame(fr)
        kind = "frames decoded" if src in (A, B) else "rejected source (allowlist)"
        assert dec.counts.as_dict() == {kind: 1}, src


def test_session_allowlist_counts_each_frame_of_a_datagram(pair):
    """The stream session's allowlist (what ``ngnav stream --allow`` sets), one datagram
    of four frames: two of the allowed source, one per single-id variant."""
    sess = make_session(allow={A})
    sess.feed_datagram(pair["base"] + pair["sysid"] + pair["compid"] + _next(pair))
    c = sess.counts.as_dict()
    assert c["frames decoded"] == 2
    assert c["rejected source (allowlist)"] == 2
    assert "bad crc" not in c and "truncated frame" not in c
    assert "sequence gap (frames lost)" not in c


def _next(pair) -> bytes:
    """The frame after ``pair["base"]`` from source A (seq 6), with no start byte inside."""
    for t in range(2_000_000, 2_100_000):
        fr = common_frame(gps_input(t, pair["lat"]), A, seq=6)
        if _clean(fr):
            return fr
    raise AssertionError("no clean frame")


def test_parse_allow():
    """``--allow SYSID:COMPID`` pairs; none given: every source."""
    assert parse_allow(["7:42"]) == {(7, 42)}
    assert parse_allow(["7:42", "9:1"]) == {(7, 42), (9, 1)}
    assert parse_allow([]) is None
    with pytest.raises(ValueError, match="SYSID:COMPID"):
        parse_allow(["7"])


def test_live_link_allowlist_and_idle_heartbeat(pair):
    """``serve`` over loopback UDP: the allowlist counts, and the idle HEARTBEAT on the
    output link carries the configured ids, STANDBY before any configuration."""
    p_in, p_out = free_udp_port(), free_udp_port()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", p_out))
    rx.settimeout(2.0)
    second = _next(pair)

    def ready() -> None:
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.sendto(pair["base"] + pair["compid"], ("127.0.0.1", p_in))
        tx.sendto(pair["sysid"] + second, ("127.0.0.1", p_in))
        tx.close()

    args = [Endpoint("udpin", "127.0.0.1", p_in), Endpoint("udpout", "127.0.0.1", p_out), _factory]
    settings = OutputSettings(system_id=9, component_id=200)
    try:
        st_ = serve(*args, settings, allow={A}, idle_exit_s=0.3, duration_s=10.0, ready=ready)
        hb = rx.recv(2048)
    finally:
        rx.close()
    assert st_.datagrams == 2
    assert st_.counts["frames decoded"] == 2
    assert st_.counts["rejected source (allowlist)"] == 2
    m = common.MAVLink(None).decode(bytearray(hb))
    assert m.get_type() == "HEARTBEAT"
    assert (m.get_srcSystem(), m.get_srcComponent(), m.system_status) == (9, 200, 3)


# ============================================================ CRC_EXTRA, versions, signing
def test_custom_frame_needs_its_own_crc_extra():
    """A hand-packed NGNAV_ARRAY_SAMPLE decodes with the CRC_EXTRA computed from ngnav.xml
    and fails with another message's."""
    values = {
        "time_usec": 1_000_000,
        "accel": [1.0] * 9 + [0.0] * 7,
        "valid": 0x1FF,
        "saturated": 0,
        "count": 9,
    }
    good = pack_custom("NGNAV_ARRAY_SAMPLE", values)
    wrong = pack_custom(
        "NGNAV_ARRAY_SAMPLE", values, crc_extra=DIALECT["NGNAV_ARRAY_BATCH"].crc_extra
    )
    assert good[:-2] == wrong[:-2] and good[-2:] != wrong[-2:]
    dec = FrameDecoder()
    assert dec.decode_frame(good).get_type() == "NGNAV_ARRAY_SAMPLE"
    assert dec.decode_frame(wrong) is None
    assert dec.counts.as_dict() == {"frames decoded": 1, "bad crc": 1}


def test_mavlink1_and_signed_frames_are_cut_at_their_own_length():
    """MAVLink 1 (0xFE, 8 bytes of overhead) and signed MAVLink 2 (13 more bytes) frames
    between plain ones: every frame decoded, nothing skipped."""
    raw = common.MAVLink_gps_raw_int_message(5, 3, 340_000_001, -1_065_000_002, 1_500_003, 1, 2,
                                             2000, 3000, 9)  # fmt: skip
    v1 = common_frame(raw, A, seq=0, v1=True)
    assert v1[0] == 0xFE and len(v1) == 6 + v1[1] + 2
    mav = common.MAVLink(None, srcSystem=A[0], srcComponent=A[1])
    mav.seq = 1
    mav.signing.secret_key = bytes(range(32))
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 3
    mav.signing.timestamp = 123_456
    signed = bytes(heartbeat().pack(mav))
    h = parse_header(signed)
    assert h.incompat & 1 and len(signed) == 10 + h.length + 2 + 13
    plain = common_frame(heartbeat(), A, seq=2)
    dec = FrameDecoder()
    msgs = dec.decode_buffer(v1 + signed + plain + v1)
    assert [m.get_type() for m in msgs] == ["GPS_RAW_INT", "HEARTBEAT", "HEARTBEAT", "GPS_RAW_INT"]
    assert (msgs[0].lat, msgs[0].lon, msgs[0].alt) == (340_000_001, -1_065_000_002, 1_500_003)
    # the second v1 frame repeats seq 0 after seq 2: 253 frames "lost" (the counter is mod 256)
    assert dec.counts.as_dict() == {"frames decoded": 4, "sequence gap (frames lost)": 253}
    bad = bytearray(v1)
    bad[-1] ^= 0x10
    dec = FrameDecoder()
    assert dec.decode_frame(bytes(bad)) is None and dec.counts.as_dict() == {"bad crc": 1}


def test_sequence_gaps_per_source():
    """Gaps count per source: A sends 0, 1, 2, 5 (2 lost) then 254, 255, 0, 1 across the wrap
    (248 lost before 254, none at the wrap); B's 200, 201 in between lose nothing; a
    rejected source's frames are not counted at all."""
    plan = [(A, 0), (A, 1), (B, 200), (A, 2), ((8, 8), 77), (B, 201), (A, 5), (A, 254),
            (A, 255), (A, 0), (A, 1)]  # fmt: skip
    buf = b"".join(common_frame(heartbeat(), src, seq) for src, seq in plan)
    dec = FrameDecoder({A, B})
    assert len(dec.decode_buffer(buf)) == 10
    c = dec.counts.as_dict()
    assert c["frames decoded"] == 10
    assert c["rejected source (allowlist)"] == 1
    assert c["sequence gap (frames lost)"] == 2 + 248


def test_truncated_datagram_keeps_the_frames_before():
    """A datagram whose last frame is cut: the whole frames decoded, one truncation."""
    f1, f2, f3 = (common_frame(heartbeat(), A, s) for s in range(3))
    for cut in (1, 2, 3, len(f3) - 1):
        dec = FrameDecoder()
        assert len(dec.decode_buffer(f1 + f2 + f3[:cut])) == 2
        assert dec.counts.as_dict() == {"frames decoded": 2, "truncated frame": 1}


def test_false_start_in_a_corrupt_frame_costs_only_that_frame():
    """frames.py: 'one bad frame costs exactly itself'. A corrupt frame whose payload holds
    0xFD followed by a large length byte must not hide the good frame after it."""
    bad = bytearray(common_frame(heartbeat(), A, 0))
    bad[10], bad[11] = 0xFD, 0xFF
    good = common_frame(heartbeat(), A, 1)
    dec = FrameDecoder()
    assert len(dec.decode_buffer(bytes(bad) + good)) == 1


def test_rejected_source_frame_costs_only_itself():
    """A ground station's HEARTBEAT (custom_mode 0xFFFD: payload FD FF ...) rejected by the
    allowlist must not hide the vehicle's frame that follows it in the datagram."""
    gcs = common_frame(common.MAVLink_heartbeat_message(6, 8, 0, 0xFFFD, 4, 3), (255, 190))
    ours = common_frame(heartbeat(), A)
    dec = FrameDecoder({A})
    assert len(dec.decode_buffer(gcs + ours)) == 1
    assert dec.counts.as_dict() == {"rejected source (allowlist)": 1, "frames decoded": 1}


# ============================================================ corrupt streams by construction


def _make(kind: int, src: tuple[int, int], seq: int, tweak: int) -> bytes:
    if kind == 0:
        return common_frame(gps_input(1_000_000 + tweak, 340_000_000 + tweak), src, seq)
    if kind == 1:
        return common_frame(common.MAVLink_heartbeat_message(2, 12, 0, tweak, 4, 3), src, seq)
    if kind == 2:
        att = common.MAVLink_attitude_message(tweak, 0.1, -0.2, 1.5, 0.01, 0.02, 0.03)
        return common_frame(att, src, seq)
    values = {
        "time_usec": 2_000_000 + tweak,
        "accel": [1.0 + 0.5 * i for i in range(9)] + [0.0] * 7,
        "valid": 0x1FF,
        "saturated": 0,
        "count": 9,
    }
    return pack_custom("NGNAV_ARRAY_SAMPLE", values, sysid=src[0], compid=src[1], seq=seq)


def _pool(n: int) -> list[tuple[bytes, tuple[int, int], int]]:
    """``n`` intact frames, two sources with their own running sequence, no start byte
    after each frame's first (so a corrupt frame cannot hide a false start)."""
    seqs = {A: 0, B: 0}
    out = []
    for k in range(n):
        src = B if k % 3 == 2 else A
        seq = seqs[src]
        seqs[src] += 1
        for tweak in range(k, k + 10_000_000, 1009):
            fr = _make(k % 4, src, seq, tweak)
            if _clean(fr):
                break
        else:
            raise AssertionError("no clean frame")
        out.append((fr, src, seq))
    return out


POOL = _pool(16)
OPS = ("keep", "payload", "crc", "unknown", "drop")


@st.composite
def plans(draw):
    """What happens to each pool frame, garbage before each, and an optional cut tail."""
    ops = draw(st.lists(st.sampled_from(OPS), min_size=len(POOL), max_size=len(POOL)))
    corrupt = []
    for (fr, _, _), op in zip(POOL, ops, strict=True):
        if op == "payload":
            pos = draw(st.integers(10, len(fr) - 3))
        elif op == "crc":
            pos = draw(st.integers(len(fr) - 2, len(fr) - 1))
        else:
            corrupt.append(None)
            continue
        val = draw(st.sampled_from([b for b in CLEAN if b != fr[pos]]))
        corrupt.append((pos, val))
    garbage = draw(
        st.lists(
            st.lists(st.sampled_from(CLEAN), max_size=12),
            min_size=len(POOL) + 1,
            max_size=len(POOL) + 1,
        )
    )
    cut = draw(st.one_of(st.none(), st.integers(1, 40)))
    return ops, corrupt, [bytes(g) for g in garbage], cut


def _apply(op: str, fr: bytes, corrupt) -> bytes:
    b = bytearray(fr)
    if op in ("payload", "crc"):
        b[corrupt[0]] = corrupt[1]
    elif op == "unknown":
        b[7:10] = UNKNOWN_ID.to_bytes(3, "little")
    return bytes(b)


def _expected_gaps(ops: list[str]) -> int:
    last: dict[tuple[int, int], int] = {}
    gaps = 0
    for (_, src, seq), op in zip(POOL, ops, strict=True):
        if op == "keep":
            if src in last:
                gaps += seq - last[src] - 1
            last[src] = seq
    return gaps


def _expected(ops, garbage, cut, per_corrupt: int, per_frame_overhead: int) -> dict[str, int]:
    n_bad = sum(op in ("payload", "crc") for op in ops)
    skipped = sum(len(g) for g in garbage) + sum(
        len(fr) + per_frame_overhead - per_corrupt
        for (fr, _, _), op in zip(POOL, ops, strict=True)
        if op in ("payload", "crc")
    )
    exp = {
        "frames decoded": ops.count("keep"),
        "bad crc": n_bad,
        "unknown message id": ops.count("unknown"),
        "bytes skipped (no frame start)": skipped,
        "truncated frame": int(cut is not None),
        "sequence gap (frames lost)": _expected_gaps(ops),
    }
    return {k: v for k, v in exp.items() if v}


def _check_datagram(ops, corrupt, garbage, cut) -> None:
    parts = []
    for (fr, _, _), op, cor, g in zip(POOL, ops, corrupt, garbage, strict=False):
        parts.append(g)
        if op != "drop":
            parts.append(_apply(op, fr, cor))
    parts.append(garbage[-1])
    tail = POOL[0][0]
    if cut is not None:
        parts.append(tail[: min(cut, len(tail) - 1)])
    dec = FrameDecoder()
    msgs = dec.decode_buffer(b"".join(parts))
    kept = [fr for (fr, _, _), op in zip(POOL, ops, strict=True) if op == "keep"]
    assert [bytes(m.get_msgbuf()) for m in msgs] == kept
    # a corrupt frame costs its first byte as the failed start, the rest as skipped bytes
    assert dec.counts.as_dict() == _expected(ops, garbage, cut, 1, 0)


@settings(max_examples=150, deadline=None)
@given(plans())
def test_corrupt_datagram_counts_are_known_by_construction(plan):
    """One datagram of the pool with frames corrupted (payload or CRC byte), renamed to an
    unknown id, dropped, garbage between them and maybe a cut tail: the messages returned
    are exactly the intact frames, and every counter equals what was put in."""
    _check_datagram(*plan)


def test_corrupt_datagram_one_of_each():
    """The same check on a fixed plan with every kind of damage at least once."""
    ops = ["keep", "payload", "keep", "crc", "unknown", "drop", "keep", "keep"] * 2
    corrupt = []
    for (fr, _, _), op in zip(POOL, ops, strict=True):
        pos = 12 if op == "payload" else len(fr) - 1 if op == "crc" else None
        corrupt.append(None if pos is None else (pos, 0x00 if fr[pos] else 0x01))
    garbage = [b"\x00\x01\x02" if k % 4 == 1 else b"" for k in range(len(POOL) + 1)]
    _check_datagram(ops, corrupt, garbage, 7)


def _ts_pool() -> list[int]:
    """Record times (tlog us) whose eight bytes hold no start byte."""
    out, t = [], EPOCH_2026_US + 1_000_000
    while len(out) < len(POOL):
        if all(b in CLEAN for b in t.to_bytes(8, "big")):
            out.append(t)
        t += 10_007
    return out


TS = _ts_pool()


@pytest.fixture(scope="module")
def tlog_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("damaged")


@settings(max_examples=80, deadline=None)
@given(plan=plans())
def test_corrupt_tlog_counts_are_known_by_construction(tlog_dir, plan):
    """A tlog of the pool with the same damage (garbage before the records present): the
    records read are exactly the intact ones with their timestamps; a corrupt record is
    skipped whole (timestamp and frame); a record cut after its first frame bytes is one
    truncation."""
    ops, corrupt, garbage, cut = plan
    # no garbage in place of a dropped record nor after the last record: a tail shorter
    # than a timestamp reads as a truncated record, which test_tlog_cut_* pins
    garbage = [g if op != "drop" else b"" for g, op in zip(garbage, ops, strict=False)] + [b""]
    parts = []
    for (fr, _, _), op, cor, g, ts in zip(POOL, ops, corrupt, garbage, TS, strict=False):
        parts.append(g)
        if op != "drop":
            parts.append(ts.to_bytes(8, "big") + _apply(op, fr, cor))
    if cut is not None:
        rec = TS[-1].to_bytes(8, "big") + POOL[1][0]
        parts.append(rec[: min(11 + cut, len(rec) - 1)])
    path = tlog_dir / "damaged.tlog"
    path.write_bytes(b"".join(parts))
    dec = FrameDecoder()
    got = list(read_tlog(path, dec))
    kept = [(ts, fr) for (fr, _, _), op, ts in zip(POOL, ops, TS, strict=True) if op == "keep"]
    assert [(ts, bytes(m.get_msgbuf())) for ts, m in got] == kept
    assert dec.counts.as_dict() == _expected(ops, garbage, cut, 0, 8)


def test_tlog_cut_inside_the_last_timestamp(tmp_path):
    """A tlog whose last record is cut inside its 8-byte timestamp: one truncation, the
    records before it all read."""
    recs = [ts.to_bytes(8, "big") + fr for ts, (fr, _, _) in zip(TS[:3], POOL, strict=False)]
    for n in range(1, 9):
        path = tmp_path / f"cut{n}.tlog"
        path.write_bytes(b"".join(recs) + TS[3].to_bytes(8, "big")[:n])
        dec = FrameDecoder()
        assert [ts for ts, _ in read_tlog(path, dec)] == TS[:3]
        assert dec.counts.as_dict() == {"frames decoded": 3, "truncated frame": 1}


def test_pool_is_what_the_fuzz_assumes():
    """The pool's frames are intact (the reference CRC), from both sources with running
    sequences, with no start byte inside, and the record times likewise."""
    assert all(_clean(fr) for fr, _, _ in POOL)
    for fr, src, seq in POOL:
        h = parse_header(fr)
        assert (h.sysid, h.compid, h.seq) == (*src, seq)
    assert TS == sorted(set(TS)) and TS[-1] - TS[0] < 86_400 * 10**6
    dec = FrameDecoder()
    assert len(dec.decode_buffer(b"".join(fr for fr, _, _ in POOL))) == len(POOL)
    assert dec.counts.as_dict() == {"frames decoded": len(POOL)}


@pytest.mark.parametrize("extra", [1, 2])
def test_tlog_cut_just_after_the_last_timestamp(tmp_path, extra: int):
    """read_tlog: 'a truncated last record is counted as truncated frame'."""
    recs = [ts.to_bytes(8, "big") + fr for ts, (fr, _, _) in zip(TS[:3], POOL, strict=False)]
    path = tmp_path / "cut.tlog"
    path.write_bytes(b"".join(recs) + (TS[3].to_bytes(8, "big") + POOL[3][0])[: 8 + extra])
    dec = FrameDecoder()
    assert len(list(read_tlog(path, dec))) == 3
    assert dec.counts.as_dict() == {"frames decoded": 3, "truncated frame": 1}
