"""The GPS/array filter end to end: files, bad input, glitches, covariance checks, CLI."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from filters.comparison import (
    EvaluationRow,
    evaluate_scenario,
    gap_before_divergence,
    run_configuration,
)
from filters.consistency import consistency, nees_profile
from filters.ekf import FilterNoise, NavFilter
from filters.evaluate import chi2_bounds, run_errors, summarise, truth_aoa_rad, truth_indices
from filters.pipeline import run_filter
from ngnav.errors import CovarianceError
from ngnav.records import ArraySamples
from ngnav.runconfig import read_run_config, write_run_config
from ngnav.runio import read_array_csv, read_gps_csv, write_array_csv, write_gps_csv
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from tests.helpers import initialise_level

ROOT = Path(__file__).resolve().parents[1]
SHORT = ["run.rate_hz=200"]


@pytest.fixture(scope="module")
def tactical():
    return simulate_flight(load_flight("tactical", SHORT), 0)


def test_config_round_trip(tmp_path, tactical):
    write_run_config(tactical.config, tmp_path / "config.toml")
    back = read_run_config(tmp_path / "config.toml")
    assert np.array_equal(
        back.known_errors.axis_error_rad, tactical.config.known_errors.axis_error_rad
    )
    assert np.array_equal(back.scale, tactical.config.scale)
    assert back.initial == tactical.config.initial and back.filter == tactical.config.filter
    # a hand-over starts on the launcher's rate reading: the truth plus a draw of its sigma
    ini = tactical.config.initial
    err = np.array(ini.rate_dps) - np.rad2deg(tactical.truth.omega_b_rps[0])
    assert ini.alignment == "config" and np.all(np.abs(err) > 0)
    assert np.all(np.abs(err) < 5.0 * ini.rate_sigma_dps)
    text = (tmp_path / "config.toml").read_text()
    bad = text.replace("rate_dps = [", "rate_dps = [1.0, ")
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(ValueError, match=r"initial\.rate_dps must be 3 finite numbers"):
        read_run_config(tmp_path / "bad.toml")


def test_config_format_documents_every_setting():
    """The ``config.toml`` format in ``ngnav.runconfig``'s docstring (which the README
    points to for the full list) names every key of its settings sections."""
    import dataclasses
    import re

    import ngnav.runconfig as rc

    doc = rc.__doc__
    sections = (
        ("initial", rc.InitialSettings),
        ("filter", rc.FilterSettings),
        ("compensation", rc.CompensationSettings),
        ("vehicle", rc.VehicleSettings),
        ("rest", rc.RestSettings),
    )
    for section, cls in sections:
        block = doc[doc.index(f"[{section}]") :]
        block = block[: re.search(r"\n    \[(?!" + section + r"\])", block + "\n    [").start()]
        missing = [
            f.name for f in dataclasses.fields(cls) if not re.search(rf"\b{f.name}\b", block)
        ]
        assert not missing, (section, missing)


def test_csv_round_trip_and_bad_files(tmp_path, tactical):
    write_array_csv(tmp_path / "array.csv", tactical.samples)
    s, rep = read_array_csv(tmp_path / "array.csv", 9)
    assert np.allclose(s.accel_mps2, tactical.samples.accel_mps2, rtol=1e-9, atol=1e-12)
    assert rep.counts == {}
    lines = (tmp_path / "array.csv").read_text().splitlines()
    # a NaN row is held and counted; a dropped row is filled and counted
    lines[10] = ",".join([lines[10].split(",")[0]] + ["nan"] * 9)
    del lines[20]
    (tmp_path / "a2.csv").write_text("\n".join(lines))
    s2, rep2 = read_array_csv(tmp_path / "a2.csv", 9)
    assert rep2.counts == {"missing samples filled": 1, "bad samples (non-finite cell)": 1}
    assert np.count_nonzero(s2.invalid) == 2
    assert s2.t_s.shape == s.t_s.shape
    # unsorted time: file, line and column named
    bad = lines.copy()
    bad[30], bad[31] = bad[31], bad[30]
    (tmp_path / "a3.csv").write_text("\n".join(bad))
    with pytest.raises(
        ValueError, match=r"a3.csv, line 32, column 't_s': unsorted time 0.15 after 0.155"
    ):
        read_array_csv(tmp_path / "a3.csv", 9)
    (tmp_path / "a4.csv").write_text("t_s,a1_mps2\n0,1\n")
    with pytest.raises(ValueError, match=r"a4.csv: missing column 'a2_mps2'"):
        read_array_csv(tmp_path / "a4.csv", 9)
    bad = lines.copy()
    bad[5] = bad[5].replace(bad[5].split(",")[3], "x1", 1)
    (tmp_path / "a5.csv").write_text("\n".join(bad))
    with pytest.raises(ValueError, match=r"a5.csv, line 6, column 'a3_mps2': not a number"):
        read_array_csv(tmp_path / "a5.csv", 9)


def test_gps_without_fix_is_skipped_and_counted(tmp_path, tactical):
    write_gps_csv(tmp_path / "gps.csv", tactical.fixes)
    lines = (tmp_path / "gps.csv").read_text().splitlines()
    cells = lines[5].split(",")
    cells[-2] = "1"  # fix_type 1: no 3-D fix
    lines[5] = ",".join(cells)
    cells = lines[8].split(",")
    cells[1] = ""
    lines[8] = ",".join(cells)
    (tmp_path / "g2.csv").write_text("\n".join(lines))
    fixes, rep = read_gps_csv(tmp_path / "g2.csv")
    assert len(fixes) == len(tactical.fixes) - 2
    assert rep.counts == {"no fix (fix_type < 3)": 1, "no fix (empty or nan cell)": 1}


def test_bad_samples_and_a_glitch_do_not_stop_or_corrupt_the_run(tactical):
    a = tactical.samples.accel_mps2.copy()
    a[3000] = np.nan  # one corrupt sample
    a[3500, 4] = np.inf
    samples = ArraySamples(tactical.samples.t_s, a)
    t = tactical.fixes
    lat = t.lat_deg.copy()
    k = 300
    lat[k] += 50.0 / 111_000.0  # a 50 m jump north in one fix
    from dataclasses import replace

    fixes = replace(t, lat_deg=lat)
    res = run_filter(samples, fixes, tactical.config)
    assert res.counts["samples held (non-finite)"] == 2
    i = int(np.flatnonzero(np.isclose(res.innovations.t_s, t.t_s[k]))[0])
    assert not res.innovations.pos_accepted[i] and res.innovations.nis_pos[i] > 100
    e = int(np.searchsorted(res.estimates.t_s, t.t_s[k]))
    est = res.estimates
    moved = (
        est.pos_ned_m[e]
        - est.pos_ned_m[e - 1]
        - est.vel_ned_mps[e - 1] * (est.t_s[e] - est.t_s[e - 1])
    )
    assert np.linalg.norm(moved[:2]) < np.sqrt(np.trace(est.cov_nav[e - 1][:2, :2]))
    clean = run_filter(tactical.samples, tactical.fixes, tactical.config)
    err_bad = run_errors(res.estimates, tactical.truth)
    err_ok = run_errors(clean.estimates, tactical.truth)
    late = err_ok.t_s > t.t_s[k] + 5
    assert np.abs(err_bad.pos_ned_m[late] - err_ok.pos_ned_m[late]).max() < 0.5


def test_the_final_record_carries_the_whole_state_and_its_covariance(tactical):
    """The last epoch's record holds every block the filter carries, the one it used."""
    res = run_filter(tactical.samples, tactical.fixes, tactical.config)
    fin = res.final
    names = [name for name, _ in fin.state_blocks]
    assert names == ["pos", "vel", "att", "rate", "b_wdot", "b_f", "b_quad", "dr", "aoa"]
    assert fin.cov.shape == (res.state_size, res.state_size)
    np.testing.assert_array_equal(fin.cov, fin.cov.T)
    assert np.linalg.eigvalsh(fin.cov).min() > 0.0
    np.testing.assert_array_equal(fin.cov_nav, res.estimates.cov_nav[-1])
    np.testing.assert_array_equal(fin.block_cov("vel"), fin.cov[3:6, 3:6])
    # the sensor positions' estimate against the simulated residual scatter (27 dof)
    dr_true = (
        tactical.true_errors.position_error_b_m - tactical.config.known_errors.position_error_b_m
    ).ravel()
    e = dr_true - fin.dr_m
    assert e @ np.linalg.solve(fin.block_cov("dr"), e) < chi2.ppf(0.999, 27)
    assert fin.aoa_states.shape == (2,)
    with pytest.raises(KeyError, match="no state block 'gyro'"):
        fin.block_cov("gyro")


