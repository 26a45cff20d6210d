"""A ground-side MAVLink client that knows only common.xml (pymavlink's mavutil).

Used by the live tests as a separate process, the way a ground station sits
on the other end of the link: ``python tests/mav_client.py PORT OUT.jsonl
IDLE_S`` listens on ``udpin:127.0.0.1:PORT``, writes one JSON line per
message (type, source ids, sequence, fields) and exits after ``IDLE_S`` of
silence once something arrived (or 60 s with nothing).
"""

import json
import os
import socket
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil


def main() -> int:
    port, out, idle = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
    # A ground station on a fast link sizes its receive buffer for bursts, as the
    # stream's own sockets do: the replay runs at 20x real time (thousands of frames
    # a second) and this decoder, sharing two cores with two other processes, can
    # fall behind the default 208 KiB (one CI run lost frames that way).
    conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    print("listening", flush=True)
    t_last = None
    t0 = time.monotonic()
    with open(out, "w") as fh:
        while True:
            msg = conn.recv_match(blocking=True, timeout=0.2)
            now = time.monotonic()
            if msg is None:
                if (t_last is not None and now - t_last > idle) or (
                    t_last is None and now - t0 > 60
                ):
                    break
                continue
            t_last = now
            d = {
                "type": msg.get_type(),
                "sys": msg.get_srcSystem(),
                "comp": msg.get_srcComponent(),
                "seq": msg.get_seq(),
            }
            if not d["type"].startswith("UNKNOWN"):
                d["fields"] = {
                    k: (list(v) if isinstance(v, (list, tuple)) else v)
                    for k, v in msg.to_dict().items()
                    if k != "mavpackettype"
                }
            fh.write(json.dumps(d) + "\n")
    print("target_system", conn.target_system, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
