"""Telemetry logs (``.tlog``): each frame preceded by its 8-byte timestamp.

The format Mission Planner, QGroundControl and pymavlink's ``mavlogdump.py``
read: a big-endian ``uint64`` of microseconds since the UNIX epoch, then one
raw MAVLink frame, repeated. ngnav writes run-clock times offset by
:data:`EPOCH_BASE_US` (so tools show a date) and reads any tlog.

Reading is robust: a corrupt frame, garbage between frames or a truncated
end is counted and skipped (see :class:`telemetry.frames.FrameDecoder`), the
frames around it are kept.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from pathlib import Path

from telemetry import ngnav_mavlink as mavlink
from telemetry.frames import MAGIC_V1, MAGIC_V2, FrameDecoder, frame_length

#: Run clock zero in a written tlog: 2026-01-01T00:00:00Z, in microseconds.
EPOCH_BASE_US = 1_767_225_600_000_000
_TS = struct.Struct(">Q")
#: Largest plausible step between two tlog timestamps when resyncing (one day).
_MAX_STEP_US = 86_400 * 1_000_000


class FrameWriter:
    """Pack messages as MAVLink 2 frames with one sender's ids and a running sequence."""

    def __init__(self, system_id: int = 1, component_id: int = 1) -> None:
        if not (1 <= system_id <= 255 and 0 <= component_id <= 255):
            raise ValueError(f"bad MAVLink ids: system {system_id}, component {component_id}")
        self._mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)

    def pack(self, msg: mavlink.MAVLink_message) -> bytes:
        """The frame of ``msg``; the sequence number advances by one."""
        buf = msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        return bytes(buf)


def tlog_record(t_us: int, frame: bytes) -> bytes:
    """One tlog record: the run-clock time on :data:`EPOCH_BASE_US`, then the frame."""
    return _TS.pack(EPOCH_BASE_US + int(t_us)) + frame


def frames_of(
    messages: Iterable[tuple[int, mavlink.MAVLink_message]], writer: FrameWriter | None = None
) -> Iterator[tuple[int, bytes]]:
    """Pack ``(run-clock time_usec, message)`` pairs into ``(time_usec, frame)`` pairs."""
    w = writer or FrameWriter()
    for t_us, msg in messages:
        yield int(t_us), w.pack(msg)


def write_tlog(
    path: str | Path,
    messages: Iterable[tuple[int, mavlink.MAVLink_message]],
    writer: FrameWriter | None = None,
) -> int:
    """Write ``(run-clock time_usec, message)`` pairs as a tlog; returns the frame count."""
    n = 0
    with Path(path).open("wb") as fh:
        for t_us, frame in frames_of(messages, writer):
            fh.write(tlog_record(t_us, frame))
            n += 1
    return n


def read_tlog(
    path: str | Path, decoder: FrameDecoder | None = None
) -> Iterator[tuple[int, mavlink.MAVLink_message]]:
    """Yield ``(tlog timestamp in us, message)`` for every intact frame of a tlog.

    Bad frames and bytes are counted in ``decoder.counts``; a truncated last
    record is counted as ``"truncated frame"``.
    """
    dec = decoder or FrameDecoder()
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such file")
    buf = p.read_bytes()
    n = len(buf)
    i = 0
    last_ts: int | None = None
    while i < n:
        if i + 8 >= n:
            dec.counts.add("truncated frame")
            break
        ts = _TS.unpack_from(buf, i)[0]
        j = i + 8
        ln = frame_length(buf, j)
        plausible = buf[j] in (MAGIC_V1, MAGIC_V2) and (
            last_ts is None or abs(ts - last_ts) <= _MAX_STEP_US
        )
        if not plausible:
            k = _resync(buf, i + 1, last_ts)
            dec.counts.add("bytes skipped (no frame start)", k - i)
            i = k
            continue
        if ln is None or j + ln > n:
            dec.counts.add("truncated frame")
            break
        msg = dec.decode_frame(buf[j : j + ln])
        if msg is None:
            k = _resync(buf, i + 1, last_ts)
            dec.counts.add("bytes skipped (no frame start)", k - i)
            i = k
            continue
        last_ts = ts
        i = j + ln
        if isinstance(msg, mavlink.MAVLink_message):
            yield ts, msg


def _resync(buf: bytes, i: int, last_ts: int | None) -> int:
    """Next offset where a plausible timestamp is followed by a frame start."""
    n = len(buf)
    while i + 9 <= n:
        j = min(
            (x for x in (buf.find(b"\xfd", i + 8), buf.find(b"\xfe", i + 8)) if x >= 0),
            default=-1,
        )
        if j < 0:
            return n
        start = j - 8
        ts = _TS.unpack_from(buf, start)[0]
        if last_ts is None or abs(ts - last_ts) <= _MAX_STEP_US:
            return start
        i = start + 1
    return n