def test_covariance_check_fails_loudly():
    eye = np.eye(9) * 1e-6
    nf = NavFilter(FilterNoise(eye, eye, eye), np.array([[1, 2], [0, 2], [0, 1]]), np.zeros(3))
    initialise_level(nf)
    p = nf.P.copy()
    p[0, 0] = -1.0
    nf.P = p
    with pytest.raises(CovarianceError, match=r"not positive definite after test at t = 0\.000 s"):
        nf.check_covariance("test")


@pytest.fixture(scope="module")
def tactical_1khz():
    # at 1 kHz the uncompensated filter fails its covariance check at about 22 s
    return simulate_flight(load_flight("tactical"), 0)


def test_a_diverged_run_keeps_what_it_estimated_before_the_failure(tactical_1khz):
    sim = tactical_1khz
    with pytest.raises(CovarianceError) as info:
        run_filter(sim.samples, sim.fixes, sim.config, compensation="none")
    part = info.value.partial
    assert part is not None
    t_fail = float(info.value.args[0].split("t = ")[1].split(" s")[0])
    t_end = float(part.estimates.t_s[-1])
    assert 1.0 < t_end <= t_fail
    # causality: the partial estimates are those of the same run cut short
    t_cut = t_end - 0.2
    cut = sim.samples.t_s <= t_cut
    short = run_filter(
        ArraySamples(sim.samples.t_s[cut], sim.samples.accel_mps2[cut]),
        sim.fixes,
        sim.config,
        compensation="none",
    )
    k = short.estimates.t_s <= t_cut - 0.5
    n = int(k.sum())
    np.testing.assert_allclose(part.estimates.t_s[:n], short.estimates.t_s[k], rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        part.estimates.pos_ned_m[:n], short.estimates.pos_ned_m[k], atol=1e-6
    )
    np.testing.assert_allclose(part.estimates.cov_nav[:n], short.estimates.cov_nav[k], atol=1e-8)


