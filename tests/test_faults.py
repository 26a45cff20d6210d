"""Channel faults: injected by the simulator, found by the health tests (filters.faults)."""

from __future__ import annotations

import numpy as np
import pytest

from filters.faults import (
    _CHI2_1_MEDIAN,
    FLAT_RUN,
    NOISE_WINDOW,
    NOISY_RATIO,
    ChannelMonitor,
    pair_isolability,
    signature_groups,
)
from ngnav.frontend import ArraySolver
from ngnav.layout import nine_accelerometer_cube, six_accelerometer_cube
from ngnav.sim.faults import ChannelFault, inject_faults, parse_faults
from ngnav.sim.flight_scenario import load_flight

SIGMA = 0.005  # m/s^2 per sample, about mems-tactical at 1 kHz
LSB = 7.7e-5  # its 20-bit step over +-4.096 g
RANGE = 40.17


def _noise(rng, k, n=9, lsb=LSB):
    return np.round(rng.normal(0.0, SIGMA, (k, n)) / lsb) * lsb


def _monitor(n=9):
    return ChannelMonitor(np.full(n, SIGMA), RANGE, np.zeros((3, n)))


def _feed(m, t, a, chunk):
    for i in range(0, t.shape[0], chunk):
        m.observe_samples(t[i : i + chunk], a[i : i + chunk])


# ----------------------------------------------------------------- injection
def test_each_kind_changes_its_channel_from_its_start_and_nothing_else():
    rng = np.random.default_rng(1)
    t = np.arange(1000) * 1e-3
    a = rng.normal(0.0, SIGMA, (1000, 9)) + 3.0
    faults = (
        ChannelFault(1, "dead", 0.5),
        ChannelFault(2, "stuck", 0.5),
        ChannelFault(3, "drift", 0.5, 0.2),
        ChannelFault(4, "noisy", 0.5, 10.0),
        ChannelFault(5, "saturated", 0.5, -1.0),
    )
    out = inject_faults(t, a, faults, SIGMA, RANGE, np.random.default_rng(2))
    on = slice(500, None)
    np.testing.assert_array_equal(out[:500], a[:500])
    np.testing.assert_array_equal(out[:, 5:], a[:, 5:])
    assert np.all(out[on, 0] == 0.0)
    assert np.all(out[on, 1] == a[500, 1])
    np.testing.assert_allclose(out[on, 2] - a[on, 2], 0.2 * (t[on] - t[500]), atol=1e-12)
    extra = out[on, 3] - a[on, 3]
    assert np.std(extra) == pytest.approx(SIGMA * np.sqrt(99.0), rel=0.1)
    assert np.all(out[on, 4] == -RANGE)


def test_a_scenario_faults_section_is_parsed_and_checked():
    scn = load_flight(
        "tactical", ['faults.inject=[{channel=6, kind="drift", start_s=20.0, size=0.01}]']
    )
    assert scn.faults == (ChannelFault(6, "drift", 20.0, 0.01),)
    assert load_flight("tactical").faults == ()
    for table, msg in (
        ({"inject": [{"channel": 6, "kind": "melted", "start_s": 1.0}]}, "melted"),
        ({"inject": [{"channel": 0, "kind": "dead", "start_s": 1.0}]}, "channel"),
        ({"inject": [{"channel": 2, "kind": "drift", "start_s": 1.0}]}, "finite size"),
        ({"inject": [{"channel": 2, "kind": "noisy", "start_s": 1.0, "size": 0.5}]}, "> 1"),
        ({"inject": [{"kind": "dead", "start_s": 1.0}]}, "missing key channel"),
        ({"inject": [{"channel": 2, "kind": "dead", "start_s": 1.0, "when": 2}]}, "when"),
        ({"list": []}, "faults.list"),
    ):
        with pytest.raises(ValueError, match=msg):
            parse_faults(table, "x.toml")
    with pytest.raises(ValueError, match="has 9 channels"):
        load_flight("tactical", ['faults.inject=[{channel=10, kind="dead", start_s=1.0}]'])


