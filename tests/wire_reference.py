"""Independent references for the wire tests: a MAVLink 2 codec and the maths, written here.

Nothing in this module imports ngnav's code. The codec reads the ngnav dialect's
XML (``telemetry/dialects/ngnav.xml``, the definition the generated module comes
from) and applies the MAVLink 2 rules by hand: fields on the wire sorted by
type size (stable), trailing zero bytes of the payload trimmed, CRC-16/MCRF4XX
over header and payload and the message's CRC_EXTRA (itself a CRC of the
message's name and fields). The geodesy (WGS-84 through ECEF) and the rotations
(Hamilton quaternion, scalar first, body to NED; ZYX Euler angles) are the
textbook formulas, so a test comparing ngnav with them does not compare ngnav
with itself.
"""

from __future__ import annotations

import math
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The ngnav dialect's definition.
DIALECT_XML = Path(__file__).resolve().parents[1] / "telemetry" / "dialects" / "ngnav.xml"
#: Run clock zero of ngnav's tlogs: 2026-01-01T00:00:00Z in microseconds (date -d @1767225600).
EPOCH_2026_US = 1_767_225_600 * 1_000_000

# MAVLink base type -> (struct code, size in bytes)
_BASE = {
    "uint8_t": ("B", 1),
    "int8_t": ("b", 1),
    "uint16_t": ("H", 2),
    "int16_t": ("h", 2),
    "uint32_t": ("I", 4),
    "int32_t": ("i", 4),
    "float": ("f", 4),
    "uint64_t": ("Q", 8),
    "int64_t": ("q", 8),
    "double": ("d", 8),
}


def x25(data: bytes, crc: int = 0xFFFF) -> int:
    """MAVLink's checksum (CRC-16/MCRF4XX, the X.25 accumulate) of ``data``."""
    for b in data:
        t = (b ^ crc) & 0xFF
        t = (t ^ (t << 4)) & 0xFF
        crc = ((crc >> 8) ^ (t << 8) ^ (t << 3) ^ (t >> 4)) & 0xFFFF
    return crc


@dataclass(frozen=True)
class XmlMessage:
    """One message of the dialect XML, in wire order."""

    msg_id: int
    name: str
    #: (field name, base type, array length or 0 for a scalar), in wire order
    wire: tuple[tuple[str, str, int], ...]
    crc_extra: int

    @property
    def fmt(self) -> struct.Struct:
        return struct.Struct(
            "<" + "".join(f"{n}{_BASE[t][0]}" if n else _BASE[t][0] for _, t, n in self.wire)
        )


def read_dialect(path: Path = DIALECT_XML) -> dict[str, XmlMessage]:
    """The messages of a dialect XML (its own ``<message>`` elements, not the includes)."""
    out: dict[str, XmlMessage] = {}
    for m in ET.parse(path).getroot().iter("message"):
        if m.find("extensions") is not None:
            raise NotImplementedError("extension fields are not in the ngnav dialect")
        fields = []
        for f in m.findall("field"):
            base, _, n = f.get("type").partition("[")
            fields.append((f.get("name"), base, int(n.rstrip("]")) if n else 0))
        # MAVLink 2 wire order: largest base type first, XML order within a size
        wire = tuple(sorted(fields, key=lambda x: -_BASE[x[1]][1]))
        crc = x25(f"{m.get('name')} ".encode())
        for name, base, n in wire:
            crc = x25(f"{base} {name} ".encode(), crc)
            if n:
                crc = x25(bytes([n]), crc)
        out[m.get("name")] = XmlMessage(
            int(m.get("id")), m.get("name"), wire, (crc & 0xFF) ^ (crc >> 8)
        )
    return out


DIALECT = read_dialect()
BY_ID = {m.msg_id: m for m in DIALECT.values()}


def frame_crc(frame_wo_crc: bytes, crc_extra: int) -> bytes:
    """The two CRC bytes of a MAVLink 2 frame (everything after the magic, then CRC_EXTRA)."""
    return x25(bytes([crc_extra]), x25(frame_wo_crc[1:])).to_bytes(2, "little")


def pack_v2(
    msg_id: int, payload: bytes, crc_extra: int, sysid: int, compid: int, seq: int
) -> bytes:
    """A MAVLink 2 frame of ``payload`` (trailing zeros trimmed, at least one byte kept)."""
    payload = payload.rstrip(b"\0") or b"\0"
    head = bytes([0xFD, len(payload), 0, 0, seq, sysid, compid]) + msg_id.to_bytes(3, "little")
    body = head + payload
    return body + frame_crc(body, crc_extra)


def pack_custom(
    name: str,
    values: dict,
    *,
    sysid: int = 7,
    compid: int = 42,
    seq: int = 0,
    crc_extra: int | None = None,
) -> bytes:
    """A frame of an ngnav-dialect message from field values (arrays at full length)."""
    d = DIALECT[name]
    flat: list = []
    for fname, _, n in d.wire:
        v = values[fname]
        if n:
            if len(v) != n:
                raise ValueError(f"{name}.{fname} needs {n} values, got {len(v)}")
            flat.extend(v)
        else:
            flat.append(v)
    extra = d.crc_extra if crc_extra is None else crc_extra
    return pack_v2(d.msg_id, d.fmt.pack(*flat), extra, sysid, compid, seq)


@dataclass(frozen=True)
class Header:
    """A MAVLink 2 frame's header fields."""

    length: int
    incompat: int
    compat: int
    seq: int
    sysid: int
    compid: int
    msg_id: int