def test_gm11_gap_is_measured_before_no_compensation_diverges(tactical_1khz):
    sim = tactical_1khz
    errors, rows = {}, []
    for name in ("gm11", "none", "oracle"):
        try:
            res, failure = run_configuration(sim, name), None
        except CovarianceError as exc:
            res, failure = exc.partial, f"diverged: {exc}"
        errors[name] = run_errors(res.estimates, sim.truth)
        rows.append(EvaluationRow(name, summarise(errors[name]), None, {}, failure))
    assert rows[1].failure and not rows[0].failure and not rows[2].failure
    gap = gap_before_divergence(rows, errors)
    t0, t1 = gap["window_s"]
    assert t1 == errors["none"].t_s[-1] and 1.0 < t1 < 60.0
    rms = {}
    for name, e in errors.items():
        s = summarise(e, (e.t_s >= t0) & (e.t_s <= t1))
        rms[name] = float(np.sqrt(s.roll_rms_deg**2 + s.pitch_rms_deg**2 + s.yaw_rms_deg**2))
        assert gap["att_rms_deg"][name] == pytest.approx(rms[name], rel=1e-9)
    closed = (rms["none"] - rms["gm11"]) / (rms["none"] - rms["oracle"])
    assert gap["closed"] == pytest.approx(closed, rel=1e-9)
    # without a divergence there is nothing to window
    rows[1] = EvaluationRow("none", rows[1].summary, None, {}, None)
    assert gap_before_divergence(rows, errors) is None


def test_gps_alone_row_when_every_filter_configuration_diverges():
    # "none" on tactical loses its tilt twice (LostTrackError at 3.0 s); the GPS-alone
    # row must not depend on a filter configuration that finished
    scn = load_flight("tactical", ["run.rate_hz=200", "filter.rate_hz=100"])
    out = evaluate_scenario(scn, 0, configurations=("none", "gps-alone"))
    none, gps = out["rows"]
    assert none.failure and "lost" in none.failure
    assert gps.name == "gps-alone" and gps.failure is None
    # GPS alone (a constant-velocity filter on the fixes) over the whole run: finite and
    # below the raw fixes' error
    assert 0.0 < gps.summary.horiz_rms_m < out["raw_gps_horiz_rms_m"]
    assert "events" not in out


def test_oracle_needs_truth(tactical):
    with pytest.raises(ValueError, match="oracle"):
        run_filter(tactical.samples, tactical.fixes, tactical.config, compensation="oracle")


