"""End-to-end runs bounded against the truth, as real subprocesses of the CLI.

``ngnav simulate`` writes a flight and its truth; ``ngnav run`` (a CSV run directory,
and a tlog of the same run) and ``ngnav stream`` (live over loopback UDP) write the
filter's estimates. Each run's estimates are read back from its ``estimates.csv``
and compared with ``truth.csv`` here, independently of the filter's own evaluation:

- physical bounds: the horizontal and vertical position errors' RMS below half the
  GPS's own per-axis sigma (a filter that passed each fix through would sit at 1.41
  and 1 times it), the velocity's below the GPS velocity's sigma per axis, the tilt's
  below the 1 deg the tactical hand-over starts with (GPS velocity through the
  manoeuvres and the vehicle models hold it within seconds), the heading's below 3
  times the sigma it starts with (at rest nothing observes it: the error stays the
  prior's draw);
- consistency: each position, velocity, attitude and rate component within 3 of the
  filter's own reported sigmas on at least 90 % of the epochs. A consistent Gaussian
  filter leaves 0.27 % of epochs outside in expectation, so by Markov's inequality a
  share outside above 10 % has a probability below 2.7 % whatever the errors'
  correlation over the run; a filter whose sigma is half its error is outside on
  13 % of epochs per component, and far more where it is off by more.

Three flights, each short (the file runs in about 30 s on one core): ``tactical`` at a
200 Hz array (60 s of +-2.5 g manoeuvres after a 1 deg hand-over, sensor-position
states, body-frame velocity error, lever arm 0.4 m), a 60 s ``uav-survey`` (static
alignment, take-off roll through the lift-off blend, climb, a 25 deg turn), and 40 s of
``static`` (the zero-rate update at rest). The live path runs ``tactical`` at 20 times
real time.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ngnav.rotation import quat_conjugate, quat_multiply, quat_to_rotvec

ROOT = Path(__file__).resolve().parents[1]
NGNAV = (sys.executable, "-m", "ngnav.cli")

TACTICAL = ("--scenario", "tactical", "--set", "run.rate_hz=200")
#: uav-survey's first minute: 10 s at rest (5 s of static alignment), the take-off roll
#: to 20 m/s through the lift-off blend, a climb, a 25 deg turn and the roll-out.
UAV_SHORT = (
    "--scenario",
    "uav-survey",
    "--set",
    "run.rate_hz=200",
    "--set",
    "flight.legs=[{duration_s=10.0,ramp_s=1.0,speed_mps=0.0},"
    "{duration_s=10.0,ramp_s=8.0,speed_mps=20.0},"
    "{duration_s=15.0,ramp_s=2.0,pitch_deg=8.0},"
    "{duration_s=16.0,ramp_s=2.0,pitch_deg=0.0,bank_deg=25.0},"
    "{duration_s=9.0,ramp_s=2.0,bank_deg=0.0}]",
)
#: static's rest, 40 s of it (the zero-rate update holds the rate).
STATIC_SHORT = (
    "--scenario",
    "static",
    "--set",
    "run.rate_hz=200",
    "--set",
    "flight.legs=[{duration_s=40.0,ramp_s=1.0,speed_mps=0.0}]",
)

#: The scenarios' receivers (h_acc_m, v_acc_m, vel_acc_mps: the same in all three) and
#: the configured heading sigma (deg) each flight starts with.
GPS_H_M, GPS_V_M, GPS_VEL_MPS = 1.5, 3.0, 0.1
HEADING_SIGMA_DEG = {"tactical": 2.0, "uav": 5.0, "static": 5.0}
#: The tilt bound, deg: the tactical hand-over's 1-sigma, the worst tilt any flight
#: here starts with (the static alignments level to a few tenths of a degree or better).
TILT_BOUND_DEG = 1.0
#: Share of epochs each component must keep within 3 sigma (module docstring).
INSIDE_3_SIGMA = 0.90


def _cli(*args: str, timeout: float = 300.0) -> str:
    proc = subprocess.run(
        [*NGNAV, *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout
    )
    assert proc.returncode == 0, f"ngnav {' '.join(args)}: {proc.stderr}"
    return proc.stdout


def _read_table(path: Path) -> dict[str, np.ndarray]:
    header = path.read_text().split("\n", 1)[0].strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {name: data[:, i] for i, name in enumerate(header)}


def _cols(table: dict[str, np.ndarray], names: list[str], idx=slice(None)) -> np.ndarray:
    return np.column_stack([table[n][idx] for n in names])


POS_COLS = ["n_m", "e_m", "d_m"]
VEL_COLS = ["vn_mps", "ve_mps", "vd_mps"]
Q_COLS = ["qw", "qx", "qy", "qz"]
RATE_COLS = ["wx_radps", "wy_radps", "wz_radps"]
ATT_SIGMA_COLS = ["att_n_rad_sigma", "att_e_rad_sigma", "att_d_rad_sigma"]


def _errors(estimates: Path, truth: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Errors (truth - estimate) and the filter's sigmas at every estimate epoch, by block:
    NED position and velocity, NED attitude rotation vector, body rate."""
    est, tru = _read_table(estimates), _read_table(truth)
    t = est["t_s"]
    i = np.searchsorted(tru["t_s"], t - 1e-9)
    assert np.all(i < tru["t_s"].shape[0]) and np.allclose(tru["t_s"][i], t, atol=1e-6)
    q_err = quat_multiply(_cols(tru, Q_COLS, i), quat_conjugate(_cols(est, Q_COLS)))
    out = {
        "pos": (_cols(tru, POS_COLS, i) - _cols(est, POS_COLS), POS_COLS),
        "vel": (_cols(tru, VEL_COLS, i) - _cols(est, VEL_COLS), VEL_COLS),
        "att": (quat_to_rotvec(q_err), ATT_SIGMA_COLS),
        "rate": (_cols(tru, RATE_COLS, i) - _cols(est, RATE_COLS), RATE_COLS),
    }
    return {
        k: (e, _cols(est, [c if c.endswith("_sigma") else f"{c}_sigma" for c in names]))
        for k, (e, names) in out.items()
    }


