"""The filter's inputs as MAVLink: array samples, GPS fixes and the run configuration.

Encoding (``input_frames``) turns a run (``ArraySamples``, ``GpsFixes``,
``RunConfig``) into time-ordered frames; decoding (``InputAssembler``) turns
decoded messages back into the same records, counting everything it drops.

Fields used
-----------
- ``NGNAV_ARRAY_BATCH`` / ``NGNAV_ARRAY_SAMPLE``: ``time_usec`` (sample time,
  run clock), ``accel`` (m/s^2, float32), ``valid`` (bit clear: the channel
  becomes NaN, a held sample), ``count`` (must equal the layout's channels).
  ``saturated`` is informative: the filter detects saturation from
  ``range_mps2`` itself.
- ``GPS_INPUT``: ``time_usec`` (time of validity, run clock), ``fix_type``
  (< 3 is skipped and counted), ``lat``/``lon`` (degE7), ``alt`` (m; ngnav
  carries the WGS-84 *ellipsoidal* height here, as in ``gps.csv``), ``vn``,
  ``ve``, ``vd`` (m/s), ``horiz_accuracy``, ``vert_accuracy``,
  ``speed_accuracy`` (1-sigma, m and m/s). Accuracies flagged in
  ``ignore_flags`` fall back to the configured ones; an altitude or velocity flagged
  ignored is left out (NaN) and the filter fuses the rest.
- ``GPS_RAW_INT`` and ``HIL_GPS``: position, ``vel``/``cog`` or ``vn``/``ve``/``vd``;
  accuracies they lack come from :class:`GpsDefaults`. GPS_RAW_INT has no vertical
  velocity (left out), and no velocity at all when ``vel`` or ``cog`` is unknown.
- ``NGNAV_CONFIG_TEXT``: the run's ``config.toml`` in chunks (CRC-32 checked).

Times: ``time_usec`` is microseconds on the run clock (``t_s * 1e6``,
rounded to the microsecond).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from ngnav.records import FIX_RANGE_KINDS, ArraySamples, GpsFixes, fix_range_problems
from ngnav.runconfig import RunConfig, read_run_config_text, run_config_text
from telemetry import ngnav_mavlink as mavlink
from telemetry.frames import FrameCounts

#: Samples per NGNAV_ARRAY_BATCH frame and its float capacity.
BATCH_MAX_SAMPLES = 6
BATCH_FLOATS = 54
#: Channels an NGNAV_ARRAY_SAMPLE can hold.
SAMPLE_MAX_CHANNELS = 16
#: Bytes of config text per NGNAV_CONFIG_TEXT chunk.
CONFIG_CHUNK = 200
#: A fix used without a field its source did not give: counted per field (row index).
_ABSENT_KINDS = {
    2: "gps without altitude (the rest used)",
    3: "gps without horizontal velocity (the rest used)",
    5: "gps without vertical velocity (the rest used)",
}

#: GPS_INPUT ignore flags for the fields ngnav does not send (HDOP, VDOP).
_IGNORE_DOP = mavlink.GPS_INPUT_IGNORE_FLAG_HDOP | mavlink.GPS_INPUT_IGNORE_FLAG_VDOP


_BITS = np.arange(SAMPLE_MAX_CHANNELS)


def to_usec(t_s: float | np.ndarray) -> np.ndarray:
    """Run-clock seconds to integer microseconds (rounded)."""
    return np.rint(np.asarray(t_s, dtype=float) * 1e6).astype(np.int64)


@dataclass(frozen=True)
class GpsDefaults:
    """Accuracies (1-sigma) used when a GPS message does not carry them."""

    h_acc_m: float = 2.5
    v_acc_m: float = 5.0
    vel_acc_mps: float = 0.3


def batch_messages(
    samples: ArraySamples, saturated_mps2: float, batch: int = BATCH_MAX_SAMPLES
) -> Iterator[tuple[int, mavlink.MAVLink_message]]:
    """NGNAV_ARRAY_BATCH frames for ``samples`` (``batch`` samples each, the last shorter).

    Yields ``(time_usec of the batch's last sample, message)``: a batch can be
    sent once its last sample exists.
    """
    n = samples.n_channels
    if not 1 <= n <= 16:
        raise ValueError(f"a MAVLink array sample holds 1-16 channels, the run has {n}")
    per = max(1, min(batch, BATCH_MAX_SAMPLES, BATCH_FLOATS // n))
    t_us = to_usec(samples.t_s)
    a = samples.accel_mps2
    finite = np.isfinite(a)
    bits = 1 << np.arange(n)
    valid = (finite * bits).sum(axis=1)
    with np.errstate(invalid="ignore"):
        sat = ((finite & (np.abs(a) >= saturated_mps2)) * bits).sum(axis=1)
    vals = np.where(finite, a, 0.0)
    dt_us = int(np.median(np.diff(t_us))) if t_us.shape[0] > 1 else 0
    for k in range(0, t_us.shape[0], per):
        sl = slice(k, min(k + per, t_us.shape[0]))
        m = sl.stop - sl.start
        acc = np.zeros(BATCH_FLOATS)
        acc[: m * n] = vals[sl].ravel()
        v = [0] * BATCH_MAX_SAMPLES
        s = [0] * BATCH_MAX_SAMPLES
        v[:m] = valid[sl].tolist()
        s[:m] = sat[sl].tolist()
        msg = mavlink.MAVLink_ngnav_array_batch_message(
            int(t_us[sl.start]), acc.tolist(), dt_us, v, s, n, m
        )
        yield int(t_us[sl.stop - 1]), msg


def gps_input_message(fixes: GpsFixes, m: int) -> tuple[int, mavlink.MAVLink_message]:
    """GPS_INPUT for fix ``m``; returns ``(arrival time_usec, message)``."""
    t_us = int(to_usec(fixes.t_s[m]))
    arrival = int(to_usec(fixes.t_s[m] + fixes.latency_s[m]))
    v = fixes.vel_ned_mps[m]
    alt = float(fixes.alt_m[m])
    flags = _IGNORE_DOP
    # a field the fix lacks (NaN) goes as 0 with its ignore flag
    for absent, flag in (
        (not math.isfinite(alt), mavlink.GPS_INPUT_IGNORE_FLAG_ALT),
        (not np.isfinite(v[0:2]).all(), mavlink.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ),
        (not math.isfinite(v[2]), mavlink.GPS_INPUT_IGNORE_FLAG_VEL_VERT),
    ):
        if absent:
            flags |= flag
    v = np.nan_to_num(v)
    msg = mavlink.MAVLink_gps_input_message(
        t_us,
        0,
        flags,
        0,
        0,
        3,
        round(float(fixes.lat_deg[m]) * 1e7),
        round(float(fixes.lon_deg[m]) * 1e7),
        alt if math.isfinite(alt) else 0.0,
        0.0,
        0.0,
        float(v[0]),
        float(v[1]),
        float(v[2]),
        float(fixes.vel_acc_mps[m]),
        float(fixes.h_acc_m[m]),
        float(fixes.v_acc_m[m]),
        12,
    )
    return arrival, msg


def config_messages(cfg: RunConfig) -> list[mavlink.MAVLink_message]:
    """NGNAV_CONFIG_TEXT chunks of ``config.toml`` and one NGNAV_ARRAY_CONFIG per channel."""
    text = run_config_text(cfg).encode("utf-8")
    cid = zlib.crc32(text)
    chunks = [text[i : i + CONFIG_CHUNK] for i in range(0, len(text), CONFIG_CHUNK)]
    if len(chunks) > 65535:
        raise ValueError("config.toml too large for NGNAV_CONFIG_TEXT")
    out: list[mavlink.MAVLink_message] = []
    for k, c in enumerate(chunks):
        data = list(c) + [0] * (CONFIG_CHUNK - len(c))
        out.append(mavlink.MAVLink_ngnav_config_text_message(cid, k, len(chunks), len(c), data))
    lay, err = cfg.layout, cfg.known_errors
    n = lay.n_sensors
    for i in range(n):
        out.append(
            mavlink.MAVLink_ngnav_array_config_message(
                cid,
                lay.positions_b_m[i].tolist(),
                lay.axes_b[i].tolist(),
                err.position_error_b_m[i].tolist(),
                err.axis_error_rad[i].tolist(),
                float(cfg.scale[i]),
                float(cfg.offset_mps2[i]),
                float(cfg.noise_sigma_mps2[i]),
                i,
                n,
            )
        )
    return out


def input_frames(
    samples: ArraySamples,
    fixes: GpsFixes,
    cfg: RunConfig,
    *,
    config_every_s: float = 10.0,
) -> Iterator[tuple[int, mavlink.MAVLink_message]]:
    """Every input message of a run in send order: ``(send time_usec, message)``.

    The configuration goes first and every ``config_every_s``; array batches
    when their last sample exists; GPS fixes at their arrival (time + latency).
    """
    cfg_msgs = config_messages(cfg)
    gps = sorted((gps_input_message(fixes, m) for m in range(len(fixes))), key=lambda x: x[0])
    t0 = int(to_usec(samples.t_s[0]))
    for msg in cfg_msgs:
        yield t0, msg
    next_cfg = t0 + int(config_every_s * 1e6)
    g = 0
    for t_us, msg in batch_messages(samples, cfg.range_mps2):
        while g < len(gps) and gps[g][0] <= t_us:
            yield gps[g]
            g += 1
        if config_every_s > 0 and t_us >= next_cfg:
            for c in cfg_msgs:
                yield t_us, c
            next_cfg += int(config_every_s * 1e6)
        yield t_us, msg
    yield from gps[g:]


class SampleGrid:
    """Put array samples on their uniform time grid as they arrive.

    The grid step is the first batch's ``dt_usec`` or, failing that, the
    median interval of the first :attr:`SETTLE` samples (buffered until then).
    A sample off the grid (by more than 1/1000 of a step) is dropped and
    counted; a missing grid point becomes a held (NaN) row, counted.
    """

    SETTLE = 9

    def __init__(self, counts: FrameCounts) -> None:
        self.counts = counts
        self.dt_us: int | None = None
        self.t0_us: int | None = None
        self._k_last = -1
        self._buf: list[tuple[int, np.ndarray]] = []

    def hint(self, dt_us: int) -> None:
        """A step the source declares (a batch's ``dt_usec``); used if none is set yet."""
        if self.dt_us is None and dt_us > 0:
            self.dt_us = int(dt_us)

    def add(self, t_us: int, a: np.ndarray) -> None:
        """Take one sample (strictly later than the last); :meth:`drain` releases it."""
        self._buf.append((t_us, a))

    def drain(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The grid rows now final: ``(t_us (K,), accel (K, N))``, or None."""
        if self.dt_us is None:
            if len(self._buf) < self.SETTLE:
                return None
            d = np.diff([t for t, _ in self._buf])
            self.dt_us = max(1, int(np.median(d)))
        return self._drain()

    def flush(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Everything still buffered (at the end of the input)."""
        if not self._buf:
            return None
        if self.dt_us is None:
            if len(self._buf) < 2:
                return None
            self.dt_us = max(1, int(np.median(np.diff([t for t, _ in self._buf]))))
        return self._drain()

    def _drain(self) -> tuple[np.ndarray, np.ndarray] | None:
        dt = self.dt_us
        ts: list[int] = []
        rows: list[np.ndarray] = []
        for t_us, a in self._buf:
            if self.t0_us is None:
                self.t0_us = t_us
            off = (t_us - self.t0_us) % dt
            if min(off, dt - off) > max(1, dt // 1000):
                self.counts.add("array sample off the grid")
                continue
            k = (t_us - self.t0_us + dt // 2) // dt
            if k <= self._k_last:
                self.counts.add("array sample off the grid")
                continue
            if k > self._k_last + 1 and self._k_last >= 0:
                gap = k - self._k_last - 1
                self.counts.add("missing samples filled", gap)
                for j in range(self._k_last + 1, k):
                    ts.append(self.t0_us + j * dt)
                    rows.append(np.full(a.shape[0], np.nan))
            ts.append(self.t0_us + k * dt)
            rows.append(a)
            self._k_last = k
        self._buf = []
        if not ts:
            return None
        return np.array(ts, dtype=np.int64), np.array(rows)


@dataclass
class InputAssembler:
    """Turn decoded input messages into samples, fixes and the configuration.

    Call :meth:`add` for every message (any type; others are ignored). With
    callbacks the results stream out as they become final: ``on_samples(t_us
    (K,), accel (K, N))`` grid rows (gaps as NaN rows), ``on_fix(t_us, row)``
    with ``row = (lat_deg, lon_deg, alt_m, vn, ve, vd, h_acc_m, v_acc_m,
    vel_acc_mps)``, ``on_config(text)``. Without them they are collected:
    call :meth:`finish`, then :meth:`samples`, :meth:`fixes` and :meth:`config`.
    Everything dropped is counted in ``counts``.
    """

    n_channels: int | None = None
    gps_defaults: GpsDefaults = field(default_factory=GpsDefaults)
    counts: FrameCounts = field(default_factory=FrameCounts)
    on_samples: Callable[[np.ndarray, np.ndarray], None] | None = None
    on_fix: Callable[[int, tuple[float, ...]], None] | None = None
    on_config: Callable[[str], None] | None = None

    def __post_init__(self) -> None:
        self._grid = SampleGrid(self.counts)
        self._t: list[np.ndarray] = []
        self._a: list[np.ndarray] = []
        self._last_t = -1
        self._rows_t: list[int] = []
        self._rows_a: list[np.ndarray] = []
        self._gps: list[tuple] = []
        self._last_gps_t = -1
        self._chunks: dict[int, dict[int, bytes]] = {}
        self._totals: dict[int, int] = {}
        self._config_text: str | None = None

    # ------------------------------------------------------------- array
    def _add_sample(self, t_us: int, values: list[float], valid: int) -> None:
        if t_us <= self._last_t:
            kind = (
                "array sample duplicate time"
                if t_us == self._last_t
                else "array sample out of order"
            )
            self.counts.add(kind)
            return
        a = np.array(values, dtype=float)
        ok = ((valid >> _BITS[: a.shape[0]]) & 1).astype(bool)
        bad = ok & ~np.isfinite(a)
        if bad.any():
            self.counts.add("non-finite field")
        a[~ok | bad] = np.nan
        self._last_t = t_us
        self._grid.add(t_us, a)

    def _emit_samples(self, t_us: np.ndarray, a: np.ndarray) -> None:
        if self.on_samples is not None:
            self.on_samples(t_us, a)
        else:
            self._t.append(t_us)
            self._a.append(a)

    def _check_count(self, count: int) -> bool:
        if self.n_channels is None:
            if not 1 <= count <= SAMPLE_MAX_CHANNELS:
                self.counts.add("wrong channel count")
                return False
            self.n_channels = count
        if count != self.n_channels:
            self.counts.add("wrong channel count")
            return False
        return True

    def add(self, msg: mavlink.MAVLink_message) -> None:
        """Take one decoded message."""
        name = msg.get_type()
        if name == "NGNAV_ARRAY_BATCH":
            if (
                not self._check_count(msg.count)
                or not 1 <= msg.n <= BATCH_MAX_SAMPLES
                or msg.n * msg.count > BATCH_FLOATS
            ):
                if msg.count == self.n_channels:
                    self.counts.add("bad batch size")
                return
            if msg.n > 1 and msg.dt_usec == 0:
                self.counts.add("bad batch size")
                return
            c = msg.count
            if msg.n > 1:
                self._grid.hint(msg.dt_usec)
            for j in range(msg.n):
                self._add_sample(
                    msg.time_usec + j * msg.dt_usec, msg.accel[j * c : (j + 1) * c], msg.valid[j]
                )
            got = self._grid.drain()
            if got is not None:
                self._emit_samples(*got)
        elif name == "NGNAV_ARRAY_SAMPLE":
            if self._check_count(msg.count):
                self._add_sample(msg.time_usec, msg.accel[: msg.count], msg.valid)
                got = self._grid.drain()
                if got is not None:
                    self._emit_samples(*got)
        elif name == "GPS_INPUT":
            self._add_gps_input(msg)
        elif name == "GPS_RAW_INT":
            self._add_gps_raw(msg, msg.time_usec, msg.fix_type, msg.vel, msg.cog, None)
        elif name == "HIL_GPS":
            self._add_gps_raw(
                msg, msg.time_usec, msg.fix_type, msg.vel, msg.cog, (msg.vn, msg.ve, msg.vd)
            )
        elif name == "NGNAV_CONFIG_TEXT":
            self._add_chunk(msg)

    # --------------------------------------------------------------- gps
    def _push_gps(self, t_us: int, row: tuple[float, ...], absent: tuple[int, ...] = ()) -> None:
        """Check a fix row (lat, lon, alt, vn, ve, vd, h_acc, v_acc, vel_acc) and pass it
        on; the fields at ``absent`` the source did not give go on as NaN (the filter
        fuses the rest), each kind counted."""
        given = [x for i, x in enumerate(row) if i not in absent]
        if not all(math.isfinite(x) for x in given):
            self.counts.add("non-finite field")
            return
        if row[6] <= 0 or row[7] <= 0 or row[8] <= 0:
            self.counts.add("gps accuracy not positive")
            return
        row = tuple(math.nan if i in absent else x for i, x in enumerate(row))
        k = int(fix_range_problems(row[0], row[1], row[2], row[3:6])[0])
        if k >= 0:
            self.counts.add(f"gps {FIX_RANGE_KINDS[k]}")
            return
        if t_us <= self._last_gps_t:
            kind = "gps duplicate time" if t_us == self._last_gps_t else "gps out of order"
            self.counts.add(kind)
            return
        self._last_gps_t = t_us
        for i in absent:
            if i in _ABSENT_KINDS:
                self.counts.add(_ABSENT_KINDS[i])
        if self.on_fix is not None:
            self.on_fix(t_us, row)
        else:
            self._gps.append((t_us, *row))

    def _add_gps_input(self, msg) -> None:
        if msg.fix_type < 3:
            self.counts.add("gps without fix")
            return
        d = self.gps_defaults
        f = msg.ignore_flags
        h = (
            d.h_acc_m
            if f & mavlink.GPS_INPUT_IGNORE_FLAG_HORIZONTAL_ACCURACY
            else msg.horiz_accuracy
        )
        v = d.v_acc_m if f & mavlink.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY else msg.vert_accuracy
        s = (
            d.vel_acc_mps
            if f & mavlink.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
            else msg.speed_accuracy
        )
        absent = ()
        if f & mavlink.GPS_INPUT_IGNORE_FLAG_ALT:
            absent += (2,)
        if f & mavlink.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ:
            absent += (3, 4)
        if f & mavlink.GPS_INPUT_IGNORE_FLAG_VEL_VERT:
            absent += (5,)
        self._push_gps(
            msg.time_usec,
            (msg.lat * 1e-7, msg.lon * 1e-7, msg.alt, msg.vn, msg.ve, msg.vd, h, v, s),
            absent,
        )

    def _add_gps_raw(self, msg, t_us: int, fix_type: int, vel_cms: int, cog_cdeg: int, ned) -> None:
        if fix_type < 3:
            self.counts.add("gps without fix")
            return
        if ned is not None:
            vn, ve, vd = (x / 100.0 for x in ned)
            absent = ()
        elif vel_cms == 65535 or cog_cdeg == 65535:
            vn = ve = vd = 0.0
            absent = (3, 4, 5)
        else:
            # GPS_RAW_INT: ground speed along the course; no vertical velocity
            cog = math.radians(cog_cdeg / 100.0)
            vn, ve, vd = vel_cms / 100.0 * math.cos(cog), vel_cms / 100.0 * math.sin(cog), 0.0
            absent = (5,)
        d = self.gps_defaults
        self._push_gps(
            t_us,
            (
                msg.lat * 1e-7,
                msg.lon * 1e-7,
                msg.alt / 1000.0,
                vn,
                ve,
                vd,
                d.h_acc_m,
                d.v_acc_m,
                d.vel_acc_mps,
            ),
            absent,
        )

    # ------------------------------------------------------------ config
    def _add_chunk(self, msg) -> None:
        cid, total = msg.config_id, msg.total
        if (
            self._config_text is not None
            or total == 0
            or msg.seq >= total
            or msg.length > CONFIG_CHUNK
        ):
            if self._config_text is None:
                self.counts.add("bad config chunk")
            return
        self._totals[cid] = total
        self._chunks.setdefault(cid, {})[msg.seq] = bytes(msg.data[: msg.length])
        got = self._chunks[cid]
        if len(got) == total:
            text = b"".join(got[k] for k in range(total))
            if zlib.crc32(text) != cid:
                self.counts.add("bad config chunk")
                del self._chunks[cid]
                return
            self._config_text = text.decode("utf-8", errors="replace")
            if self.on_config is not None:
                self.on_config(self._config_text)

    # ----------------------------------------------------------- results
    def config(self, where: str = "tlog") -> RunConfig:
        """The run configuration carried by the stream (ValueError if none arrived whole)."""
        if self._config_text is None:
            raise ValueError(f"{where}: no complete NGNAV_CONFIG_TEXT configuration in the stream")
        return read_run_config_text(self._config_text, where)

    def finish(self) -> None:
        """End of input: release the samples the grid still holds."""
        got = self._grid.flush()
        if got is not None:
            self._emit_samples(*got)

    def samples(self) -> ArraySamples:
        """The collected array samples on their uniform grid (flushes the grid first)."""
        self.finish()
        n = sum(t.shape[0] for t in self._t)
        if n < 2:
            raise ValueError(f"the stream holds {n} array samples; at least 2 are needed")
        return ArraySamples(np.concatenate(self._t) * 1e-6, np.concatenate(self._a))

    def fixes(self) -> GpsFixes:
        """The accepted GPS fixes, in time order."""
        g = np.array(self._gps, dtype=float).reshape(-1, 10)
        return GpsFixes(
            t_s=g[:, 0] * 1e-6,
            lat_deg=g[:, 1],
            lon_deg=g[:, 2],
            alt_m=g[:, 3],
            vel_ned_mps=g[:, 4:7],
            h_acc_m=g[:, 7],
            v_acc_m=g[:, 8],
            vel_acc_mps=g[:, 9],
            latency_s=np.zeros(g.shape[0]),
        )