def test_simulate_then_run_cli(tmp_path):
    run = (sys.executable, "-m", "ngnav.cli")
    d = tmp_path / "run"
    sim = subprocess.run(
        [*run, "simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--out", str(d)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert sim.returncode == 0, sim.stderr
    # the unknown positions' channel error beside the noise, and whether states model it
    assert "unknown sensor positions (0.5 mm 1-sigma): channel error" in sim.stdout
    assert "filter position states on" in sim.stdout
    # the calibration's residual beside the bias walk: tactical's few g leave it below
    assert "the calibration's scale and axis residual: channel error moves by" in sim.stdout
    assert "filter axis states off" in sim.stdout
    for f in ("array.csv", "gps.csv", "config.toml", "truth.csv"):
        assert (d / f).is_file()
    out = subprocess.run([*run, "run", str(d)], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    # the summary: "  GROUP: name value, name value", counters that are zero left out
    counts = dict(
        item.rsplit(" ", 1)
        for line in out.stdout.splitlines()
        if line.startswith("  ") and ": " in line and "truth" not in line
        for item in line.split(": ", 1)[1].split(", ")
    )
    # a 0.9999 gate rejects about one good fix in 10^4 per measurement
    rejected = int(counts.get("gps positions rejected (gate)", 0))
    assert int(counts["gps fixes used"]) >= 595 and rejected <= 3
    assert "against truth.csv" in out.stdout
    header = (d / "estimates.csv").read_text().splitlines()[0].split(",")
    contract = (
        "t_s,lat_deg,lon_deg,alt_m,n_m,e_m,d_m,vn_mps,ve_mps,vd_mps,qw,qx,qy,qz,"
        "wx_radps,wy_radps,wz_radps"
    ).split(",")
    assert header[: len(contract)] == contract
    assert all(f"{c}_sigma" in header for c in contract[1:10] + contract[14:17])
    bad = subprocess.run(
        [*run, "run", str(tmp_path / "nowhere")], capture_output=True, text=True, cwd=ROOT
    )
    assert bad.returncode == 2 and "nowhere: no such file or directory" in bad.stderr


#: The hand-over transient of ``tactical`` ends by this time (s); see
#: :func:`test_hand_over_is_consistent`.
HAND_OVER_S = 10.0


@pytest.fixture(scope="module")
def monte_carlo():
    # the scenario as shipped (1 kHz array): about 45 s on two workers
    return consistency(
        load_flight("tactical"), runs=6, workers=2, profile_s=2.0, from_s=HAND_OVER_S
    )


def test_consistency_small_monte_carlo(monte_carlo):
    """After the hand-over, the velocity, attitude, rate, joint and angle-of-attack NEES
    and every NIS inside the 6-run bounds on >= 90 % of epochs (at 50 runs every block
    meets it from 10 s: 96.8 / 97.7 / 99.2 / 95.5 / 95.0 / 100.0 %, the position
    included). The position from 10 s is left out at this size: it reads 89.1 % where a
    perfect-array filter on the same fixes reads 81.4 % (the fixes' draw)."""
    out = monte_carlo
    assert out["from_s"] == HAND_OVER_S
    b = out["blocks_from"]
    names = ("NEES vel", "NEES att", "NEES rate", "NEES all", "NEES aoa")
    for name in (*names, "NIS gps pos", "NIS gps vel", "NIS rate"):
        assert b[name]["share_inside"] >= 0.9, (name, b[name])
    for blocks in (out["blocks"], b):
        for name, v in blocks.items():
            share = v["share_inside"] + v["share_below"] + v["share_above"]
            assert share == pytest.approx(1.0), name
    # the 60 s flight in 2 s windows from its start (the profile covers the whole run)
    assert [round(r["t0_s"]) for r in out["profile"]] == list(range(0, 60, 2))
    assert all(np.isfinite(r[k]) for r in out["profile"] for k in ("pos", "att", "all"))
    json.dumps(out)


def test_target_is_met(monte_carlo):
    """The issue's target at CI size: every NEES block (position, velocity, attitude,
    rate, all twelve together, angle of attack) and every NIS inside the 6-run bounds
    on >= 90 % of the whole run's epochs. At 50 runs (``ngnav consistency --scenario
    tactical --runs 50``, README "Targets (issue 3)") it reads 96.4 / 97.1 / 99.4 /
    94.2 / 93.4 / 95.7 %, NIS 94.7 / 94.8 / 94.8 %; here 90.9 / 96.8 / 97.3 / 95.4 /
    92.3 / 99.5 %. Until the sensor positions' states took the forecast loop's
    ``T S G`` (``NavFilter.geometry_jacobian``) the joint read 85.0 % at 50 runs."""
    blocks = monte_carlo["blocks"]
    nees = [f"NEES {b}" for b in ("pos", "vel", "att", "rate", "all", "aoa")]
    assert set(blocks) == {*nees, "NIS gps pos", "NIS gps vel", "NIS rate"}
    for name, v in blocks.items():
        assert v["share_inside"] >= 0.9, (name, v)


def test_hand_over_is_consistent(monte_carlo):
    """Every 2 s window's attitude and angle-of-attack NEES inside the 6-run bounds,
    the hand-over included. Until the attitude-product part of the vehicle models'
    remainder was counted as persistent (``vehicle_model.ATTITUDE_REMAINDER_UPDATES``) the
    hand-over's 1 deg tilt errors made the attitude and angle of attack optimistic
    at 2-6 s (attitude NEES 5-7.5 against a bound of 5.25); at this size the windows
    now read attitude 2.3-4.3 and angle of attack 0.8-1.5 in the first 14 s (2b4e58e;
    the hand-over counts its remainder as a coast's end, ``NavFilter.handover_hold_s``)."""
    lo3, hi3 = chi2_bounds(3, 6)
    lo1, hi1 = chi2_bounds(1, 6)
    for row in monte_carlo["profile"]:
        assert lo3 <= row["att"] <= hi3, row
        assert lo1 <= row["aoa"] <= hi1, row


def test_each_run_flies_its_own_airframe(tactical):
    """A simulated run's truth flies at the angle of attack of its own aircraft: the
    type's lift law with alpha0 and K drawn from the scenario's scatter. Fitting
    ``alpha = alpha0 + K n_w / V^2`` to the truth (the evaluation's angle, the truth's
    own specific force) recovers them exactly, away from the type's values and within
    4 sigma of them."""
    from filters.evaluate import truth_aoa_rad

    scn = load_flight("tactical", SHORT)
    truth = tactical.truth
    idx = np.arange(0, truth.t_s.shape[0], 20)
    alpha = truth_aoa_rad(truth, idx)
    f = truth.f_b_mps2[idx]
    n_w = np.sin(alpha) * f[:, 0] - np.cos(alpha) * f[:, 2]
    u = n_w / np.sum(truth.vel_ned_mps[idx] ** 2, axis=1)
    (alpha0, k), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(u), u]), alpha, rcond=None)
    assert np.abs(alpha0 + k * u - alpha).max() < 1e-9
    s_a, s_k = scn.lift_scatter
    z = ((alpha0 - scn.lift.alpha0_rad) / s_a, (k - scn.lift.k_m) / s_k)
    assert all(1e-6 < abs(v) < 4.0 for v in z), z