def _assert_bounded(estimates: Path, truth: Path, flight: str, min_epochs: int) -> dict:
    """The module docstring's bounds on one run; returns the measured figures."""
    err = _errors(estimates, truth)
    e_pos, _ = err["pos"]
    assert e_pos.shape[0] >= min_epochs, f"{flight}: {e_pos.shape[0]} estimates"
    got = {
        "horiz_rms_m": float(np.sqrt(np.mean(e_pos[:, 0] ** 2 + e_pos[:, 1] ** 2))),
        "vert_rms_m": float(np.sqrt(np.mean(e_pos[:, 2] ** 2))),
        "vel_rms_mps": np.sqrt(np.mean(err["vel"][0] ** 2, axis=0)),
        "att_rms_deg": np.rad2deg(np.sqrt(np.mean(err["att"][0] ** 2, axis=0))),
    }
    assert got["horiz_rms_m"] < 0.5 * GPS_H_M, (flight, got)
    assert got["vert_rms_m"] < 0.5 * GPS_V_M, (flight, got)
    assert np.all(got["vel_rms_mps"] < GPS_VEL_MPS), (flight, got)
    assert np.all(got["att_rms_deg"][0:2] < TILT_BOUND_DEG), (flight, got)
    assert got["att_rms_deg"][2] < 3.0 * HEADING_SIGMA_DEG[flight], (flight, got)
    for block, (e, sigma) in err.items():
        assert np.all(np.isfinite(sigma)) and np.all(sigma > 0), (flight, block)
        inside = np.mean(np.abs(e) <= 3.0 * sigma, axis=0)
        got[f"{block}_inside_3sigma"] = inside
        assert np.all(inside >= INSIDE_3_SIGMA), (flight, block, inside)
    return got


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Simulate the three flights (tactical twice: as a CSV directory and as a tlog) and
    run the filter on each through ``ngnav run``."""
    tmp = tmp_path_factory.mktemp("bounds")
    _cli("simulate", *TACTICAL, "--out", str(tmp / "tactical"))
    _cli("simulate", *TACTICAL, "--out", str(tmp / "tactical.tlog"))
    _cli("simulate", *UAV_SHORT, "--out", str(tmp / "uav"))
    _cli("simulate", *STATIC_SHORT, "--out", str(tmp / "static"))
    for run in ("tactical", "tactical.tlog", "uav", "static"):
        _cli("run", str(tmp / run))
    return tmp


def test_tactical_csv_run_is_bounded_by_truth(runs):
    """``ngnav run DIR`` on the tactical flight (6001 epochs at 100 Hz)."""
    _assert_bounded(
        runs / "tactical" / "estimates.csv", runs / "tactical" / "truth.csv", "tactical", 6000
    )


def test_tactical_tlog_run_is_bounded_by_truth(runs):
    """``ngnav run X.tlog`` on the same flight as MAVLink: the same bounds, and the same
    errors as the CSV run's to the tlog's float32 fields (positions to 1e-2 m, the rest
    far closer than any bound)."""
    got = _assert_bounded(
        runs / "tactical.estimates.csv", runs / "tactical.truth.csv", "tactical", 6000
    )
    csv = _assert_bounded(
        runs / "tactical" / "estimates.csv", runs / "tactical" / "truth.csv", "tactical", 6000
    )
    assert got["horiz_rms_m"] == pytest.approx(csv["horiz_rms_m"], abs=1e-2)
    np.testing.assert_allclose(got["att_rms_deg"], csv["att_rms_deg"], atol=1e-3)


def test_uav_survey_take_off_is_bounded_by_truth(runs):
    """``ngnav run DIR`` on the first minute of uav-survey (2751 epochs at 50 Hz after the
    5 s static alignment): the lift law through its blend, the vehicle models."""
    _assert_bounded(runs / "uav" / "estimates.csv", runs / "uav" / "truth.csv", "uav", 2700)


def test_static_rest_is_bounded_by_truth(runs):
    """``ngnav run DIR`` on 40 s at rest: the zero-rate update holds the rate; the heading,
    which nothing observes at rest, keeps its prior's error and sigma."""
    _assert_bounded(
        runs / "static" / "estimates.csv", runs / "static" / "truth.csv", "static", 3400
    )


