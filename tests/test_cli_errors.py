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


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("[gps]", "[gpss]", "unknown section [gpss] (did you mean [gps]?)"),
        (
            "antenna_b_m =",
            "antena_b_m =",
            "unknown key gps.antena_b_m (did you mean gps.antenna_b_m?)",
        ),
        ("[vehicle]", "[vehicles]", "unknown section [vehicles] (did you mean [vehicle]?)"),
        (
            "range_mps2 =",
            "range_mps =",
            "unknown key sensor.range_mps (did you mean sensor.range_mps2?)",
        ),
    ],
)
def test_a_misspelt_config_section_or_key_is_refused(tactical_run, tmp_path, old, new, needle):
    """Read as absent, a misspelt [gps] put the antenna at the array and a misspelt [vehicle]
    turned the fixed-wing models off, without a word."""
    run = tmp_path / "run"
    run.mkdir()
    for f in tactical_run.iterdir():
        (run / f.name).write_bytes(f.read_bytes())
    text = (run / "config.toml").read_text()
    assert old in text
    (run / "config.toml").write_text(text.replace(old, new, 1))
    proc = run_cli("run", str(run), check=False)
    assert proc.returncode == 2 and needle in _one_line(proc)


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
    # a shell's background job (`make test &`) ignores SIGINT, and a child inherits that: start
    # the command as a terminal would, with SIGINT at its default (a caught signal is)
    ignored = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
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
    finally:
        signal.signal(signal.SIGINT, ignored)
    t0 = time.monotonic()
    try:
        assert proc.stdout.readline().startswith("simulated ")  # now streaming for a minute
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    took = time.monotonic() - t0
    assert proc.returncode == 130, f"exit {proc.returncode} after {took:.1f} s: {out!r} {err!r}"
    assert "Traceback" not in err and err.strip() == "ngnav simulate: interrupted"


def test_a_bad_stream_endpoint_is_refused_before_the_simulation(tmp_path):
    proc = run_cli(
        "simulate",
        "--scenario",
        "static",
        "--out",
        str(tmp_path / "run"),
        "--stream",
        "127.0.0.1:14560",
        check=False,
    )
    assert proc.returncode == 2 and "is not udpin:HOST:PORT or udpout" in _one_line(proc)
    assert not (tmp_path / "run").exists()  # nothing simulated, nothing written


def test_output_options_a_csv_run_ignores_are_still_checked(tactical_run, tmp_path):
    """A bad MAVLink rate was refused only for a tlog output; ``convert`` to NAME.csv made a
    directory of that name."""
    proc = run_cli(
        "run", str(tactical_run), "--rate", "odometry=abc", "--out", str(tmp_path / "e.csv"),
        check=False,
    )  # fmt: skip
    assert proc.returncode == 2 and "output rate 'odometry=abc' is not STREAM=HZ" in _one_line(proc)
    proc = run_cli("convert", str(tactical_run), str(tmp_path / "out.csv"), check=False)
    assert proc.returncode == 2 and "a run is a directory" in _one_line(proc)
    assert not (tmp_path / "out.csv").exists()