def test_airframe_draws_have_the_stated_scatter():
    """``LiftLaw.drawn``: 4000 aircraft, their alpha0 and K deviations' sums of squares
    inside the two-sided 99.9 % chi-square bounds of the stated sigmas."""
    from scipy.stats import chi2

    from ngnav.sim.flight import LiftLaw

    law = LiftLaw(-0.02, 18.0, 40.0)
    rng = np.random.default_rng(5)
    draws = [law.drawn(0.0175, 0.9, rng) for _ in range(4000)]
    lo, hi = chi2.ppf([0.0005, 0.9995], 4000)
    for dev, sigma in (
        ([d.alpha0_rad - law.alpha0_rad for d in draws], 0.0175),
        ([d.k_m - law.k_m for d in draws], 0.9),
    ):
        stat = float(np.sum((np.asarray(dev) / sigma) ** 2))
        assert lo < stat < hi, stat
    assert all(d.liftoff_speed_mps == 40.0 for d in draws)


def test_nees_profile_windows():
    """Window means of a known sequence; a non-positive window is refused by name."""
    t = np.arange(100) * 0.1
    rows = nees_profile(t, {"pos": t.copy()}, 5.0)
    assert [(r["t0_s"], r["t1_s"]) for r in rows] == [(0.0, 5.0), (5.0, 10.0)]
    assert rows[0]["pos"] == pytest.approx(2.45) and rows[1]["pos"] == pytest.approx(7.45)
    with pytest.raises(ValueError, match="profile window"):
        nees_profile(t, {"pos": t}, 0.0)


def test_first_fix_after_an_outage_resets_position_and_velocity(tactical):
    """A 10 s outage: the first fix is not fused through the coast's cross-covariances
    but puts position and velocity on it (antenna lever arm removed, exactly); a
    50 m glitch in that first fix fails the gate and is not adopted."""
    from dataclasses import replace

    from ngnav.geodesy import LocalTangentPlane
    from ngnav.rotation import dcm_from_quat

    fixes, cfg = tactical.fixes, tactical.config
    keep = (fixes.t_s < 30.0) | (fixes.t_s >= 40.0)
    out = fixes.select(keep)
    res = run_filter(tactical.samples, out, cfg)
    assert res.counts["gps resets after an outage"] == 1
    m = int(np.flatnonzero(out.t_s >= 40.0)[0])
    est = res.estimates
    e = int(np.flatnonzero(np.isclose(est.t_s, out.t_s[m], atol=1e-9))[0])
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    antenna = ltp.to_ned(out.lat_deg[m : m + 1], out.lon_deg[m : m + 1], out.alt_m[m : m + 1])[0]
    c = dcm_from_quat(est.q_nb[e])
    # the fix is time-tagged within half a sample of the epoch: allow v * dt
    assert np.allclose(
        est.pos_ned_m[e] + c @ cfg.antenna_b_m,
        antenna,
        atol=np.abs(est.vel_ned_mps[e]).max() * 5e-3,
    )
    assert np.allclose(
        est.cov_nav[e][0:3, 0:3], np.diag([out.h_acc_m[m]] * 2 + [out.v_acc_m[m]]) ** 2
    )
    err = run_errors(est, tactical.truth)
    z = np.abs(err.pos_ned_m) / np.sqrt(np.diagonal(est.cov_nav[:, 0:3, 0:3], axis1=1, axis2=2))
    after = err.t_s >= 40.0
    assert z[after].max() < 4.5  # over 4000 epochs x 3 axes of a consistent filter
    # a glitched first fix after the outage fails the gate: no reset to it
    lat = out.lat_deg.copy()
    lat[m] += 50.0 / 111_000.0
    res2 = run_filter(tactical.samples, replace(out, lat_deg=lat), cfg)
    i = int(np.flatnonzero(np.isclose(res2.innovations.t_s, out.t_s[m]))[0])
    assert not res2.innovations.pos_accepted[i]
    assert res2.counts["gps resets after an outage"] == 1  # the next, good, fix
    err2 = run_errors(res2.estimates, tactical.truth)
    assert np.linalg.norm(err2.pos_ned_m[e, :2]) < 10.0


