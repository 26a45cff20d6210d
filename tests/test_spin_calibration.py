"""Sensor positions from rate-table poses (ngnav.spin_calibration).

The truth is the simulator's array (the one a flight run flies), its positions taken into
the frame the static calibration defines; the recovered corrections are judged by
chi-square against the fit's own covariance (rank 3N - 3: no common translation), over
several runs. Spin axes that cannot show a position are refused, naming it.
"""

import json
import tomllib

import numpy as np
import pytest
from scipy.stats import chi2

from ngnav.layout import layout_by_name
from ngnav.recordings import poses_from_files
from ngnav.sim.bench_recordings import SPIN_AXES, bench_session, write_bench_session
from ngnav.sim.flight_scenario import load_flight
from ngnav.spin_calibration import (
    fit_spin_poses,
    offset_drift_var,
    read_spin_pose,
    translation_free_basis,
)
from ngnav.static_calibration import fit_static_poses
from tests.helpers import run_cli

SCN = load_flight("uav-survey")
LAYOUT = layout_by_name(SCN.array.layout, SCN.array.lever_arm_m)
N = LAYOUT.n_sensors


def _fit(session, spins=None):
    sen = tomllib.loads(session.config_text)["sensor"]
    noise = (np.full(N, sen["noise_sigma_mps2"]), np.full(N, sen["bias_rw_mps2_rts"]))
    rng = sen["range_mps2"]
    static = poses_from_files(session.recordings, *noise, rng)
    cal = fit_static_poses(static.means_mps2, static.sigma_mps2, LAYOUT)
    chosen = session.spins if spins is None else [session.spins[j] for j in spins]
    poses = poses_from_files([(n, s) for n, s, _ in chosen], *noise, rng)
    drawings = np.array(tomllib.loads(session.config_text)["calibration"]["position_error_b_m"])
    rates = np.array([w for _, _, w in chosen])
    static_t = (session.recordings[0][1].t_s[0], session.recordings[-1][1].t_s[-1])
    spin_t = (chosen[0][1].t_s[0], chosen[-1][1].t_s[-1])
    drift = offset_drift_var(noise[1], static_t, spin_t)
    return fit_spin_poses(poses.means_mps2, poses.sigma_mps2, rates, LAYOUT, drawings, cal, drift)


def test_the_fit_recovers_the_sensor_positions_within_their_sigmas():
    """Four runs' arrays, 24 position dof each: the summed NEES is chi-square with 96 dof;
    inside its 0.001 / 0.999 quantiles."""
    b = translation_free_basis(N)
    total = 0.0
    for i in range(4):
        s = bench_session(SCN, i)
        fit = _fit(s)
        drawings = np.array(tomllib.loads(s.config_text)["calibration"]["position_error_b_m"])
        truth = (s.position_error_b_m - drawings).ravel()
        e = b.T @ (fit.position_correction_b_m.ravel() - truth)  # no common translation
        total += float(e @ np.linalg.solve(b.T @ fit.position_cov_m2 @ b, e))
        assert abs(fit.position_correction_b_m.mean(axis=0)).max() < 1e-12
    lo, hi = chi2.ppf([0.001, 0.999], 4 * (3 * N - 3))
    assert lo < total < hi


def test_spin_axes_in_one_plane_leave_positions_undetermined():
    s = bench_session(SCN, 0)
    # axes in the x-y plane only (each pose twice): readings enough, but nothing shows
    # how far along z a sensor across z sits
    with pytest.raises(ValueError, match=r"sensor \d's position along body [xyz] undetermined"):
        _fit(s, spins=[0, 1, 3, 4, 0, 1, 3, 4])
    with pytest.raises(ValueError, match=r"3 spin poses give 27 readings"):
        _fit(s, spins=[3, 5, 7])


def test_the_spin_pose_reads_its_axis_and_rate(tmp_path):
    p = tmp_path / "yaw_360dps.csv"
    (tmp_path / "yaw_360dps.toml").write_text("axis_b = [0, 0, 2]\n")
    np.testing.assert_allclose(read_spin_pose(p), [0, 0, 2 * np.pi])
    (tmp_path / "yaw_360dps.toml").write_text("axis_b = [1, 0, 0]\nrate_dps = -90\n")
    np.testing.assert_allclose(read_spin_pose(p), [-np.pi / 2, 0, 0])
    for text, why in (
        ("rate_dps = 90\n", "axis_b must be 3 finite numbers"),
        ("axis_b = [0, 0, 0]\nrate_dps = 90\n", "axis_b must be 3 finite numbers"),
        ("axis_b = [0, 0, 1]\nrate_dps = 0\n", "rate_dps must be a non-zero number"),
        ('axis_b = "up"\nrate_dps = 90\n', "axis_b must be 3 finite numbers"),
        ('axis_b = [0, 0, 1]\nrate_dps = "fast"\n', "rate_dps must be a non-zero number"),
    ):
        (tmp_path / "yaw_360dps.toml").write_text(text)
        with pytest.raises(ValueError, match=why):
            read_spin_pose(p)
    with pytest.raises(ValueError, match=r"no spin\.toml beside it"):
        read_spin_pose(tmp_path / "spin.csv")


def test_calibrate_cli_writes_the_spun_positions(tmp_path):
    d = write_bench_session(bench_session(SCN, 0), tmp_path / "bench")
    assert len(list((d / "spin").glob("*.csv"))) == SPIN_AXES.shape[0]
    out = run_cli("calibrate", str(d)).stdout
    assert "and 9 spin poses" in out and "spin fit: chi-square per dof" in out
    fit = json.loads(run_cli("calibrate", str(d), "--json").stdout)
    section = tomllib.loads((d / "calibration.toml").read_text())["calibration"]
    drawings = tomllib.loads((d / "config.toml").read_text())["calibration"]
    np.testing.assert_allclose(
        section["position_error_b_m"],
        np.array(drawings["position_error_b_m"]) + fit["position_correction_b_m"],
        rtol=0,
        atol=1e-15,
    )
    # what is left: the largest fitted sigma and the drawings' common translation
    sig = np.array(fit["position_sigma_b_m"])
    expected = np.sqrt(sig.max() ** 2 + drawings["position_sigma_m"] ** 2 / N)
    assert section["position_sigma_m"] == pytest.approx(expected, rel=1e-12)
    assert section["position_sigma_m"] < drawings["position_sigma_m"]
    (d / "spin" / "spin_03.toml").unlink()
    proc = run_cli("calibrate", str(d), check=False)
    assert proc.returncode == 2 and "spin_03.csv: no spin_03.toml beside it" in proc.stderr


def test_the_python_api_calibrates_as_the_cli_does(tmp_path):
    from ngnav import api

    d = tmp_path / "bench"
    session = api.simulate_bench("uav-survey", 1, d)
    assert len(session.spins) == SPIN_AXES.shape[0]
    run_cli("calibrate", str(d))
    got = api.calibrate(d)
    assert got.section == (d / "calibration.toml").read_text()
    assert got.spin is not None and got.spin_poses.means_mps2.shape[0] == SPIN_AXES.shape[0]
