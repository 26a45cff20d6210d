"""What ground stations send back on the output link: answered or counted, never queued.

The ground station's messages are built with pymavlink's common dialect (not ngnav's
encoder); the session is the real one, the live link real UDP sockets on loopback."""

from __future__ import annotations

import socket
import threading
import time

import pytest
from pymavlink.dialects.v20 import common

from filters.pipeline import Pipeline
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from telemetry.inputs import input_frames
from telemetry.live import Endpoint, free_udp_port, serve
from telemetry.outputs import OutputSettings
from telemetry.session import StreamSession
from telemetry.tlog import FrameWriter

ME = OutputSettings(system_id=9, component_id=200)
GCS = (255, 190)


def _factory(cfg, on_epoch):
    return Pipeline(cfg, on_epoch=on_epoch)


def _gcs(msg, seq: int = 0) -> bytes:
    mav = common.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1])
    mav.seq = seq
    return bytes(msg.pack(mav))


def _decode(frames) -> list:
    mav = common.MAVLink(None)
    return [mav.decode(bytearray(f.frame)) for f in frames]


def _request(msg_id: float, target=(9, 200)):
    return common.MAVLink_command_long_message(
        *target, common.MAV_CMD_REQUEST_MESSAGE, 0, float(msg_id), 0, 0, 0, 0, 0, 0
    )


@pytest.fixture(scope="module")
def flown_session():
    """A session that has run 3 s of `tactical` (its estimates sent)."""
    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    session = StreamSession(_factory, ME)
    writer = FrameWriter()
    for _, msg in input_frames(sim.samples, sim.fixes, sim.config):
        if getattr(msg, "time_usec", 0) > 3_000_000:
            break
        session.feed_datagram(writer.pack(msg))
    assert session.latest is not None
    return session


def test_a_ping_is_returned_to_its_sender():
    session = StreamSession(_factory, ME)
    (reply,) = _decode(session.feed_command(_gcs(common.MAVLink_ping_message(123456, 7, 0, 0))))
    assert reply.get_type() == "PING"
    assert (reply.time_usec, reply.seq) == (123456, 7)
    assert (reply.target_system, reply.target_component) == GCS
    assert (reply.get_srcSystem(), reply.get_srcComponent()) == (9, 200)
    # a ping reply addressed to someone is not a request: dropped, counted
    assert session.feed_command(_gcs(common.MAVLink_ping_message(1, 1, 3, 4), seq=1)) == []
    c = session.counts.as_dict()
    assert c["commands answered (PING)"] == 1 and c["commands dropped (PING)"] == 1


def test_request_message_answers_what_the_session_sends(flown_session):
    sent = flown_session._sent
    assert common.MAVLINK_MSG_ID_ATTITUDE in sent
    ack, att = _decode(flown_session.feed_command(_gcs(_request(common.MAVLINK_MSG_ID_ATTITUDE))))
    assert ack.get_type() == "COMMAND_ACK" and att.get_type() == "ATTITUDE"
    assert (ack.command, ack.result) == (common.MAV_CMD_REQUEST_MESSAGE, common.MAV_RESULT_ACCEPTED)
    assert (ack.target_system, ack.target_component) == GCS
    # the latest instance the session sent
    assert att.time_boot_ms == sent[common.MAVLINK_MSG_ID_ATTITUDE].time_boot_ms
    ack, hb = _decode(
        flown_session.feed_command(_gcs(_request(common.MAVLINK_MSG_ID_HEARTBEAT, (0, 0)), 1))
    )
    assert hb.get_type() == "HEARTBEAT" and hb.system_status == common.MAV_STATE_ACTIVE
    # a message it never sends: denied
    rc = _gcs(_request(common.MAVLINK_MSG_ID_RC_CHANNELS), 2)
    (ack,) = _decode(flown_session.feed_command(rc))
    assert ack.result == common.MAV_RESULT_DENIED
    # a garbage id is denied too, not an exception in the link's loop
    (ack,) = _decode(flown_session.feed_command(_gcs(_request(float("nan")), 3)))
    assert ack.result == common.MAV_RESULT_DENIED


def test_other_commands_are_unsupported_and_others_traffic_dropped():
    session = StreamSession(_factory, ME)
    arm = common.MAVLink_command_long_message(
        9, 200, common.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
    )
    (ack,) = _decode(session.feed_command(_gcs(arm)))
    assert (ack.command, ack.result) == (
        common.MAV_CMD_COMPONENT_ARM_DISARM,
        common.MAV_RESULT_UNSUPPORTED,
    )
    dropped = [
        _request(common.MAVLINK_MSG_ID_ATTITUDE, (1, 1)),  # for another vehicle
        common.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3),
        common.MAVLink_param_request_list_message(9, 200),
        common.MAVLink_file_transfer_protocol_message(0, 9, 200, [0] * 251),
    ]
    for k, msg in enumerate(dropped, start=1):
        assert session.feed_command(_gcs(msg, seq=k)) == []
    c = session.counts.as_dict()
    assert c["commands answered (COMMAND_LONG)"] == 1
    assert c["commands dropped (COMMAND_LONG)"] == 1
    assert c["commands dropped (HEARTBEAT)"] == 1
    assert c["commands dropped (PARAM_REQUEST_LIST)"] == 1
    assert c["commands dropped (FILE_TRANSFER_PROTOCOL)"] == 1


def test_live_link_answers_a_ground_station_and_drains_its_flood():
    """``serve`` over loopback: a ground station bound at the output address answers the
    first heartbeat's sender with a flood of heartbeats, a PING and a request; every one is
    read and counted, the PING and the request answered on the link."""
    p_in, p_out = free_udp_port(), free_udp_port()
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", p_out))
    gcs.settimeout(5.0)
    flood = 300
    got: list = []

    def ground_station() -> None:
        mav = common.MAVLink(None)
        _, vehicle = gcs.recvfrom(2048)  # the idle heartbeat: where to answer
        for k in range(flood):
            gcs.sendto(_gcs(common.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3), k % 256), vehicle)
        gcs.sendto(_gcs(common.MAVLink_ping_message(42, 5, 0, 0), 44), vehicle)
        gcs.sendto(_gcs(_request(common.MAVLINK_MSG_ID_HEARTBEAT), 45), vehicle)
        t_end = time.monotonic() + 4.0
        while time.monotonic() < t_end and len(got) < 3:
            try:
                data = gcs.recv(2048)
            except TimeoutError:
                break
            m = mav.decode(bytearray(data))
            if m.get_type() in ("PING", "COMMAND_ACK") or (
                m.get_type() == "HEARTBEAT" and got and got[-1] == "COMMAND_ACK"
            ):
                got.append(m.get_type())

    thread = threading.Thread(target=ground_station)
    thread.start()
    args = [Endpoint("udpin", "127.0.0.1", p_in), Endpoint("udpout", "127.0.0.1", p_out), _factory]
    try:
        stats = serve(*args, ME, duration_s=3.0)
    finally:
        thread.join()
        gcs.close()
    assert stats.counts["commands dropped (HEARTBEAT)"] == flood
    assert stats.counts["commands answered (PING)"] == 1
    assert stats.counts["commands answered (COMMAND_LONG)"] == 1
    assert "return link: bad crc" not in stats.counts
    assert got == ["PING", "COMMAND_ACK", "HEARTBEAT"]