def test_live_stream_is_bounded_by_truth(tmp_path):
    """``ngnav stream`` fed by ``ngnav simulate --stream`` over loopback UDP at 20 times
    real time, its ``--csv`` estimates against the truth ``simulate --out`` wrote."""
    from telemetry.live import free_udp_port

    port = free_udp_port()
    # where the estimate frames go: a bound socket nobody reads (UDP drops the excess)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    live_csv = tmp_path / "live.csv"
    stream = subprocess.Popen(
        [
            *NGNAV,
            "stream",
            "--in",
            f"udpin:127.0.0.1:{port}",
            "--out",
            f"udpout:127.0.0.1:{sink.getsockname()[1]}",
            "--idle-exit",
            "2",
            "--csv",
            str(live_csv),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
    )
    try:
        line = stream.stdout.readline()
        assert "ngnav stream:" in line, (line, stream.stderr.read() if stream.poll() else "")
        _cli(
            "simulate",
            *TACTICAL,
            "--out",
            str(tmp_path / "sim"),
            "--stream",
            f"udpout:127.0.0.1:{port}",
            "--speed",
            "20",
        )
        _, err = stream.communicate(timeout=120)
        assert stream.returncode == 0, err
    finally:
        sink.close()
        if stream.poll() is None:
            stream.kill()
            stream.communicate()
    _assert_bounded(live_csv, tmp_path / "sim" / "truth.csv", "tactical", 6000)
