"""Replay a run's MAVLink inputs through the stream path as fast as possible.

``ngnav run RUN.tlog`` (and ``ngnav run DIR --out NAME.tlog``) come here: the
input frames go through the same :class:`telemetry.session.StreamSession` a
live link uses, so a replay and the live link of the same run give the same
estimates.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from ngnav.records import RunResult
from ngnav.runconfig import RunConfig
from telemetry.inputs import input_frames
from telemetry.outputs import OutputSettings
from telemetry.runfiles import RunInputs
from telemetry.session import EstimatorFactory, OutputFrame, StreamSession
from telemetry.tlog import FrameWriter, frames_of, read_tlog, tlog_record


@dataclass
class ReplayResult:
    """What a replay produced: the filter's result, the configuration, counts."""

    result: RunResult | None
    config: RunConfig | None
    counts: dict[str, int]
    frames_sent: dict[str, int] = field(default_factory=dict)
    failure: str | None = None


def _run(session: StreamSession, feed: Iterable, out_tlog: Path | None) -> ReplayResult:
    sent: Counter[str] = Counter()
    fh = out_tlog.open("wb") if out_tlog is not None else None

    def on_frame(f: OutputFrame) -> None:
        sent[f.name] += 1
        if fh is not None:
            fh.write(tlog_record(f.t_us, f.frame))

    session.on_frame = on_frame
    try:
        for kind, item in feed:
            if kind == "msg":
                session.feed_message(item)
            else:
                session.feed_datagram(item)
        result = session.finish()
    finally:
        if fh is not None:
            fh.close()
    return ReplayResult(
        result, session.config, session.counts.as_dict(), dict(sent), session.failure
    )


def replay_tlog(
    path: str | Path,
    make_estimator: EstimatorFactory,
    settings: OutputSettings | None = None,
    *,
    out_tlog: str | Path | None = None,
) -> ReplayResult:
    """Run an estimator over an input tlog; write the estimate frames to ``out_tlog``."""
    session = StreamSession(make_estimator, settings)
    feed = (("msg", msg) for _, msg in read_tlog(path, session.decoder))
    return _run(session, feed, Path(out_tlog) if out_tlog is not None else None)


def replay_inputs(
    inp: RunInputs,
    make_estimator: EstimatorFactory,
    settings: OutputSettings | None = None,
    *,
    out_tlog: str | Path | None = None,
) -> ReplayResult:
    """Encode a run's inputs as frames (as ``simulate --out NAME.tlog`` would) and replay them."""
    session = StreamSession(make_estimator, settings)
    frames = frames_of(input_frames(inp.samples, inp.fixes, inp.config), FrameWriter())
    feed = (("bytes", frame) for _, frame in frames)
    return _run(session, feed, Path(out_tlog) if out_tlog is not None else None)