def parse_header(frame: bytes) -> Header:
    """Header of a MAVLink 2 frame (checks the magic and the total length)."""
    assert frame[0] == 0xFD, f"not a MAVLink 2 frame: {frame[:1].hex()}"
    ln = frame[1]
    sig = 13 if frame[2] & 1 else 0
    assert len(frame) == 10 + ln + 2 + sig, "frame length does not match its header"
    return Header(
        ln, frame[2], frame[3], frame[4], frame[5], frame[6], int.from_bytes(frame[7:10], "little")
    )


def unpack_custom(frame: bytes) -> tuple[Header, str, dict]:
    """Header, message name and field values of an ngnav-dialect frame (CRC checked here)."""
    h = parse_header(frame)
    d = BY_ID[h.msg_id]
    body = frame[: 10 + h.length]
    assert frame[10 + h.length : 12 + h.length] == frame_crc(body, d.crc_extra), "bad CRC"
    payload = frame[10 : 10 + h.length]
    assert len(payload) <= d.fmt.size
    raw = d.fmt.unpack(payload + bytes(d.fmt.size - len(payload)))
    values: dict = {}
    k = 0
    for fname, _, n in d.wire:
        if n:
            values[fname] = list(raw[k : k + n])
            k += n
        else:
            values[fname] = raw[k]
            k += 1
    return h, d.name, values


def f32(x: float) -> float:
    """``x`` as it comes back from a MAVLink float field."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


# ----------------------------------------------------------------- geodesy
_A = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def _ecef(lat_deg: float, lon_deg: float, h: float) -> np.ndarray:
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    n = _A / math.sqrt(1.0 - _E2 * math.sin(la) ** 2)
    return np.array(
        [
            (n + h) * math.cos(la) * math.cos(lo),
            (n + h) * math.cos(la) * math.sin(lo),
            (n * (1.0 - _E2) + h) * math.sin(la),
        ]
    )


def ned_to_geodetic(
    ned: np.ndarray, lat0_deg: float, lon0_deg: float, h0: float
) -> tuple[float, float, float]:
    """WGS-84 latitude, longitude (deg) and ellipsoidal height (m) of a NED point."""
    la, lo = math.radians(lat0_deg), math.radians(lon0_deg)
    north = np.array([-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)])
    east = np.array([-math.sin(lo), math.cos(lo), 0.0])
    down = np.array([-math.cos(la) * math.cos(lo), -math.cos(la) * math.sin(lo), -math.sin(la)])
    x, y, z = _ecef(lat0_deg, lon0_deg, h0) + ned[0] * north + ned[1] * east + ned[2] * down
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1.0 - _E2))
    h = 0.0
    for _ in range(20):
        n = _A / math.sqrt(1.0 - _E2 * math.sin(lat) ** 2)
        h = p / math.cos(lat) - n
        lat = math.atan2(z, p * (1.0 - _E2 * n / (n + h)))
    return math.degrees(lat), math.degrees(math.atan2(y, x)), h


def radii(lat_deg: float) -> tuple[float, float]:
    """Meridian (M) and prime-vertical (N) radii of curvature at a latitude, m."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    n = _A / math.sqrt(1.0 - _E2 * s2)
    return _A * (1.0 - _E2) / (1.0 - _E2 * s2) ** 1.5, n


# --------------------------------------------------------------- rotations
def dcm(q: np.ndarray) -> np.ndarray:
    """Body-to-NED rotation matrix of a Hamilton quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in np.asarray(q) / np.linalg.norm(q))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def euler(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (rad, ZYX) of a body-to-NED quaternion, from its matrix."""
    c = dcm(q)
    return np.array(
        [
            math.atan2(c[2, 1], c[2, 2]),
            math.asin(max(-1.0, min(1.0, -c[2, 0]))),
            math.atan2(c[1, 0], c[0, 0]),
        ]
    )


def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def _rotvec_quat(v: np.ndarray) -> np.ndarray:
    a = float(np.linalg.norm(v))
    if a == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(a / 2)], math.sin(a / 2) * v / a])


def odometry_jacobians(q: np.ndarray, vel_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Numerical Jacobians (6, 12) of ODOMETRY's pose and twist on the error state.

    Error state ``[dp, dv, dtheta, dw]`` with ``q_true = exp(dtheta) q``: the pose is
    ``(p, roll, pitch, yaw)``, the twist ``(C^T v, w)``. Central differences, so
    nothing of ngnav's analytic map is reused.
    """
    h = 1e-6
    jp = np.zeros((6, 12))
    jt = np.zeros((6, 12))
    jp[0:3, 0:3] = np.eye(3)
    jt[3:6, 9:12] = np.eye(3)
    jt[0:3, 3:6] = dcm(q).T
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        qp, qm = _qmul(_rotvec_quat(d), q), _qmul(_rotvec_quat(-d), q)
        de = euler(qp) - euler(qm)
        jp[3:6, 6 + k] = ((de + math.pi) % (2 * math.pi) - math.pi) / (2 * h)
        jt[0:3, 6 + k] = (dcm(qp).T @ vel_ned - dcm(qm).T @ vel_ned) / (2 * h)
    return jp, jt


def upper(m: np.ndarray) -> list[float]:
    """Row-major upper triangle of a 6x6 matrix (MAVLink's covariance layout)."""
    return [float(m[i, j]) for i in range(6) for j in range(i, 6)]
