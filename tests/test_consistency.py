"""``ngnav consistency`` (filters.consistency): the block statistics and the command's report."""

import json

import numpy as np
import pytest

from filters.consistency import summarise_block
from tests.helpers import SHORT_TACTICAL_ARGS, run_cli, run_study


def test_block_mean_carries_its_standard_error_over_runs():
    """``mean_se`` counts each run once: four runs whose statistic is 1, 2, 3 and 4 at
    every epoch (NaN epochs skipped) give std(1..4) / 2, however many epochs."""
    per_run = [np.full(30, v) for v in (1.0, 2.0, 3.0, 4.0)]
    per_run[2][:10] = np.nan
    out, _ = summarise_block(per_run, 3, 4)
    # the mean is over epochs of the run average: 7/3 where run 3 has no value
    assert out["mean"] == pytest.approx((10 * 7 / 3 + 20 * 2.5) / 30)
    assert out["mean_se"] == pytest.approx(np.std([1, 2, 3, 4], ddof=1) / 2, rel=1e-12)
    assert np.isnan(summarise_block(per_run[:1], 3, 1)[0]["mean_se"])


def test_nees_is_exact_where_the_covariance_is_and_nan_where_it_is_not():
    """The NEES is ``e^T P^-1 e`` per block at every epoch whose block is positive definite
    (units of very different sizes included); an epoch a failing filter recorded with a
    singular or non-finite covariance has no statistic, and the others are kept."""
    from filters.evaluate import RunErrors, nees

    rng = np.random.default_rng(4)
    n = 6
    a = rng.normal(size=(n, 12, 12))
    scale = np.array([1e2] * 3 + [1e-1] * 3 + [1e-3] * 3 + [1e-5] * 3)  # m, m/s, rad, rad/s
    cov = (a @ a.transpose(0, 2, 1) + 0.1 * np.eye(12)) * np.outer(scale, scale)
    err = rng.normal(size=(n, 12)) * scale
    cov[2, 6:9, 6:9] = np.outer(scale[6:9], scale[6:9])  # rank one: singular
    cov[4] = np.nan  # a lost track's row
    e = RunErrors(np.arange(n), err[:, 0:3], err[:, 3:6], err[:, 6:9], err[:, 6:9], err[:, 9:12])
    out = nees(e, cov)
    blocks = {"pos": slice(0, 3), "vel": slice(3, 6), "att": slice(6, 9), "rate": slice(9, 12)}
    for name, sl in {**blocks, "all": slice(0, 12)}.items():
        for k in range(n):
            if k == 4 or (k == 2 and name in ("att", "all")):
                assert np.isnan(out[name][k])
            else:
                want = err[k, sl] @ np.linalg.solve(cov[k, sl, sl], err[k, sl])
                assert out[name][k] == pytest.approx(want, rel=1e-9)


def test_cli_reports_the_blocks_the_study_reports_without_its_research():
    """``ngnav consistency --runs 1 --from 10`` and ``python -m studies.consistency``
    with the same options as real subprocesses: the same runs give the same blocks,
    from 10 s too, verdict and attitude RMS, to the last digit; the command carries no
    control, and its text report prints one line per block (twice: whole run and from
    10 s), the verdict and no control row. The study's options are not the command's."""
    args = ("consistency", *SHORT_TACTICAL_ARGS, "--workers", "1", "--runs", "1", "--from", "10")
    user = json.loads(run_cli(*args, "--json").stdout)
    study = json.loads(run_study(*args, "--json").stdout)
    assert "control" not in user and "control_from" not in user
    assert set(study) > set(user)
    for key in user:
        assert user[key] == study[key], key
    text = run_cli(*args).stdout.splitlines()
    assert not any("control" in line for line in text)
    for name, b in user["blocks"].items():
        rows = [line for line in text if line.startswith(f"  {name:14s} dim")]
        assert len(rows) == 2, name
        assert f"inside {100 * b['share_inside']:5.1f} % of epochs" in rows[0]
        assert f"mean {b['mean']:7.2f}" in rows[0]
    assert "  from 10 s on:" in text
    assert sum(line.startswith("  target (") for line in text) == 1
    for research in ("--reference", "--sets=2", "--tails=10", "--cycle=0.2"):
        proc = run_cli(*args, research, check=False)
        assert proc.returncode == 2 and "unrecognized arguments" in proc.stderr, research


def test_cli_refuses_no_runs_in_one_line():
    proc = run_cli("consistency", *SHORT_TACTICAL_ARGS, "--runs", "0", check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "ngnav consistency: error: runs must be at least 1, got 0"


def test_the_running_summary_equals_the_summary_of_all_runs(tmp_path):
    """Runs summarised as they arrive, out of order and one at a time, give the report of
    all runs held at once; saved runs read back as they were."""
    from filters.consistency import RunningSummary, monte_carlo_runs, summarise_runs
    from ngnav.sim.flight_scenario import load_flight

    scn = load_flight("tactical", ["run.rate_hz=200"])
    results, diverged = monte_carlo_runs(scn, 3, "gm11", workers=1)
    want, want_avg = summarise_runs("s", "gm11", results, diverged, 2.0, 10.0)
    acc = RunningSummary(10.0, tmp_path / "runs")
    for r in reversed(results):
        acc.add(r["run"], r)
    got, got_avg = acc.summary("s", "gm11", 2.0)
    for section in ("blocks", "blocks_from"):
        assert got[section].keys() == want[section].keys()
        for name, block in want[section].items():
            for key, value in block.items():
                assert got[section][name][key] == pytest.approx(value, rel=1e-6, abs=1e-12), (
                    section,
                    name,
                    key,
                )
    assert got["att_rms_deg_median"] == want["att_rms_deg_median"]
    for name, avg in want_avg.items():
        np.testing.assert_allclose(got_avg[name], avg, rtol=1e-6)
    saved = np.load(tmp_path / "runs" / "run_00001.npz")
    np.testing.assert_array_equal(saved["nees_att"], results[1]["nees"]["att"])
    np.testing.assert_array_equal(saved["nis_pos"], results[1]["nis_pos"])