def test_fixes_that_keep_failing_the_gate_after_an_outage_reset_on_the_third(tactical):
    """After an outage, fixes that all disagree with the coast (here every fix from then on
    50 m north: the coast looks 50 m off) are not a glitch: the first two are rejected,
    the third (GAP_RESET_AFTER_REJECTS) puts position and velocity on the fix, and the
    fixes after it are fused normally."""
    from dataclasses import replace

    from filters.supervision import GAP_RESET_AFTER_REJECTS

    fixes, cfg = tactical.fixes, tactical.config
    out = fixes.select((fixes.t_s < 30.0) | (fixes.t_s >= 40.0))
    lat = out.lat_deg.copy()
    lat[out.t_s >= 40.0] += 50.0 / 111_000.0
    res = run_filter(tactical.samples, replace(out, lat_deg=lat), cfg)
    inn = res.innovations
    first = int(np.flatnonzero(inn.t_s >= 40.0)[0])
    n = GAP_RESET_AFTER_REJECTS
    assert n == 3
    assert not inn.pos_accepted[first : first + n - 1].any()
    assert inn.pos_accepted[first + n - 1 : first + n + 10].all()
    assert res.counts["gps resets after an outage"] == 1
    assert res.counts["gps resets after rejections"] == 0


def test_a_long_gap_of_held_samples_widens_the_covariance(tactical, monkeypatch):
    """0.5 s of lost array samples in a 2 g turn: the forecast stands in, and the
    covariance grows with its error (``filters.forecast.HOLD_*``), so the attitude stays
    consistent."""
    from dataclasses import replace

    from scipy.stats import chi2

    import filters.step
    from ngnav.settings import VehicleSettings

    sim = tactical
    acc = sim.samples.accel_mps2.copy()
    i0 = int(np.searchsorted(sim.samples.t_s, 12.0))
    acc[i0 : i0 + 100] = np.nan
    gap = ArraySamples(sim.samples.t_s, acc)
    ref = run_filter(sim.samples, sim.fixes, sim.config)

    def worst_att_nees(cfg):
        r = run_filter(gap, sim.fixes, cfg)
        e = run_errors(r.estimates, sim.truth)
        m = (e.t_s > 12.0) & (e.t_s < 20.0)
        d = e.stacked()[m][:, 6:9]
        p = r.estimates.cov_nav[m][:, 6:9, 6:9]
        return float(np.einsum("ei,eij,ej->e", d, np.linalg.inv(p), d).max()), r

    worst, res = worst_att_nees(sim.config)
    assert res.counts["samples held (non-finite)"] == 100
    assert worst < chi2.ppf(0.999, 3)
    assert (
        res.counts["gps positions rejected (gate)"] == ref.counts["gps positions rejected (gate)"]
    )
    # the same gap without the hold model: the filter turns grossly overconfident
    # (measured: worst attitude NEES 12 899 and 11 GPS velocities rejected; 9.8 and
    # one with it)
    free = replace(sim.config, vehicle=VehicleSettings())
    worst_nm, _ = worst_att_nees(free)
    with monkeypatch.context() as mp:
        mp.setattr(filters.step, "HOLD_WDOT_SIGMA_RPS2", 0.0)
        mp.setattr(filters.step, "HOLD_FORCE_SIGMA_MPS2", 0.0)
        worst_off, res_off = worst_att_nees(sim.config)
        worst_none, res_none = worst_att_nees(free)
    assert worst_off > 100 * chi2.ppf(0.999, 3)
    assert res_off.counts["gps velocities rejected (gate)"] > 0
    # without the vehicle model (sideslip and angle of attack) the hold model alone keeps
    # the attitude consistent through the gap (measured worst 10.6); without both the
    # filter is grossly overconfident (measured: worst 2 133, 13 velocities rejected, one
    # tilt reopen; on the draws before 9e531ec it lost its tilt twice)
    assert worst_nm < chi2.ppf(0.999, 3)
    assert worst_none > 100 * chi2.ppf(0.999, 3)
    assert res_none.counts["gps velocities rejected (gate)"] > 0