# ----------------------------------------------------------------- sample tests
@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_flat_lines_are_found_after_their_run_whatever_the_chunks(chunk):
    rng = np.random.default_rng(3)
    k = 3000
    t = np.arange(k) * 1e-3
    a = _noise(rng, k)
    a[1000:, 1] = 0.0
    a[1500:, 4] = a[1500, 4] + 0.123  # a value no noise sample has
    a[2000:, 8] = RANGE
    m = _monitor()
    _feed(m, t, a, chunk)
    got = {(e.channels, e.kind): (e.detected_at_s, e.isolated_at_s) for e in m.events}
    # the run holds FLAT_RUN equal readings: the alarm is at its last
    assert got[((2,), "dead")] == pytest.approx((t[1000 + FLAT_RUN - 1],) * 2)
    assert got[((5,), "stuck")] == pytest.approx((t[1500 + FLAT_RUN - 1],) * 2)
    # the jump to the rail trips the noise test first; the flat line then names it
    assert ((9,), "saturated") in got
    assert len(m.events) == 3
    assert m.faulty_mask == (1 << 1) | (1 << 4) | (1 << 8)


def test_a_channel_that_moves_again_leaves_the_mask_but_keeps_its_event():
    rng = np.random.default_rng(4)
    t = np.arange(2000) * 1e-3
    a = _noise(rng, 2000)
    a[500:600, 2] = 1.0
    m = _monitor()
    _feed(m, t[:550], a[:550], 10)
    assert m.faulty_mask == 1 << 2
    _feed(m, t[550:], a[550:], 10)
    assert m.faulty_mask == 0
    assert [(e.channels, e.kind) for e in m.events] == [((3,), "stuck")]


def test_a_noisy_channel_is_named_within_two_windows():
    rng = np.random.default_rng(5)
    k = 5 * NOISE_WINDOW
    t = np.arange(k) * 1e-3
    a = _noise(rng, k)
    start = 2 * NOISE_WINDOW + 37
    a[start:, 6] += rng.normal(0.0, SIGMA * np.sqrt(99.0), k - start)
    m = _monitor()
    _feed(m, t, a, 13)
    (ev,) = m.events
    assert ev.channels == (7,) and ev.kind == "noisy"
    assert t[start] < ev.detected_at_s <= t[start] + 2 * NOISE_WINDOW * 1e-3


@pytest.mark.parametrize("lsb", [LSB, SIGMA])
def test_white_noise_stays_far_below_the_noisy_threshold(lsb):
    """200,000 windows of white noise at the configured sigma (quantised at the 20-bit
    step, and at a step as large as the noise): the largest ratio is under half the
    threshold, and no flat line."""
    rng = np.random.default_rng(6)
    worst = 0.0
    for _ in range(20):
        x = _noise(rng, NOISE_WINDOW * 10_000 + 2, n=1, lsb=lsb)[:, 0]
        d2 = x[2:] - 2 * x[1:-1] + x[:-2]
        sq = (d2 * d2).reshape(-1, NOISE_WINDOW)
        worst = max(worst, float(np.max(np.median(sq, axis=1))))
        same = np.flatnonzero(np.diff(x) != 0.0)
        assert np.max(np.diff(same)) < FLAT_RUN
    assert worst / (6 * SIGMA**2 * _CHI2_1_MEDIAN) < NOISY_RATIO / 2


# ----------------------------------------------------------------- parity
def test_the_nine_cube_parity_groups_are_its_angular_acceleration_pairs():
    """With the rate known, A2/A5 alone carry wdot_z, A3/A8 wdot_y, A6/A9 wdot_x (paper
    eq. 26): an offset on either of a pair moves the parity the same way."""
    s = ArraySolver(nine_accelerometer_cube(0.1)).solve_matrix
    assert signature_groups(s[6:]) == [(0,), (1, 4), (2, 7), (3,), (5, 8), (6,)]
    six = ArraySolver(six_accelerometer_cube(0.1), 1.0)
    assert six.solve_matrix.shape[0] == 6  # no rate rows: nothing to group
    assert signature_groups(np.zeros((0, 6))) == []


def test_the_parity_can_name_nine_of_the_nine_cubes_pairs():
    """Two offsets move the innovation in their signatures' plane; on the nine-cube the six
    groups' directions make four coplanar triples, so only the pairs whose plane holds no
    third group can be told apart (checked here by the triple product, not the verdict's
    projection)."""
    s = ArraySolver(nine_accelerometer_cube(0.1)).solve_matrix[6:]
    verdicts = pair_isolability(s)
    assert len(verdicts) == 36
    assert sorted(k for k, v in verdicts.items() if v == "one group") == [(1, 4), (2, 7), (5, 8)]
    groups = signature_groups(s)
    unit = [s[:, g[0]] / np.linalg.norm(s[:, g[0]]) for g in groups]
    group_of = {c: i for i, g in enumerate(groups) for c in g}
    for (i, j), verdict in verdicts.items():
        gi, gj = group_of[i], group_of[j]
        if gi == gj:
            continue
        dets = [abs(np.linalg.det(np.column_stack([unit[gi], unit[gj], unit[g]])))
                for g in range(len(groups)) if g not in (gi, gj)]  # fmt: skip
        assert (verdict == "isolable") == (min(dets) > 0.1), (i, j, verdict, min(dets))
    assert sum(v == "isolable" for v in verdicts.values()) == 9
    # a channel the parity does not see, and a layout with no rate rows
    s0 = s.copy()
    s0[:, 0] = 0.0
    assert pair_isolability(s0)[(0, 3)] == "unseen"
    assert pair_isolability(np.zeros((0, 6)))[(0, 1)] == "unseen"


