"""Robust MAVLink frame decoding: one frame at a time, every failure counted.

pymavlink's stream parser keeps one buffer across calls; after a corrupt
datagram it can lose the good frames that follow. Here every candidate frame
is cut out by its own header (MAVLink 1 ``0xFE`` or MAVLink 2 ``0xFD``) and
decoded alone, so one bad frame costs exactly itself. The same code serves
tlogs (frames after 8-byte timestamps) and UDP (frames inside a datagram).

Counters (``FrameCounts``) name what went wrong; nothing raises on bad bytes.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from telemetry import ngnav_mavlink as mavlink

#: Start-of-frame bytes.
MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
_SIGNED = 0x01  # MAVLink 2 incompat flag: 13-byte signature follows the CRC


def frame_length(buf: bytes | bytearray | memoryview, i: int) -> int | None:
    """Total length of the frame starting at ``buf[i]`` (header, payload, CRC, signature).

    None when ``buf[i]`` is not a start byte or the header is incomplete.
    """
    n = len(buf)
    if i >= n:
        return None
    magic = buf[i]
    if magic == MAGIC_V2:
        if i + 3 > n:
            return None
        sig = 13 if buf[i + 2] & _SIGNED else 0
        return 10 + buf[i + 1] + 2 + sig
    if magic == MAGIC_V1:
        if i + 2 > n:
            return None
        return 6 + buf[i + 1] + 2
    return None


@dataclass
class FrameCounts:
    """What the decoder saw, by kind (see :data:`KINDS`)."""

    counts: Counter = field(default_factory=Counter)

    def add(self, kind: str, n: int = 1) -> None:
        if n:
            self.counts[kind] += n

    def as_dict(self) -> dict[str, int]:
        return dict(sorted(self.counts.items()))


#: Returned by :meth:`FrameDecoder.decode_frame` for a frame of an unknown id.
UNKNOWN = object()
#: Returned by :meth:`FrameDecoder.decode_frame` for an intact frame of a source outside
#: the allowlist: its length can be trusted, so a scan steps over it whole.
REJECTED = object()

#: Counter names of the frame layer.
KINDS = (
    "frames decoded",
    "bad crc",
    "unknown message id",
    "truncated frame",
    "bytes skipped (no frame start)",
    "rejected source (allowlist)",
    "sequence gap (frames lost)",
)


class FrameDecoder:
    """Decode frames one by one with a private pymavlink parser.

    Parameters
    ----------
    allow : set of (system id, component id), optional
        Sources whose frames are accepted; others are counted and dropped.
        None accepts every source.
    """

    def __init__(self, allow: set[tuple[int, int]] | None = None) -> None:
        self._mav = mavlink.MAVLink(None)
        self._mav.robust_parsing = True
        # a second parser for look-ahead checks, so that they leave no trace
        self._probe = mavlink.MAVLink(None)
        self._probe.robust_parsing = True
        self.allow = allow
        self.counts = FrameCounts()
        self._last_seq: dict[tuple[int, int], int] = {}

    def decode_frame(self, frame: bytes | bytearray) -> mavlink.MAVLink_message | object | None:
        """Decode one complete frame; None (counted) if it is not intact.

        A well-formed frame of an id outside the dialect returns :data:`UNKNOWN`
        (counted): its length can be trusted, its content cannot. An intact frame of
        a source outside the allowlist returns :data:`REJECTED` (counted).
        """
        try:
            msg = self._mav.decode(bytearray(frame))
        except Exception:
            # CRC mismatch, bad length, bad signature: the frame is not intact
            self.counts.add("bad crc")
            return None
        if isinstance(msg, mavlink.MAVLink_unknown):
            # no CRC_EXTRA for an id outside the dialect: it cannot be checked
            self.counts.add("unknown message id")
            return UNKNOWN
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.allow is not None and src not in self.allow:
            self.counts.add("rejected source (allowlist)")
            return REJECTED
        seq = msg.get_seq()
        last = self._last_seq.get(src)
        if last is not None:
            gap = (seq - last - 1) % 256
            self.counts.add("sequence gap (frames lost)", gap)
        self._last_seq[src] = seq
        self.counts.add("frames decoded")
        return msg

    def decode_buffer(self, buf: bytes | bytearray) -> list[mavlink.MAVLink_message]:
        """Decode every frame in ``buf`` (one UDP datagram, say), resyncing on bad bytes.

        A frame that fails its CRC costs one byte of resync: the scan restarts at
        the next start byte, so a good frame inside a corrupt region is still found.
        A start byte whose header promises more bytes than ``buf`` holds is a false
        start when an intact frame follows it (its bytes are counted as skipped) and
        the datagram's truncated last frame otherwise. An intact frame, decoded,
        unknown or rejected by the allowlist, is stepped over whole.
        """
        out: list[mavlink.MAVLink_message] = []
        i, n = 0, len(buf)
        while i < n:
            if buf[i] not in (MAGIC_V1, MAGIC_V2):
                j = _next_start(buf, i + 1)
                self.counts.add("bytes skipped (no frame start)", j - i)
                i = j
                continue
            ln = frame_length(buf, i)
            if ln is None or i + ln > n:
                j = self._next_intact(buf, i + 1)
                if j is None:
                    self.counts.add("truncated frame")
                    break
                self.counts.add("bytes skipped (no frame start)", j - i)
                i = j
                continue
            msg = self.decode_frame(buf[i : i + ln])
            if msg is None:
                i += 1
                continue
            if msg is not UNKNOWN and msg is not REJECTED:
                out.append(msg)
            i += ln
        return out

    def _next_intact(self, buf: bytes | bytearray, i: int) -> int | None:
        """Offset of the first intact frame at or after ``i`` (nothing counted), or None."""
        n = len(buf)
        j = _next_start(buf, i)
        while j < n:
            ln = frame_length(buf, j)
            if ln is not None and j + ln <= n:
                try:
                    self._probe.decode(bytearray(buf[j : j + ln]))
                    return j
                except Exception:
                    pass
            j = _next_start(buf, j + 1)
        return None


def _next_start(buf: bytes | bytearray, i: int) -> int:
    a = buf.find(bytes([MAGIC_V2]), i)
    b = buf.find(bytes([MAGIC_V1]), i)
    c = [x for x in (a, b) if x >= 0]
    return min(c) if c else len(buf)