def test_a_lost_tilt_is_reopened_and_relearned_from_gps_velocity(tactical):
    """A hand-over whose pitch is 15 deg off but told as 1 deg: the velocity it
    predicts fails every GPS gate, and without the fallback nothing could correct
    it. After 10 rejected velocities the filter puts position and velocity on the
    fix and adds tilt and rate variance back (``NavFilter.reopen_attitude``); the
    next fixes relearn the tilt, and from then on it is inside its covariance.
    It also needs the vehicle model's pause while velocities are rejected
    (``MODEL_PAUSE_AFTER_VELOCITY_REJECTS``): without it an angle-of-attack update
    fused through the wrong covariance put the pitch rate 21 deg/s off and the
    filter lost its tilt again 1.6 s after the reopen."""
    from dataclasses import replace

    cfg = tactical.config
    bad = replace(cfg, initial=replace(cfg.initial, pitch_deg=cfg.initial.pitch_deg + 15.0))
    res = run_filter(tactical.samples, tactical.fixes, bad)
    assert res.counts["attitude reopened after rejected velocities"] >= 1
    est = res.estimates
    err = run_errors(est, tactical.truth)
    assert np.rad2deg(np.linalg.norm(err.att_ned_rad[0, 0:2])) > 10.0  # it did start lost
    late = est.t_s >= 10.0
    tilt_sd = np.sqrt(np.diagonal(est.cov_nav[:, 6:8, 6:8], axis1=1, axis2=2))
    tilt_z = np.abs(err.att_ned_rad[:, 0:2]) / tilt_sd
    assert tilt_z[late].max() < 4.5  # every epoch after 10 s, both tilt axes
    ok = run_filter(tactical.samples, tactical.fixes, cfg)
    err_ok = run_errors(ok.estimates, tactical.truth)
    # after 5 s the tilt is as good as that of the same run started right (measured
    # 1.15x its RMS: the reopened variance costs a little information)
    m = est.t_s >= 5.0
    rms = np.sqrt(np.mean(err.att_ned_rad[m, 0:2] ** 2))
    rms_ok = np.sqrt(np.mean(err_ok.att_ned_rad[m, 0:2] ** 2))
    assert rms < 1.25 * rms_ok
    assert ok.counts["attitude reopened after rejected velocities"] == 0  # a good run never


def test_unknown_position_error_is_the_real_array_minus_the_calibrated_one(tactical):
    # the real array's outputs minus those of an array with the real axes at the
    # calibrated positions, through the design matrix (independent of the cross products)
    from ngnav.layout import ArrayLayout

    real = tactical.true_layout()
    dr = tactical.true_errors.position_error_b_m - tactical.config.known_errors.position_error_b_m
    calibrated = ArrayLayout(real.positions_b_m - dr, real.axes_b)
    tr = tactical.truth
    args = (tr.omega_dot_b_rps2, tr.f_b_mps2, tr.omega_b_rps)
    ref = real.outputs(*args) - calibrated.outputs(*args)
    got = tactical.unknown_position_error_mps2()
    assert np.abs(ref).max() > 1e-4  # tactical's turns make the 0.5 mm scatter visible
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def test_a_declared_position_scatter_is_always_carried(tactical):
    """Sensor-position states exactly when the calibration declares their scatter."""
    from dataclasses import replace

    from filters.bench import _first_seconds

    samples, fixes = _first_seconds(tactical.samples, tactical.fixes, 3.0)
    on = run_filter(samples, fixes, tactical.config)
    cfg = replace(tactical.config, position_sigma_m=0.0)
    off = run_filter(samples, fixes, cfg)
    n_dr = 3 * tactical.config.layout.n_sensors
    assert tactical.config.position_sigma_m > 0
    assert on.state_size - off.state_size == n_dr
    assert dict(on.final.state_blocks)["dr"] == n_dr and "dr" not in dict(off.final.state_blocks)
    assert np.all(np.isfinite(off.estimates.pos_ned_m))


def test_first_epoch_angle_of_attack_takes_the_lift_law_at_the_seed_load():
    """The first estimate (before any block) is the lift law at the seed sample's load:
    over 100 one-second ``tactical`` hand-overs its error against the truth's angle is
    chi-square with 100 dof within the 0.001 / 0.999 quantiles. Without a load the law
    gives its offset alone, 2.5-3.5 deg (K u at 1 g, 60 m/s) off: the sum was 882."""
    scn = load_flight(
        "tactical",
        ["run.rate_hz=200", "flight.legs=[{ duration_s = 1.0, ramp_s = 0.5, bank_deg = 0.0 }]"],
    )
    z = []
    for i in range(100):
        sim = simulate_flight(scn, i)
        est = run_filter(sim.samples, sim.fixes, sim.config).estimates
        alpha = truth_aoa_rad(sim.truth, truth_indices(sim.truth, est.t_s[:1]))[0]
        z.append((alpha - est.aoa_rad[0]) / est.aoa_sigma_rad[0])
    lo, hi = chi2.ppf([0.001, 0.999], 100)
    assert lo < float(np.sum(np.square(z))) < hi


