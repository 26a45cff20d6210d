"""The consistency study (``python -m studies.consistency``): ``--sets`` (disjoint run sets,
each judged as the target judges one), ``--cycle`` and ``--tails``."""

import json

import numpy as np
import pytest

from filters.evaluate import chi2_bounds
from studies.consistency import consistency_study, nees_cycle, nees_tails, set_shares
from tests.helpers import SHORT_TACTICAL_ARGS, run_study


def _result(run: int, pos_nees: np.ndarray) -> dict:
    """The parts of one Monte Carlo run's record that the share counts read."""
    n = pos_nees.shape[0]
    t = np.arange(n, dtype=float)
    return {
        "run": run,
        "nees": {"pos": pos_nees},
        "t_s": t,
        "nis_pos": np.full(n, 3.0),
        "nis_vel": np.full(n, 3.0),
        "t_fix_s": t,
        "rate_dim": 0,
        "control_pos": np.full(n, 3.0),
        "control_vel": np.full(n, 3.0),
        "control_pos-pn": np.full(n, 3.0),
        "control_vel-pn": np.full(n, 3.0),
        "control_t_s": t,
    }


def test_each_set_is_judged_on_its_own_runs_and_bounds():
    """Runs 0-2 sit at the statistic's mean (every epoch inside), runs 3-5 at ten
    times it in the first half of the epochs: set 1 is inside on half its epochs, set
    0 on all; a diverged run (5, absent) leaves set 1 with two runs, judged against
    the two-run bounds. Set membership follows the run index, not list order."""
    n = 40
    high = np.where(np.arange(n) < n // 2, 30.0, 3.0)
    results = [_result(4, high), _result(0, np.full(n, 3.0)), _result(3, high)]
    results += [_result(1, np.full(n, 3.0)), _result(2, np.full(n, 3.0))]
    rows = set_shares(results, {"pos": 3}, per_set=3, sets=3)
    assert [r["first_run"] for r in rows] == [0, 3, 6]
    assert [r["runs"] for r in rows] == [3, 2, 0]
    assert [r["last_run"] for r in rows] == [2, 5, 8]
    assert rows[0]["share_inside"]["NEES pos"] == 1.0
    assert 30.0 > chi2_bounds(3, 2)[1]
    assert rows[1]["share_inside"]["NEES pos"] == 0.5
    assert rows[0]["share_inside"]["NIS gps pos"] == 1.0
    assert rows[1]["control_share_inside"] == {"pos": 1.0, "vel": 1.0, "pos-pn": 1.0, "vel-pn": 1.0}
    for r in results:  # runs without the process-noise control: the perfect-array one alone
        del r["control_pos-pn"], r["control_vel-pn"]
    rows = set_shares(results, {"pos": 3}, per_set=3, sets=3)
    assert rows[1]["control_share_inside"] == {"pos": 1.0, "vel": 1.0}
    assert "share_inside" not in rows[2]


def test_sets_must_be_positive():
    from ngnav.sim.flight_scenario import load_flight

    with pytest.raises(ValueError, match="sets must be at least 1"):
        consistency_study(load_flight("tactical"), runs=1, sets=0)
    proc = run_study("consistency", "--scenario", "tactical", "--sets", "0", check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "studies.consistency: error: sets must be at least 1, got 0"


def test_cli_sets_repeat_a_single_set_exactly():
    """``python -m studies.consistency --runs 1 --sets 2`` as a real subprocess: set 0 is run 0,
    so its shares (the control's too) equal those of ``--runs 1`` (run 0 alone) to the
    last digit; set 1 is run 1; ``blocks`` then average both runs."""
    args = ("consistency", *SHORT_TACTICAL_ARGS, "--workers", "1", "--json")
    one = json.loads(run_study(*args, "--runs", "1").stdout)
    two = json.loads(run_study(*args, "--runs", "1", "--sets", "2").stdout)
    assert two["runs"] == 2 and one["runs"] == 1
    s0, s1 = two["sets"]
    assert (s0["first_run"], s0["runs"], s1["first_run"], s1["runs"]) == (0, 1, 1, 1)
    assert s0["share_inside"] == {k: v["share_inside"] for k, v in one["blocks"].items()}
    assert s0["control_share_inside"] == {k: v["share_inside"] for k, v in one["control"].items()}
    assert s1["share_inside"] != s0["share_inside"]
    meeting = sum(all(v >= 0.9 for v in s["share_inside"].values()) for s in two["sets"])
    assert two["sets_meeting_target"] == meeting
    for out in (one, two):  # the verdict names exactly the blocks under 90 %
        under = {k: v["share_inside"] for k, v in out["blocks"].items() if v["share_inside"] < 0.9}
        assert out["target"] == {"share": 0.9, "met": not under, "misses": under}
    assert two["blocks"]["NEES all"]["lower"] == pytest.approx(chi2_bounds(12, 2)[0])


def test_nees_cycle_phases():
    """Phase means and shares of a sequence built with a known dip at one phase of a
    0.2 s cycle on a 0.01 s grid; a cycle off the grid or non-positive is refused."""
    t = 3.0 + np.arange(2000) * 0.01
    k = np.arange(2000) % 20
    rng = np.random.default_rng(5)
    joint = 12.0 + rng.uniform(-0.5, 0.5, 2000)
    joint[k == 1] = 9.0  # below the lower bound at phase 1 only
    joint[(k == 7) & (np.arange(2000) % 40 == 7)] = 14.0  # above on half of phase 7
    rows = nees_cycle(t, {"all": joint, "pos": k.astype(float)}, 0.2, {"all": (10.7, 13.4)})
    assert len(rows) == 20
    assert [r["phase_s"] for r in rows] == pytest.approx(np.arange(20) * 0.01)
    assert [r["pos"] for r in rows] == pytest.approx(np.arange(20))  # each phase its own
    assert rows[1]["all"] == pytest.approx(9.0) and rows[1]["all_below"] == 1.0
    assert rows[7]["all_above"] == pytest.approx(0.5) and rows[7]["all_below"] == 0.0
    others = [r for i, r in enumerate(rows) if i not in (1, 7)]
    assert all(r["all_below"] == 0.0 and r["all_above"] == 0.0 for r in others)
    assert np.mean([r["all"] for r in others]) == pytest.approx(12.0, abs=0.05)
    with pytest.raises(ValueError, match="whole number"):
        nees_cycle(t, {"all": joint}, 0.215, {})
    with pytest.raises(ValueError, match="cycle must be"):
        nees_cycle(t, {"all": joint}, -0.2, {})


def test_cli_cycle_profile():
    """``python -m studies.consistency --cycle 0.2`` as a real subprocess: twenty phases of the
    filter's 0.01 s epochs, whose epoch-weighted means give back each block's mean,
    with the joint's shares below and above; the text report prints one row per
    phase; a cycle off the epoch grid fails with the reason."""
    base = ("consistency", *SHORT_TACTICAL_ARGS, "--workers", "1", "--runs", "1")
    out = json.loads(run_study(*base, "--cycle", "0.2", "--json").stdout)
    rows = out["cycle"]
    assert [r["phase_s"] for r in rows] == pytest.approx(np.arange(20) * 0.01)
    # epochs 0 .. E-1 fall on phase e mod 20: the first E mod 20 phases hold one more
    n_epochs = round(60.0 / 0.01) + 1
    counts = np.full(20, n_epochs // 20)
    counts[: n_epochs % 20] += 1
    for name in ("pos", "vel", "att", "rate", "all"):
        phase_means = np.array([r[name] for r in rows])
        mean = out["blocks"][f"NEES {name}"]["mean"]
        assert np.sum(counts * phase_means) / counts.sum() == pytest.approx(mean, rel=1e-5)
    assert all(0.0 <= r["all_below"] <= 1.0 and 0.0 <= r["all_above"] <= 1.0 for r in rows)
    text = run_study(*base, "--cycle", "0.2").stdout
    assert "by phase in the cycle" in text
    verdict = next(line for line in text.splitlines() if line.startswith("  target ("))
    missed = [k for k, v in out["blocks"].items() if v["share_inside"] < 0.9]
    assert verdict.endswith("met") == (not missed)
    assert all(f"{k} {100 * out['blocks'][k]['share_inside']:.1f} %" in verdict for k in missed)
    assert sum(line.startswith("      0.") for line in text.splitlines()) >= 20
    bad = run_study(*base, "--cycle", "0.215", check=False)
    assert bad.returncode != 0 and "whole number" in bad.stderr


def test_tails_tell_a_scale_error_from_a_heavy_tail():
    """``nees_tails`` on draws whose law is known. Chi-square draws (12 dof) read 1 in
    every ratio; the same draws scaled by 0.8 read 0.8 in each (a scale error); a
    mixture of 95 % scaled by 0.8 and 5 % by 4 (mean 0.96: an average NEES that looks
    nearly right) reads a median below 1 and a 0.99 quantile and variance far above.
    Tolerances are the ratios' sampling error on 40 000 draws (the median's about
    0.5 %, the 0.99 quantile's about 2 %, the variance's about 3 %), widened 3-4 times."""
    from scipy.stats import chi2

    rng = np.random.default_rng([2026, 7])
    runs, epochs = 200, 400
    t = np.arange(epochs) * 0.05  # two 10 s windows of 200 epochs each
    x = rng.chisquare(12, (runs, epochs))

    def ratios(v: np.ndarray) -> list[dict]:
        rows = nees_tails(t, v, 12, 10.0)
        assert [(r["t0_s"], r["t1_s"], r["n"]) for r in rows] == [(0, 10, 40000), (10, 20, 40000)]
        return rows

    for r in ratios(x):
        for key, tol in (("mean_ratio", 0.02), ("q0.5_ratio", 0.02), ("q0.95_ratio", 0.04)):
            assert r[key] == pytest.approx(1.0, abs=tol), key
        assert r["q0.99_ratio"] == pytest.approx(1.0, abs=0.06)
        assert r["var_ratio"] == pytest.approx(1.0, abs=0.1)
    for r in ratios(0.8 * x):
        for key in ("mean_ratio", "q0.5_ratio", "q0.95_ratio", "q0.99_ratio"):
            assert r[key] == pytest.approx(0.8, abs=0.05), key
        assert r["var_ratio"] == pytest.approx(0.64, abs=0.08)
    tail = rng.random((runs, epochs)) < 0.05
    for r in ratios(np.where(tail, 4.0, 0.8) * x):
        assert r["mean_ratio"] == pytest.approx(0.96, abs=0.03)
        assert r["q0.5_ratio"] < 0.86
        assert r["q0.99_ratio"] > 1.5
        assert r["var_ratio"] > 3.0
    # NaN epochs (no truth) are left out of the pool, not counted as values
    y = x.copy()
    y[:, :100] = np.nan
    assert nees_tails(t, y, 12, 10.0)[0]["n"] == 20000
    assert chi2.ppf(0.5, 12) == pytest.approx(11.34, abs=0.01)
    with pytest.raises(ValueError, match="positive number of seconds"):
        nees_tails(t, x, 12, 0.0)
    with pytest.raises(ValueError, match="per_run must be"):
        nees_tails(t, x[:, :10], 12, 10.0)


def test_cli_tails():
    """``python -m studies.consistency --tails 10`` as a real subprocess: a row per 10 s window for
    every block, each window pooling every run's epochs in it (the 60 s flight's
    0.01 s epochs), its mean ratio equal to the profile's run-averaged mean over the
    block's dof; the text report prints the joint's rows."""
    base = ("consistency", *SHORT_TACTICAL_ARGS, "--workers", "1", "--runs", "2")
    out = json.loads(run_study(*base, "--tails", "10", "--profile", "10", "--json").stdout)
    dims = {"pos": 3, "vel": 3, "att": 3, "rate": 3, "all": 12}
    for name, dim in dims.items():
        rows = out["tails"][name]
        assert [(r["t0_s"], r["t1_s"]) for r in rows] == [
            (p["t0_s"], p["t1_s"]) for p in out["profile"]
        ]
        assert len(rows) == 6
        assert sum(r["n"] for r in rows) == 2 * (round(60.0 / 0.01) + 1)
        for r, p in zip(rows, out["profile"], strict=True):
            assert r["mean_ratio"] * dim == pytest.approx(p[name], rel=1e-5)
    text = run_study(*base, "--tails", "10").stdout
    assert "spread over runs by window" in text
    assert sum(line.startswith("      10.0-") for line in text.splitlines()) == 1
