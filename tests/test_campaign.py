"""Campaigns on dask.distributed: a real LocalCluster gives a serial run's results, failed
runs are reported with their index and the others kept, a bad scheduler is one line."""

import math
import time

import numpy as np
import pytest

from filters.consistency import monte_carlo_runs
from ngnav.campaign import RunFailure, run_campaign
from ngnav.sim.flight_scenario import load_flight


def test_a_local_cluster_gives_the_serial_results():
    scn = load_flight("tactical", ["run.rate_hz=200"])
    serial, _ = monte_carlo_runs(scn, 3, "gm11", workers=1)
    cluster, _ = monte_carlo_runs(scn, 3, "gm11", workers=2)
    assert [r["run"] for r in cluster] == [0, 1, 2]
    for a, b in zip(serial, cluster, strict=True):
        assert a.keys() == b.keys()
        for block in a["nees"]:
            np.testing.assert_array_equal(a["nees"][block], b["nees"][block])
        for key in ("t_s", "nis_pos", "nis_vel", "rate_nis"):
            np.testing.assert_array_equal(a[key], b[key])
        assert a["att_rms_deg"] == b["att_rms_deg"]


def _slow_for_the_first(i: int) -> int:
    time.sleep(2.0 if i == 0 else 0.0)
    return i


def test_results_arrive_as_runs_finish_and_a_failure_loses_nothing_else():
    got = []
    failures = run_campaign(math.log, range(4), lambda i, v: got.append((i, v)), workers=2)
    assert failures == [RunFailure(0, "ValueError: math domain error")]
    assert sorted(got) == [(i, math.log(i)) for i in (1, 2, 3)]
    order = []
    run_campaign(_slow_for_the_first, range(4), lambda i, v: order.append(i), workers=2)
    # no barrier behind the slow run 0: the other worker's quick run arrives first
    assert sorted(order) == [0, 1, 2, 3] and order[0] != 0
    serial = []
    assert run_campaign(math.log, range(3), lambda i, v: serial.append(i), workers=1) == [
        RunFailure(0, "ValueError: math domain error")
    ]
    assert serial == [1, 2]


def test_an_unreachable_scheduler_is_one_clear_error():
    with pytest.raises(ValueError, match=r"no dask scheduler at tcp://127\.0\.0\.1:9"):
        run_campaign(math.log, range(2), lambda i, v: None, scheduler="tcp://127.0.0.1:9")


def test_a_campaign_runs_beside_another_cluster():
    """Dask's default HTTP port (8787) taken, as by another campaign on the machine: the
    campaign still runs, with no warning (pytest turns warnings into errors here)."""
    import socket
    import warnings

    other = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        other.bind(("127.0.0.1", 8787))
        other.listen()
    except OSError:
        pass  # already taken by something else: the same situation
    try:
        got = []
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            run_campaign(abs, range(-2, 2), lambda i, v: got.append(v), workers=2)
    finally:
        other.close()
    assert sorted(got) == [0, 1, 1, 2]


def test_a_local_campaign_writes_nothing_on_stderr():
    """A user's terminal shows the campaign's own output only: no dask log lines from the
    cluster's start or its shutdown (workers' connections closing, retirements)."""
    import subprocess
    import sys

    code = (
        "import time\n"
        "from ngnav.campaign import run_campaign\n"
        "got = []\n"
        "run_campaign(time.sleep, range(3), lambda i, v: got.append(i), workers=2)\n"
        "print(sorted(got))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0 and proc.stdout == "[0, 1, 2]\n", proc.stderr
    assert proc.stderr == ""