def test_a_parity_offset_is_found_on_its_group_and_named_when_alone():
    s = ArraySolver(nine_accelerometer_cube(0.1)).solve_matrix[6:]
    cov = np.eye(3) * 0.02**2
    rng = np.random.default_rng(7)
    for channel, named in ((1, (1,)), (9, (6, 9))):
        m = ChannelMonitor(np.full(9, SIGMA), RANGE, s)
        d = np.zeros(9)
        for k in range(400):
            r = rng.normal(0.0, 0.02, 3)
            if k >= 200:
                d[channel - 1] = 0.01  # m/s^2: half a sigma of the innovation per block
                r = r + s @ d
            m.observe_parity(k * 0.01, r, cov)
        (ev,) = m.events
        assert ev.channels == named and ev.kind == "drift"
        assert 2.0 < ev.detected_at_s < 3.0
        assert ev.isolated == (len(named) == 1)


def test_unbiased_innovations_raise_no_parity_alarm():
    s = ArraySolver(nine_accelerometer_cube(0.1)).solve_matrix[6:]
    rng = np.random.default_rng(8)
    cov = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 1.5]]) * 1e-4
    m = ChannelMonitor(np.full(9, SIGMA), RANGE, s)
    chol = np.linalg.cholesky(cov)
    for k in range(100_000):
        m.observe_parity(k * 0.01, chol @ rng.normal(size=3), cov)
    assert m.events == []
    assert np.max(m._cusum) < 15.0


# ----------------------------------------------------------------- the CLI
def test_a_simulated_fault_is_reported_in_the_summary_and_estimates(tmp_path):
    """ngnav simulate with [faults], then ngnav run: the summary names the channel, its
    kind and times, and estimates.csv's faulty_channels marks it from then on."""
    from filters.output import read_estimates_csv
    from tests.helpers import run_cli

    d = tmp_path / "run"
    fault = 'faults.inject=[{channel=4, kind="saturated", start_s=20.0}]'
    run_cli("simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--set", fault,
            "--out", str(d))  # fmt: skip
    out = run_cli("run", str(d)).stdout
    assert "channel faults found 1" in out
    assert "channel fault: channel 4 saturated: detected 20.120 s, isolated 20.120 s" in out
    est = read_estimates_csv(d / "estimates.csv")
    after = est.t_s >= 20.125
    assert np.all(est.faulty_channels[after] == 1 << 3)
    assert np.all(est.faulty_channels[est.t_s < 20.0] == 0)


def test_the_faults_command_reports_latencies_as_json():
    import json

    from tests.helpers import run_cli

    args = ["faults", "--scenario", "tactical", "--set", "run.rate_hz=200", "--runs", "2",
            "--kinds", "stuck,noisy", "--clean-runs", "1", "--workers", "1", "--json"]  # fmt: skip
    out = json.loads(run_cli(*args).stdout)
    stuck = out["kinds"]["stuck"]
    # 25 equal readings at 200 Hz: the 25th comes 120 ms after the first
    assert stuck["detected"] == stuck["isolated_right"] == stuck["kind_right"] == 2
    assert stuck["detection_s"]["worst"] == pytest.approx(0.120, abs=1e-6)
    assert out["kinds"]["noisy"]["isolated_right"] == 2
    assert out["fault_free"]["flights"] == 1 and out["fault_free"]["alarms"] == 0
    bad = run_cli("faults", "--kinds", "melted", check=False)
    assert bad.returncode == 2 and "melted" in bad.stderr


