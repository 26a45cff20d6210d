"""The consistent filter's share inside the bounds, against its exact limits."""

import json

import numpy as np
import pytest
from scipy.stats import binom

from filters.evaluate import chi2_bounds
from studies.share_reference import consistent_share, statistic_autocorrelation
from tests.helpers import SHORT_TACTICAL_ARGS, run_study


def test_independent_epochs_give_the_binomial_share():
    """Epochs independent in time: each is inside with probability 0.95, so the share
    is Binomial(E, 0.95) / E exactly; its median and 5th percentile (2000 epochs:
    0.950 and 0.942) come back within a few replicas' resolution."""
    rng = np.random.default_rng(3)
    per_run = rng.chisquare(3, (20, 2000))
    ref = consistent_share(per_run, 3)
    assert ref.corr_time_epochs == 1.0
    assert ref.median == pytest.approx(binom.median(2000, 0.95) / 2000, abs=0.003)
    assert ref.p05 == pytest.approx(binom.ppf(0.05, 2000, 0.95) / 2000, abs=0.003)
    assert ref.prob_below_90 == 0.0


def test_a_statistic_constant_in_time_is_all_in_or_all_out():
    """Each run's statistic constant over the flight: a run set's average is one
    chi-square draw, inside on every epoch or on none, so a share below 90 % has
    probability exactly 0.05; 400 replicas' count lies inside its two-sided 99.9 %
    binomial bounds."""
    rng = np.random.default_rng(4)
    per_run = np.repeat(rng.chisquare(3, (20, 1)) + rng.normal(0, 0.01, (20, 1)), 300, axis=1)
    ref = consistent_share(per_run, 3, replicas=400)
    assert ref.corr_time_epochs == 300.0
    lo, hi = binom.ppf([0.0005, 0.9995], 400, 0.05)
    assert lo <= ref.prob_below_90 * 400 <= hi
    assert ref.median == 1.0


def _ar1_chi2(rng, runs, dim, n, phi):
    """Per-run chi-square(dim) processes: sums of dim squared unit AR(1) processes."""
    g = np.empty((runs, dim, n))
    g[..., 0] = rng.standard_normal((runs, dim))
    e = rng.standard_normal((runs, dim, n)) * np.sqrt(1 - phi * phi)
    for k in range(1, n):
        g[..., k] = phi * g[..., k - 1] + e[..., k]
    return (g**2).sum(axis=1)


def test_matches_a_directly_simulated_correlated_statistic():
    """Where its assumptions hold exactly (stationary, equal components: squared AR(1)
    processes, phi 0.99 per epoch), the reference built from one run set's measured
    correlation gives the share distribution of many run sets drawn from the generator
    itself: the fraction below 90 % within 3 standard errors of the two estimates
    (measured: 0.06 direct, 0.07 from the reference), the medians (95.4 %, 95.5 %)
    within 1 point and the 5th percentiles (89.1 %, 89.3 %) within 2."""
    rng = np.random.default_rng(5)
    runs, dim, n, phi = 10, 3, 1500, 0.99
    lo, hi = chi2_bounds(dim, runs)
    direct = []
    for _ in range(300):
        avg = _ar1_chi2(rng, runs, dim, n, phi).mean(axis=0)
        direct.append(np.mean((avg >= lo) & (avg <= hi)))
    direct = np.array(direct)
    p_direct = np.mean(direct < 0.9)
    ref = consistent_share(_ar1_chi2(rng, 40, dim, n, phi), dim, replicas=300)
    se = np.sqrt(
        p_direct * (1 - p_direct) / 300 + ref.prob_below_90 * (1 - ref.prob_below_90) / 300
    )
    assert abs(ref.prob_below_90 - p_direct) < 3 * se, (ref, p_direct)
    assert ref.median == pytest.approx(np.median(direct), abs=0.01)
    assert ref.p05 == pytest.approx(np.percentile(direct, 5), abs=0.02)
    # the correlation of squared AR(1) processes is phi^(2 lag): 1/e at lag 50
    assert ref.corr_time_epochs == pytest.approx(1 / (2 * (1 - phi)), rel=0.2)


def test_autocorrelation_leaves_out_missing_epochs_and_rejects_bad_shapes():
    rng = np.random.default_rng(6)
    q = rng.chisquare(1, (8, 400))
    q[:, 100:150] = np.nan
    rho = statistic_autocorrelation(q)
    assert rho[0] == 1.0 and np.all(np.isfinite(rho))
    assert np.abs(rho[1:50]).max() < 0.2
    with pytest.raises(ValueError, match="runs >= 2"):
        statistic_autocorrelation(q[:1])
    with pytest.raises(ValueError, match="does not vary"):
        statistic_autocorrelation(np.ones((4, 10)))
    with pytest.raises(ValueError, match="dim and replicas"):
        consistent_share(q, 0)


def test_cli_prints_the_reference_beside_each_block():
    """``python -m studies.consistency --reference`` as a real subprocess: every block,
    the control's too, carries the consistent filter's share, a median at or above its
    5th percentile."""
    proc = run_study(
        "consistency",
        *SHORT_TACTICAL_ARGS,
        "--runs",
        "2",
        "--workers",
        "1",
        "--reference",
        "--json",
    )
    out = json.loads(proc.stdout)
    for name, b in {**out["blocks"], **out["control"]}.items():
        ref = b["consistent_share"]
        assert 0.0 <= ref["p05"] <= ref["median"] <= 1.0, name
        assert 0.0 <= ref["prob_below_90"] <= 1.0 and ref["replicas"] == 200, name
