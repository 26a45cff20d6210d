"""Calibrating a user's own array from static poses of unknown orientation.

The truth is the simulator's (the same array a flight run flies); the recovered offsets,
scales and axis errors are judged by chi-square against the fit's own covariance, over
several runs; bad recordings are refused or skipped, saying why; the CLI writes a
``[calibration]`` a run's ``config.toml`` takes as it is.
"""

import json
import re
import tomllib

import numpy as np
import pytest
from scipy.stats import chi2

from ngnav.layout import layout_by_name
from ngnav.recordings import MIN_POSE_S, poses_from_files, poses_from_recording
from ngnav.records import ArraySamples
from ngnav.runconfig import read_run_config_text
from ngnav.sim.bench_recordings import bench_session, write_bench_session
from ngnav.sim.flight_scenario import load_flight
from ngnav.static_calibration import fit_static_poses, gauge_basis
from tests.helpers import run_cli

SCN = load_flight("uav-survey")
LAYOUT = layout_by_name(SCN.array.layout, SCN.array.lever_arm_m)
N = LAYOUT.n_sensors


def _sensor(session):
    sen = tomllib.loads(session.config_text)["sensor"]
    return (
        np.full(N, sen["noise_sigma_mps2"]),
        np.full(N, sen["bias_rw_mps2_rts"]),
        sen["range_mps2"],
    )


def _nees(session, cal):
    q = gauge_basis(LAYOUT)
    e = np.concatenate(
        [
            cal.offset_mps2 - session.offset_mps2,
            cal.scale - session.scale,
            q.T @ (cal.axis_error_rad - session.axis_error_rad).ravel(),
        ]
    )
    return float(e @ np.linalg.solve(cal.cov, e))


@pytest.mark.parametrize("continuous", [False, True])
def test_the_fit_recovers_the_simulated_array_within_its_sigmas(continuous):
    """Offsets, scales and the axis errors (4N - 3 = 33 parameters) of four runs' arrays:
    the summed NEES is chi-square with 132 dof; inside its 0.001 / 0.999 quantiles."""
    total = 0.0
    for i in range(4):
        s = bench_session(SCN, i, continuous=continuous)
        if continuous:
            poses = poses_from_recording(s.recordings[0][1], *_sensor(s))
        else:
            poses = poses_from_files(s.recordings, *_sensor(s))
        assert len(poses.labels) == 18 and not poses.skipped  # every hold found, no turn
        total += _nees(s, fit_static_poses(poses.means_mps2, poses.sigma_mps2, LAYOUT))
    lo, hi = chi2.ppf([0.001, 0.999], 4 * (4 * N - 3))
    assert lo < total < hi


def test_too_few_poses_name_what_they_leave_undetermined():
    s = bench_session(SCN, 0)
    poses = poses_from_files(s.recordings[:3], *_sensor(s))
    with pytest.raises(ValueError, match=r"3 poses give 27 readings for 39 parameters"):
        fit_static_poses(poses.means_mps2, poses.sigma_mps2, LAYOUT)
    # the six faces only: enough readings, but a face's small tilt trades with the axis
    # angles of the channels across it (the edges' poses tell them apart)
    faces = poses_from_files(s.recordings[:6], *_sensor(s))
    with pytest.raises(ValueError, match=r"leave a combination of .* undetermined") as err:
        fit_static_poses(faces.means_mps2, faces.sigma_mps2, LAYOUT)
    named = str(err.value).split("combination of ")[1].split(" undetermined")[0]
    assert re.search(r"pose \d+'s tilt \d", named), named
    assert len(re.findall(r"axis angle \d of channel \d", named)) >= 2, named


def test_a_pose_that_moves_saturates_or_is_short_is_skipped_with_its_reason():
    s = bench_session(SCN, 0)
    noise, rw, rng = _sensor(s)
    recs = list(s.recordings)
    t, a = recs[0][1].t_s, recs[0][1].accel_mps2.copy()
    a[:, 2] += np.linspace(0.0, 0.05, t.size)  # turning slowly: a ramp on channel 3
    recs[0] = ("moving.csv", ArraySamples(t, a))
    a = recs[1][1].accel_mps2.copy()
    a[10, 4] = rng + 1.0
    recs[1] = ("clipped.csv", ArraySamples(recs[1][1].t_s, a))
    short = recs[2][1]
    recs[2] = ("short.csv", ArraySamples(short.t_s[:100], short.accel_mps2[:100]))
    poses = poses_from_files(recs, noise, rw, rng)
    assert len(poses.labels) == 15
    assert poses.skipped[0].startswith("moving.csv: not still: channel 3")
    assert poses.skipped[1] == "clipped.csv: 1 saturated samples (channels 5)"
    assert poses.skipped[2].startswith(f"short.csv: 0.10 s, shorter than {MIN_POSE_S:g} s")


def test_calibrate_cli_writes_what_a_run_takes(tmp_path):
    """Simulate the bench session, calibrate it through the CLI, put the section into a
    flight run's config.toml: it reads, and holds the fit."""
    d = tmp_path / "bench"
    run_cli("simulate", "--scenario", "uav-survey", "--calibration-recordings", str(d))
    out = run_cli("calibrate", str(d)).stdout
    assert "18 poses from 18 files" in out and re.search(r"chi-square per dof \d", out)
    static_table = out.split("spin fit")[0]  # the positions' table follows it
    assert len([ln for ln in static_table.splitlines() if re.match(r"\s+\d+\s+-?\d", ln)]) == N
    section = (d / "calibration.toml").read_text()
    flight = tmp_path / "flight"
    run_cli("simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--out", str(flight))
    text = (flight / "config.toml").read_text()
    start = text.index("[calibration]")
    end = text.index("[sensor]")
    cfg = read_run_config_text(text[:start] + section + "\n" + text[end:], "merged")
    fit = json.loads(run_cli("calibrate", str(d), "--json").stdout)
    np.testing.assert_allclose(cfg.scale, fit["scale"], rtol=1e-15)
    np.testing.assert_allclose(cfg.known_errors.axis_error_rad, fit["axis_error_rad"], rtol=1e-15)
    truth = tomllib.loads((d / "truth_calibration.toml").read_text())
    z = (np.array(fit["scale"]) - truth["scale"]) / np.array(fit["scale_sigma"])
    assert np.all(np.abs(z) < 5)


def test_calibrate_finds_the_poses_of_one_long_recording(tmp_path):
    d = write_bench_session(bench_session(SCN, 1, continuous=True), tmp_path / "session")
    out = run_cli("calibrate", str(d)).stdout
    assert "18 poses from the still stretches of" in out


def test_calibrate_refuses_bad_directories_in_one_line(tmp_path):
    proc = run_cli("calibrate", str(tmp_path / "none"), check=False)
    assert proc.returncode == 2 and "not a directory" in proc.stderr
    d = write_bench_session(bench_session(SCN, 0), tmp_path / "bench")
    for f in (d / "static").glob("*.csv"):
        f.unlink()
    (d / "static").rmdir()
    proc = run_cli("calibrate", str(d), check=False)
    assert proc.returncode == 2 and "no recordings" in proc.stderr
    d = write_bench_session(bench_session(SCN, 0), tmp_path / "ten")
    p = d / "static" / "pose_01.csv"
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0] + ",a10_mps2"] + [ln + ",0" for ln in lines[1:]]) + "\n")
    proc = run_cli("calibrate", str(d), check=False)
    err = proc.stderr.strip()
    assert proc.returncode == 2 and "\n" not in err
    assert "column 'a10_mps2' beyond the layout's 9 channels" in err
