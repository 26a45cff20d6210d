"""What a user sees when something goes wrong: one line and an exit status, never a traceback.

Every case runs the real ``ngnav`` command as a subprocess.
"""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.helpers import ROOT, run_cli


def _one_line(proc: subprocess.CompletedProcess) -> str:
    """The stderr of a failed command: no traceback, one line that starts with the command."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("ngnav "), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def tactical_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("tactical") / "run"
    run_cli(
        "simulate",
        "--scenario",
        "tactical",
        "--set",
        "flight.legs=[]",
        "--out",
        str(d),
        check=False,
    )
    if not (d / "config.toml").exists():
        run_cli("simulate", "--scenario", "tactical", "--out", str(d))
    return d


def test_a_diverged_filter_reports_in_one_line_keeps_its_estimates_and_exits_3(
    tactical_run, tmp_path
):
    """No compensation of tactical's 6 mm mounting offsets loses the tilt within seconds."""
    out = tmp_path / "partial.csv"
    proc = run_cli(
        "run", str(tactical_run), "--compensation", "none", "--out", str(out), check=False
    )
    assert proc.returncode == 3
    line = _one_line(proc)
    assert "the filter stopped" in line and "t = " in line and str(out) in line
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    assert rows.ndim == 2 and rows.shape[0] > 10
    n = int(line.split("the ")[2].split(" estimates")[0])
    assert rows.shape[0] == n
    # the estimates stop where the filter did, well before the flight's end
    t_stop = float(line.split("at t = ")[1].split(" s")[0])
    assert rows[-1, 0] <= t_stop + 1e-9


def test_a_diverged_tlog_replay_reports_the_same_way(tactical_run, tmp_path):
    tlog = tmp_path / "run.tlog"
    run_cli("convert", str(tactical_run), str(tlog))
    out = tmp_path / "partial.csv"
    proc = run_cli("run", str(tlog), "--compensation", "none", "--out", str(out), check=False)
    assert proc.returncode == 3
    assert "the filter stopped" in _one_line(proc)
    assert np.loadtxt(out, delimiter=",", skiprows=1).shape[0] > 10


@pytest.mark.parametrize(
    ("make", "needle"),
    [
        (lambda p: p / "missing", "no such file"),
        (lambda p: p / "run" / "array.csv", "is not a run"),
    ],
)
def test_bad_run_paths_are_one_line_and_exit_2(tactical_run, tmp_path, make, needle):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "array.csv").write_text("t_s\n")
    proc = run_cli("run", str(make(tmp_path)), check=False)
    assert proc.returncode == 2
    assert needle.lower() in _one_line(proc).lower()


def test_an_unwritable_out_is_refused_before_the_run(tactical_run, tmp_path):
    for out, needle in (
        (tmp_path / "nofolder" / "e.csv", "does not exist"),
        (tmp_path, "is a directory"),
    ):
        proc = run_cli("run", str(tactical_run), "--out", str(out), check=False)
        assert proc.returncode == 2
        assert needle in _one_line(proc)
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        proc = run_cli("run", str(tactical_run), "--out", str(ro / "e.csv"), check=False)
        assert proc.returncode == 2 and "not writable" in _one_line(proc)


def test_an_unknown_set_key_names_it_and_suggests_the_nearest():
    proc = run_cli(
        "simulate",
        "--scenario",
        "tactical",
        "--set",
        "filter.rate_hzz=5",
        "--out",
        "x",
        check=False,
    )
    assert proc.returncode == 2
    line = _one_line(proc)
    assert "filter.rate_hzz" in line and "did you mean filter.rate_hz?" in line
    proc = run_cli(
        "simulate", "--scenario", "tactical", "--set", "filtr.rate_hz=5", "--out", "x", check=False
    )
    assert proc.returncode == 2 and "did you mean filter?" in _one_line(proc)


def test_ctrl_c_exits_130_without_a_traceback(tmp_path):
    """SIGINT (what Ctrl-C sends) while a simulated flight streams in real time."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ngnav.cli",
            "simulate",
            "--scenario",
            "tactical",
            "--out",
            str(tmp_path / "run"),
            "--stream",
            "udpout:127.0.0.1:9",
            "--speed",
            "1",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().startswith("simulated ")  # now streaming for a minute
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip() == "ngnav simulate: interrupted"
