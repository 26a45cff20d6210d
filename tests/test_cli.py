"""The CLI as a real subprocess, and the paper-reproduction targets."""

import json
import os
import subprocess
import sys

import pytest

from tests.helpers import ROOT, run_cli


def run(*args, check=True):
    return run_cli(*args, check=check)


@pytest.fixture(scope="module")
def paper_json():
    return json.loads(run("paper", "--json").stdout)


def test_paper_reproduction_targets(paper_json):
    m = paper_json["methods"]
    assert set(m) == {"none", "gm11", "last", "line", "oracle"}
    assert len(paper_json["rows"]) == 16
    paper = paper_json["paper"]
    assert paper["measured"]["mean_abs_deg"] == pytest.approx(5.043, abs=1e-3)
    assert paper["compensated"]["mean_abs_deg"] == pytest.approx(3.0325, abs=1e-4)
    # GM(1,1) lowers the mean absolute error at least as much as the paper (-40 %)
    assert m["gm11"]["mean_abs_deg"] <= 0.60 * m["none"]["mean_abs_deg"]
    # and comes within 1.2x of the oracle predictor
    assert m["gm11"]["mean_abs_deg"] <= 1.2 * m["oracle"]["mean_abs_deg"]
    for name, s in m.items():
        assert s["rms_deg"] >= s["mean_abs_deg"] and s["max_abs_deg"] >= s["rms_deg"], name


def test_paper_is_reproducible(paper_json):
    again = json.loads(run("paper", "--json", "--methods", "none,gm11").stdout)
    for a, b in zip(again["rows"], paper_json["rows"], strict=True):
        assert a["gm11_deg"] == b["gm11_deg"] and a["none_deg"] == b["none_deg"]


def test_grey_command():
    out = run("grey", "27260", "29547", "32411", "35388").stdout
    assert "a = -0.08999517239" in out and "38713.4" in out


def test_bad_input_exits_with_message():
    proc = run("paper", "--set", "sensor.noise_mv=loud", check=False)
    assert proc.returncode == 2 and "sensor.noise_mv" in proc.stderr
    proc = run("grey", "1", "2", "3", check=False)
    assert proc.returncode == 2 and "at least 4" in proc.stderr


def test_help_lists_commands():
    out = run("--help").stdout
    users = ("paper", "simulate", "run", "stream", "convert", "evaluate", "consistency", "bench")
    for cmd in (*users, "demo", "plot", "calibrate"):
        assert f"    {cmd}" in out
    assert "    remainder" not in out  # research: python -m studies.remainder
    # ngnav calibrate is the user's bench calibration; the simulated study is research
    assert "static poses" in run("calibrate", "--help").stdout


def test_bench_filter_command():
    """Pipeline and bare loop alternate; a window without filter blocks is an error."""
    out = run("bench-filter", "--scenario", "tactical", "--seconds", "3", "--repeats", "2").stdout
    assert "1000 Hz" in out and "(300 blocks)" in out
    runs = [float(v) for v in out.split("pipeline runs (s):")[1].split(",")]
    assert len(runs) == 2 and all(r > 0 for r in runs)
    ratio = float(out.split("pipeline / bare loop time:")[1].split("x")[0])
    assert ratio > 1.0  # the pipeline does more than filterpy's bare predict/update
    proc = run("bench-filter", "--scenario", "static", "--seconds", "5", check=False)
    assert proc.returncode == 2 and "hold no filter block" in proc.stderr
    js = json.loads(
        run(
            "bench-filter", "--scenario", "tactical", "--seconds", "2", "--repeats", "3", "--json"
        ).stdout
    )
    assert js["blocks"] == 200 and abs(js["samples"] - 2000) <= 1 and len(js["pipeline_s"]) == 3
    # 2 s of 10 Hz fixes and of the two 5 Hz vehicle models: the bare loop makes as many
    assert js["gps_fixes"] == 20 and js["model_updates"] == 20 and js["rest_updates"] == 0
    med = sorted(js["pipeline_s"])[1]
    assert js["pipeline_step_us"] == pytest.approx(1e6 * med / 200)
    assert js["pipeline_samples_per_s"] == pytest.approx(js["samples"] / med)
    ratios = sorted(p / b for p, b in zip(js["pipeline_s"], js["bare_s"], strict=True))
    assert js["pipeline_over_bare"] == pytest.approx(ratios[1])


def test_the_bare_loop_spreads_each_kind_of_update_evenly():
    from filters.bench import _spread

    for count, blocks in ((575, 5750), (7, 10), (10, 10), (0, 5), (23, 5)):
        per = _spread(count, blocks)
        assert per.shape == (blocks,) and per.sum() == count
        assert per.max() - per.min() <= (0 if count % blocks == 0 else 1)


