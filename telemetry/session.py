"""One path from MAVLink input frames to MAVLink estimates: tlog replay and live link alike.

A :class:`StreamSession` takes input frames (a tlog's frames, or UDP
datagrams), decodes them one frame at a time (:mod:`telemetry.frames`),
assembles samples, fixes and the configuration (:mod:`telemetry.inputs`),
runs an estimator as a stream and encodes its estimates
(:mod:`telemetry.outputs`). ``ngnav run RUN.tlog`` and ``ngnav stream`` both use
it, so the same input gives the same estimates. The estimator is whatever the
caller's factory builds from the run's configuration (:class:`Estimator`):
telemetry knows records, not filters.

Before the configuration (``NGNAV_CONFIG_TEXT``) is complete, samples and
fixes are kept; the filter starts from them once it arrives. If the filter
fails (its covariance check, or an alignment without valid samples) the
session stops estimating, counts it, and reports ``MAV_STATE_CRITICAL``; the
input side goes on counting.

What ground stations send back on the output link (:meth:`StreamSession.feed_command`)
is answered where a navigation source has an answer: a PING is returned to its sender,
``MAV_CMD_REQUEST_MESSAGE`` for a message this session sends is answered with its latest
instance and an accepted ``COMMAND_ACK``, any other command addressed to it with
``MAV_RESULT_UNSUPPORTED``. Heartbeats, parameter and file-transfer requests (ngnav has
neither parameters nor files to serve) and everything else are counted and dropped.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ngnav.errors import CovarianceError
from ngnav.geodesy import LocalTangentPlane
from ngnav.records import NavEstimate, RunResult
from ngnav.runconfig import RunConfig, read_run_config_text
from telemetry import ngnav_mavlink as mavlink
from telemetry.frames import FrameDecoder
from telemetry.inputs import GpsDefaults, InputAssembler
from telemetry.outputs import EstimateEncoder, OutputSettings
from telemetry.tlog import FrameWriter


@dataclass(frozen=True)
class OutputFrame:
    """One packed estimate frame and the run-clock time (us) of the epoch it belongs to."""

    t_us: int
    frame: bytes
    name: str


class Estimator(Protocol):
    """What a session needs of an estimator: a stream of samples and fixes in, records out.

    Built by the session's factory ``make(config, on_epoch)``, which must call
    ``on_epoch`` with the :class:`ngnav.records.NavEstimate` of every epoch.
    ``filters.pipeline.Pipeline`` is one.
    """

    n_channels: int
    method: str
    started: bool
    n_epochs: int
    #: True while the estimator has lost its track (it starts again by itself).
    lost: bool
    #: The innovation gate's probability (ESTIMATOR_STATUS's test ratios).
    gate_probability: float
    #: How long after an accepted GPS position an estimate counts as GPS aided, s.
    gps_gap_s: float

    def push_samples(self, t_s: np.ndarray, accel_mps2: np.ndarray) -> int: ...

    def push_fix(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vel_ned_mps: tuple[float, float, float],
        h_acc_m: float,
        v_acc_m: float,
        speed_acc_mps: float,
    ) -> None: ...

    def finish(self) -> int: ...

    def result(self) -> RunResult: ...


#: Builds an estimator from the run's configuration and the per-epoch callback.
EstimatorFactory = Callable[[RunConfig, Callable[[NavEstimate], None]], Estimator]


class StreamSession:
    """Decode inputs, run the filter, encode estimates.

    Parameters
    ----------
    make_estimator : callable
        ``make_estimator(config, on_epoch)`` builds the estimator once the
        configuration has arrived (:data:`EstimatorFactory`); a ``ValueError`` from
        it is a configuration the estimator refuses (counted, reported).
    settings : OutputSettings
        Output identity and rates.
    gps_defaults : GpsDefaults
        Accuracies for GPS messages that lack them.
    allow : set of (system id, component id), optional
        Accepted input sources (None: all).
    wall_clock : callable, optional
        Returns UNIX microseconds for SYSTEM_TIME (live); None uses the run clock.
    on_frame : callable, optional
        Called with every :class:`OutputFrame` as it is produced; otherwise
        frames collect in :attr:`pending` for :meth:`take`.
    """

    def __init__(
        self,
        make_estimator: EstimatorFactory,
        settings: OutputSettings | None = None,
        *,
        gps_defaults: GpsDefaults | None = None,
        allow: set[tuple[int, int]] | None = None,
        wall_clock: Callable[[], int] | None = None,
        on_frame: Callable[[OutputFrame], None] | None = None,
    ) -> None:
        self.make_estimator = make_estimator
        self.settings = settings or OutputSettings()
        self.decoder = FrameDecoder(allow)
        self.counts = self.decoder.counts
        self.assembler = InputAssembler(
            gps_defaults=gps_defaults or GpsDefaults(),
            counts=self.counts,
            on_samples=self._samples,
            on_fix=self._fix,
            on_config=self._config,
        )
        self.wall_clock = wall_clock
        self.on_frame = on_frame
        self.writer = FrameWriter(self.settings.system_id, self.settings.component_id)
        self.config: RunConfig | None = None
        self.estimator: Estimator | None = None
        self.latest: NavEstimate | None = None
        self.encoder: EstimateEncoder | None = None
        self.failure: str | None = None
        self.pending: list[OutputFrame] = []
        self._early: list[tuple] = []
        #: What ground stations send back, decoded on its own (its own sequence counts).
        self.command_decoder = FrameDecoder()
        #: The latest message of each id this session sent (what REQUEST_MESSAGE can get).
        self._sent: dict[int, mavlink.MAVLink_message] = {}

    # ------------------------------------------------------------ input
    def feed_datagram(self, data: bytes) -> None:
        """One UDP datagram: decoded on its own (a corrupt one costs only itself)."""
        for msg in self.decoder.decode_buffer(data):
            self.assembler.add(msg)

    def feed_message(self, msg: mavlink.MAVLink_message) -> None:
        """One message already decoded (a tlog's frames)."""
        self.assembler.add(msg)

    def finish(self) -> RunResult | None:
        """End of input: flush, finish the filter; its result (None if it never ran)."""
        self.assembler.finish()
        if self.estimator is None:
            if self.config is None:
                self.failure = self.failure or "no complete NGNAV_CONFIG_TEXT configuration arrived"
            return None
        if self.failure is None:
            self._guard(self.estimator.finish)
        if self.estimator.started:
            return self.estimator.result()
        return None

    def feed_command(self, data: bytes) -> list[OutputFrame]:
        """One datagram a ground station sent back: the answer frames (see the module
        docstring); every message is counted under ``commands`` in :attr:`counts`."""
        out = []
        for msg in self.command_decoder.decode_buffer(data):
            name = msg.get_type()
            answer = self._answer(msg)
            if answer is None:
                self.counts.add(f"commands dropped ({name})")
                continue
            self.counts.add(f"commands answered ({name})")
            t_us = self._now_us()
            out.extend(OutputFrame(t_us, self.writer.pack(m), m.get_type()) for m in answer)
        return out

    def _answer(self, msg: mavlink.MAVLink_message) -> list[mavlink.MAVLink_message] | None:
        """The replies to one ground-station message, or None (not for us, or no answer)."""
        me = (self.settings.system_id, self.settings.component_id)
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        name = msg.get_type()
        if name == "PING":
            # a request carries target 0/0; the reply names the requester
            if (msg.target_system, msg.target_component) != (0, 0):
                return None
            return [mavlink.MAVLink_ping_message(msg.time_usec, msg.seq, *src)]
        if name not in ("COMMAND_LONG", "COMMAND_INT"):
            return None
        if msg.target_system not in (0, me[0]) or msg.target_component not in (0, me[1]):
            return None
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            # a garbage id (NaN, infinite) is no message this session sends
            wanted = int(msg.param1) if math.isfinite(msg.param1) else -1
            if wanted == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                reply = self.heartbeat_message()
            else:
                reply = self._sent.get(wanted)
            result = mavlink.MAV_RESULT_ACCEPTED if reply is not None else mavlink.MAV_RESULT_DENIED
            ack = mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0, *src)
            return [ack] if reply is None else [ack, reply]
        return [
            mavlink.MAVLink_command_ack_message(
                msg.command, mavlink.MAV_RESULT_UNSUPPORTED, 0, 0, *src
            )
        ]

    def take(self) -> list[OutputFrame]:
        """The frames produced since the last call (when no ``on_frame`` is set)."""
        out, self.pending = self.pending, []
        return out

    def heartbeat(self) -> OutputFrame:
        """A HEARTBEAT frame now (for a live link's idle seconds); state from the session."""
        return OutputFrame(self._now_us(), self.writer.pack(self.heartbeat_message()), "HEARTBEAT")

    def _now_us(self) -> int:
        """The run clock now, us: the latest estimate's time (0 before the first)."""
        return 0 if self.latest is None else round(self.latest.t_s * 1e6)

    def heartbeat_message(self) -> mavlink.MAVLink_message:
        """The HEARTBEAT message now: ``MAV_STATE_CRITICAL`` after a failure, while the
        track is lost or not valid again yet (:mod:`filters.recovery`), or while a channel
        fails a health test (still navigating: ``NGNAV_ARRAY_HEALTH`` names the channels),
        ``ACTIVE`` while the filter runs, ``STANDBY`` before."""
        if self.failure is not None:
            status = mavlink.MAV_STATE_CRITICAL
        elif self.estimator is not None and self.estimator.started:
            faulty = self.estimator.monitor.faulty_mask
            invalid = self.estimator.lost or (self.latest is not None and not self.latest.valid)
            critical = faulty or invalid
            status = mavlink.MAV_STATE_CRITICAL if critical else mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return self.settings.heartbeat(status)

    # ---------------------------------------------------------- plumbing
    def _config(self, text: str) -> None:
        try:
            cfg = read_run_config_text(text, "NGNAV_CONFIG_TEXT")
        except ValueError as exc:
            self.counts.add("bad configuration")
            self.failure = str(exc)
            return
        self.config = cfg
        n = cfg.layout.n_sensors
        if self.assembler.n_channels is None:
            self.assembler.n_channels = n
        try:
            self.estimator = self.make_estimator(cfg, self._epoch)
        except ValueError as exc:
            self.failure = str(exc)
            self.counts.add("filter failed")
            return
        self.encoder = EstimateEncoder(
            self.settings,
            LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m),
            self.estimator.gate_probability,
            self.estimator.gps_gap_s,
            self.estimator.method,
        )
        early, self._early = self._early, []
        for item in early:
            if item[0] == "s":
                self._samples(item[1], item[2])
            else:
                self._fix(item[1], item[2])

    def _samples(self, t_us: np.ndarray, a: np.ndarray) -> None:
        if self.estimator is None:
            if self.failure is None:
                self._early.append(("s", t_us, a))
            return
        if a.shape[1] != self.estimator.n_channels:
            self.counts.add("wrong channel count", t_us.shape[0])
            return
        if self.failure is None:
            self._guard(self.estimator.push_samples, t_us * 1e-6, a)

    def _fix(self, t_us: int, row: tuple[float, ...]) -> None:
        if self.estimator is None:
            if self.failure is None:
                self._early.append(("f", t_us, row))
            return
        if self.failure is None:
            lat, lon, alt, vn, ve, vd, h, v, s = row
            self._guard(self.estimator.push_fix, t_us * 1e-6, lat, lon, alt, (vn, ve, vd), h, v, s)

    def _guard(self, fn, *args) -> None:
        try:
            fn(*args)
        except (CovarianceError, ValueError) as exc:
            self.failure = str(exc)
            self.counts.add("filter failed")

    def _epoch(self, est: NavEstimate) -> None:
        self.latest = est
        unix = self.wall_clock() if self.wall_clock is not None else None
        t_us = round(est.t_s * 1e6)
        for msg in self.encoder.epoch(est, unix):
            self._sent[msg.get_msgId()] = msg
            frame = OutputFrame(t_us, self.writer.pack(msg), msg.get_type())
            if self.on_frame is not None:
                self.on_frame(frame)
            else:
                self.pending.append(frame)
