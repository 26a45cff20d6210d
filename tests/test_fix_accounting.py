"""Every GPS fix a link delivers is accounted for when the link is cut: each ends in exactly
one of the pipeline's outcome counters (filters.pipeline.FIX_OUTCOMES), through the real
frame layer, assembler, session and filter."""

from __future__ import annotations

import pytest

from filters.pipeline import FIX_OUTCOMES, Pipeline
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from telemetry.inputs import input_frames
from telemetry.session import StreamSession
from telemetry.tlog import FrameWriter


@pytest.fixture(scope="module")
def link_frames():
    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    writer = FrameWriter()
    return [(msg, writer) for _, msg in input_frames(sim.samples, sim.fixes, sim.config)]


def _feed(frames, cut: int, hold_back_s: float):
    """Feed the first ``cut`` frames as datagrams, holding back the GPS fixes of the last
    ``hold_back_s`` seconds and sending them just before the cut (a receiver's late
    reports); then cut the link (finish). Returns the fixes delivered and the counts."""
    session = StreamSession(lambda cfg, on_epoch: Pipeline(cfg, on_epoch=on_epoch))
    writer = FrameWriter()
    fed = [m for m, _ in frames[:cut]]
    t_end = max(m.time_usec for m in fed if m.get_type() == "NGNAV_ARRAY_BATCH")
    held = [
        m for m in fed if m.get_type() == "GPS_INPUT" and m.time_usec > t_end - hold_back_s * 1e6
    ]
    for msg in [m for m in fed if not any(m is h for h in held)] + held:
        session.feed_datagram(writer.pack(msg))
    delivered = sum(m.get_type() == "GPS_INPUT" for m in fed)
    result = session.finish()
    assert session.failure is None, session.failure
    return delivered, len(held), result.counts, session.counts.as_dict()


@pytest.mark.parametrize("fraction", [0.3, 0.55, 0.8, 1.0])
@pytest.mark.parametrize("hold_back_s", [0.0, 0.5])
def test_every_fix_delivered_is_in_exactly_one_outcome(link_frames, fraction, hold_back_s):
    cut = int(len(link_frames) * fraction)
    delivered, held, counts, link = _feed(link_frames, cut, hold_back_s)
    dropped_at_input = sum(v for k, v in link.items() if k.startswith("gps "))
    outcomes = {k: counts[k] for k in FIX_OUTCOMES}
    assert sum(outcomes.values()) + dropped_at_input == delivered, (outcomes, link)
    assert outcomes["gps fix that started the filter"] == 1
    if held:
        # a report older than the fusion horizon is fused late, not lost
        assert counts["gps fixes later than the fusion lag"] >= 1