def test_a_free_body_runs_without_a_vehicle_model(tmp_path):
    """``vehicle.kind = "free"`` (the default of a run that declares nothing): tactical's
    manoeuvres flown by a body with no motion constraint go through ``ngnav run`` with no
    vehicle-model update, and the GPS-held errors stay small."""
    free = [
        "vehicle.kind=free",
        "vehicle.lift_k_m=0",
        "vehicle.lift_k_sigma_m=0",
        "vehicle.body_velocity_error=false",
    ]
    sets = [a for f in free for a in ("--set", f)]
    run("simulate", "--scenario", "tactical", *sets, "--out", str(tmp_path / "run"))
    assert 'kind = "free"' in (tmp_path / "run" / "config.toml").read_text()
    out = run("run", str(tmp_path / "run")).stdout
    assert "vehicle models:" not in out and "sideslip" not in out  # no model update at all
    assert "  GPS: gps fixes used " in out  # the summary shows what happened, in groups
    line = next(ln for ln in out.splitlines() if "against truth.csv" in ln)
    horiz = float(line.split("horizontal RMS ")[1].split(" m")[0])
    roll, pitch, _ = (float(x) for x in line.split("RMS ")[-1].split(" deg")[0].split("/"))
    # 10 Hz fixes of 1.5 m (per axis) and the array's tilt from GPS-held velocity
    assert horiz < 1.0 and roll < 2.0 and pitch < 2.0


def test_the_run_summary_shows_counters_that_are_not_zero_in_groups():
    from ngnav.cli.flight import count_lines

    lines = count_lines(
        {
            "samples held (non-finite)": 3,
            "gps fixes used": 600,
            "gps positions rejected (gate)": 0,
            "blocks": 10,
            "sideslip updates": 0,
            "zero-rate updates at rest": 5,
            "something new": 2,
        }
    )
    assert lines == [
        "inputs: samples held (non-finite) 3",
        "GPS: gps fixes used 600",
        "array: blocks 10",
        "rest: zero-rate updates at rest 5",
        "filter: something new 2",
    ]


def _stderr_on_a_terminal(args, env):
    """Run the CLI with stderr on a pseudo-terminal; what it drew there."""
    import fcntl
    import os
    import pty
    import struct
    import termios

    primary, secondary = pty.openpty()
    # a terminal's size, 24 x 80 (a fresh pty has none, and a bar fits in 0 columns)
    fcntl.ioctl(secondary, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "ngnav.cli", *args],
            stdout=subprocess.PIPE,
            stderr=secondary,
            cwd=ROOT,
            env=env,
            timeout=600,
        )
        os.close(secondary)
        chunks = []
        while True:
            try:
                data = os.read(primary, 65536)
            except OSError:  # the terminal's other side is closed: all read
                break
            if not data:
                break
            chunks.append(data)
    finally:
        os.close(primary)
    assert proc.returncode == 0
    return b"".join(chunks).decode(errors="replace")


def test_progress_is_drawn_on_a_terminal_and_not_in_ci_or_a_pipe(tmp_path):
    import os

    d = tmp_path / "run"
    run("simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--out", str(d))
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    drawn = _stderr_on_a_terminal(["run", str(d)], env)
    assert "filter: 100%" in drawn
    sim = ["simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--out", str(d)]
    assert "simulate: 100%" in _stderr_on_a_terminal(sim, env)
    assert _stderr_on_a_terminal(["run", str(d)], {**env, "CI": "true"}) == ""
    piped = subprocess.run(
        [sys.executable, "-m", "ngnav.cli", "run", str(d)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
    )
    assert piped.returncode == 0 and piped.stderr == ""


def test_the_command_runs_blas_on_one_thread_unless_told():
    """The filter's small matrices gain nothing from BLAS threads and lose much on a busy
    machine: the command sets one thread before numpy loads, and a user's setting stands."""
    code = (
        "import os, sys, ngnav.cli; assert 'numpy' not in sys.modules; import numpy; "
        "print(os.environ['OPENBLAS_NUM_THREADS'])"
    )
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    env = {k: v for k, v in env.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    for given, expected in ((None, "1"), ("2", "2")):
        e = env if given is None else {**env, "OPENBLAS_NUM_THREADS": given}
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=e, check=True
        )
        assert out.stdout.strip() == expected


def test_a_new_flight_removes_the_outputs_of_the_earlier_one(tmp_path):
    """Re-simulated into the same folder, the earlier flight's estimates and figures go (read
    beside the new truth they were judged against a flight they never saw); the user's own
    files stay."""
    d = tmp_path / "run"
    (d / "plots").mkdir(parents=True)
    ours = [d / "estimates.csv", d / "estimates.smoothed.npz", d / "plots" / "attitude.png"]
    ours.append(d / "plots" / "report.html")
    theirs = [d / "notes.txt", d / "plots" / "sketch.txt", d / "plots" / "my_photo.png"]
    for f in ours + theirs:
        f.write_text("earlier\n")
    out = run("simulate", "--scenario", "static", "--out", str(d)).stdout
    assert f"removed 4 outputs of an earlier flight (estimates, figures) at {d}" in out
    assert not any(f.exists() for f in ours) and all(f.exists() for f in theirs)
    assert (d / "truth.csv").exists() and (d / "array.csv").exists()