def test_bias_states_tell_the_truth_through_the_forecasts_loop():
    """The bias states against their truth, the channel biases seen through the solve.

    ``tactical`` learns its biases in flight after the hand-over (no static alignment),
    through the GM(1,1) forecast's loop, which returns the estimates' own error
    (``FilterNoise.bias_effect``). 24 runs to 4 s: the angular-acceleration and force
    bias states' NEES (6 dof), averaged over the runs, inside the 24-run chi-square
    bounds (0.5 % each side, [4.34, 7.98]) at 2, 3 and 4 s; it reads 7.27 / 6.67 / 7.38.
    The filter that took its states as ``T S b`` with the identity as their effect read
    8.32 / 8.03 / 9.17 against ``S b``, where its estimates converged (and far more
    against its own ``T S b``), and fails.
    """
    from filters.pipeline import Pipeline

    scn = load_flight("tactical")
    t_end, checks = 4.0, (2.0, 3.0, 4.0)
    runs = 24
    nees = np.zeros((runs, len(checks)))
    for i in range(runs):
        sim = simulate_flight(scn, i)
        t = sim.samples.t_s
        keep = t <= t_end + 0.2
        samples = ArraySamples(t[keep], sim.samples.accel_mps2[keep])
        fixes = sim.fixes.select(sim.fixes.t_s <= t_end)
        pipe = Pipeline(sim.config, dt_s=float(np.median(np.diff(t))))
        got = {}

        def record(p, bias=sim.channel_bias_mps2, t=t, got=got):
            nf = p.nf
            for j, tc in enumerate(checks):
                if j not in got and nf.t_s >= tc:
                    k = int(np.searchsorted(t, nf.t_s))
                    err = (p.solver.solve_matrix @ bias[k] - nf.bias)[0:6]
                    cov = nf.P[nf.layout.bias, nf.layout.bias][0:6, 0:6]
                    got[j] = float(err @ np.linalg.solve(cov, err))

        pipe.on_epoch = lambda _est, pipe=pipe, record=record: record(pipe)
        pipe.replay(samples, fixes)
        nees[i] = [got[j] for j in range(len(checks))]
    lo, hi = chi2.ppf([0.005, 0.995], 6 * runs) / runs
    mean = nees.mean(axis=0)
    assert np.all((mean > lo) & (mean < hi)), (mean, lo, hi)


def test_an_as_built_geometry_is_a_layout_like_any_other(tactical):
    """The calibrated cube given as measured positions and axes (no separate errors) solves
    the rate products, leaves its faint rate squares to the compensation, and flies as
    the nominal layout plus the same known errors does."""
    from dataclasses import replace

    from ngnav.frontend import ArraySolver
    from ngnav.mounting import MountingErrors

    cfg = tactical.config
    built = cfg.known_errors.real_layout(cfg.layout)
    solver = ArraySolver(built, cfg.noise_sigma_mps2)
    assert solver.solved_features[6:] == ("wy*wz", "wx*wz", "wx*wy")
    assert solver.aided_columns.tolist() == [6, 7, 8]  # the squares: 9 outputs, 12 terms
    as_built = replace(cfg, layout=built, known_errors=MountingErrors.zeros(built.n_sensors))
    ref = summarise(run_errors(run_filter(tactical.samples, tactical.fixes, cfg).estimates,
                               tactical.truth))  # fmt: skip
    got = summarise(
        run_errors(run_filter(tactical.samples, tactical.fixes, as_built).estimates, tactical.truth)
    )
    for name in ("horiz_rms_m", "roll_rms_deg", "pitch_rms_deg", "yaw_rms_deg", "rate_rms_dps"):
        assert getattr(got, name) == pytest.approx(getattr(ref, name), rel=0.02), name


def test_a_layout_without_the_rate_products_is_refused_naming_them(tactical):
    from dataclasses import replace

    from ngnav.layout import six_accelerometer_cube
    from ngnav.mounting import MountingErrors

    six = six_accelerometer_cube()
    cfg = replace(
        tactical.config,
        layout=six,
        known_errors=MountingErrors.zeros(6),
        scale=np.ones(6),
        offset_mps2=np.zeros(6),
        noise_sigma_mps2=tactical.config.noise_sigma_mps2[:6],
        turn_on_bias_mps2=tactical.config.turn_on_bias_mps2[:6],
        scale_sigma=0.0,
        axis_error_sigma_rad=0.0,
        bias_rw_mps2_rts=tactical.config.bias_rw_mps2_rts[:6],
    )
    samples = ArraySamples(tactical.samples.t_s, tactical.samples.accel_mps2[:, :6])
    with pytest.raises(ValueError, match=r"cannot solve the rate product wy\*wz, wx\*wz, wx\*wy"):
        run_filter(samples, tactical.fixes, cfg)