def test_the_faults_command_runs_two_channel_trials():
    """`ngnav faults --pairs`: each trial's pair with the parity's verdict on it; two dead
    channels are each named by their flat lines, whatever the geometry."""
    import json

    from tests.helpers import run_cli

    args = ["faults", "--scenario", "tactical", "--set", "run.rate_hz=200", "--pairs",
            "--runs", "4", "--kinds", "dead", "--workers", "1", "--json"]  # fmt: skip
    out = json.loads(run_cli(*args).stdout)
    # runs 0-3 take A1+A2, A1+A3, A1+A4, A1+A5: ambiguous, ambiguous, isolable, ambiguous
    dead = out["pairs"]["dead"]
    assert dead["ambiguous"]["trials"] == 3 and dead["isolable"]["trials"] == 1
    for r in dead.values():
        assert r["detected"] == r["both_isolated"] == r["trials"]
        assert r["wrong_isolated"] == 0
    assert len(out["verdicts"]["isolable"]) == 9 and "A1+A4" in out["verdicts"]["isolable"]
    bad = run_cli("faults", "--pairs", "--clean-runs", "2", check=False)
    assert bad.returncode == 2 and "--pairs" in bad.stderr


# ----------------------------------------------------------------- exclusion
def test_the_reduced_solve_is_exact_without_any_one_channel():
    """Rigid-body outputs (paper eq. 3) with one channel replaced by garbage: the solve
    without it, its aided terms from the true rate, gives the true features exactly; without
    both of a pair (A2, A5: wdot_z) angular acceleration is lost and it says so."""
    from filters.reduced import reduced_solve
    from ngnav.layout import kinematic_features, rate_quadratics
    from tests.conftest import rigid_body_outputs_direct

    lay = nine_accelerometer_cube(0.1)
    cols = ArraySolver(lay).solved_columns
    rng = np.random.default_rng(9)
    wd, f, w = rng.normal(size=3), rng.normal(size=3) * 5, rng.normal(size=3)
    a = rigid_body_outputs_direct(lay.positions_b_m, lay.axes_b, wd, f, w)
    phi = kinematic_features(wd, f, w)[cols]
    for c in range(9):
        red = reduced_solve(lay, np.ones(9), cols, 1 << c)
        bad = a.copy()
        bad[c] = 1e3
        got = red.solve_matrix @ bad - red.aided_quadratics @ rate_quadratics(w)
        assert red.solved.sum() == 8 and np.all(red.solved[:6])
        np.testing.assert_allclose(got[red.solved], phi[red.solved], atol=1e-11)
    with pytest.raises(ValueError, match="angular acceleration"):
        reduced_solve(lay, np.ones(9), cols, (1 << 1) | (1 << 4))


def test_a_rate_nis_of_fewer_dof_is_judged_on_the_full_dimension():
    from types import SimpleNamespace

    from filters.consistency import _rate_nis_as_full_dim

    rng = np.random.default_rng(10)
    nis = np.concatenate([rng.chisquare(3, 50_000), rng.chisquare(2, 50_000)])
    dof = np.repeat([3, 2], 50_000)
    res = SimpleNamespace(rate_nis=nis, rate_nis_dof=dof, rate_dim=3)
    out = _rate_nis_as_full_dim(res)
    np.testing.assert_array_equal(out[:50_000], nis[:50_000])
    assert np.mean(out[50_000:]) == pytest.approx(3.0, abs=0.05)
    assert np.mean(out[50_000:] > 7.815) == pytest.approx(0.05, abs=0.005)  # chi2(3) 95 %


def test_a_drifts_cost_is_measured_against_the_same_run_without_it():
    """The drift's cost at detection is the faulted estimate against the fault-free one of
    the same run (the same noise): zero before the fault, and within the issue's 3 sigma
    at detection on this run."""
    from dataclasses import replace

    from filters.fault_trials import attitude_cost_sigmas, fault_trial
    from filters.pipeline import run_filter
    from ngnav.sim.simulate import simulate_flight

    scn = load_flight("tactical", ["run.rate_hz=200"])
    fault = ChannelFault(3, "drift", 20.0, 0.0098)
    est = {}
    for name, faults in (("faulted", (fault,)), ("clean", ())):
        sim = simulate_flight(replace(scn, faults=faults), 0)
        est[name] = run_filter(sim.samples, sim.fixes, sim.config, truth=sim.truth).estimates
    t_fault = sim.truth.t_s[0] + 20.0
    before = float(est["faulted"].t_s[est["faulted"].t_s < t_fault][-1])
    assert attitude_cost_sigmas(est["faulted"], est["clean"], sim.truth, before) == 0.0
    later = float(est["faulted"].t_s[est["faulted"].t_s > t_fault + 3.0][0])
    assert attitude_cost_sigmas(est["faulted"], est["clean"], sim.truth, later) > 0.1
    out = fault_trial(scn, 0, fault, 10.0)
    assert np.isfinite(out.detected_s) and out.detected_s < 1.0
    assert 0.0 < out.attitude_cost_sigmas <= 3.0
