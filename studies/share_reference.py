"""What share of epochs inside the 95 % bounds a consistent filter would reach.

The consistency criterion (:func:`filters.evaluate.share_inside`) counts the
epochs whose run-averaged NEES or NIS lies inside its two-sided 95 % chi-square
bounds. For a filter consistent by construction each epoch is inside with
probability 0.95, so the share's mean is 95 %; but its spread depends on how
strongly the statistic is correlated in time. Independent epochs give a
binomial share, tightly about 95 %; a statistic that stays put for seconds (a
position error held by GPS averaging) makes many epochs fall outside together,
and a share below 90 % then happens to consistent filters too.

:func:`consistent_share` measures that spread for a given run set: it takes the
per-run statistic's autocorrelation in time from the runs themselves, builds
chi-square processes with it (``dim`` Gaussian processes squared and summed per
run, independent runs), averages them over the same number of runs, and counts
the share inside the same bounds, over many replicas. Assumptions, all
approximations: the correlation is the same at every epoch (stationary; a
flight's phases differ) and for every component of the block; the Gaussian
components' correlation is the square root of the statistic's (exact for
squares of Gaussians); the autocorrelation is cut at its first zero crossing
(its tail is estimation noise). Exact in both limits: independent epochs give
the binomial share, a statistic constant in time gives 0 or 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from filters.evaluate import TARGET_SHARE, chi2_bounds

#: Replicas of the consistent run set per block (the percentiles' resolution).
DEFAULT_REPLICAS = 200
#: Seed of the replicas: the reference is reproducible.
DEFAULT_SEED = 2026


@dataclass(frozen=True)
class ShareReference:
    """Share of epochs inside the bounds for a consistent filter, over replicas.

    Attributes
    ----------
    median, p05 : float
        Median and 5th percentile of the share (0-1).
    prob_below_90 : float
        Share of replicas below 0.9 (the issue's threshold).
    corr_time_epochs : float
        Lag (epochs) at which the statistic's autocorrelation falls below 1/e.
    replicas : int
        Replicas drawn.
    """

    median: float
    p05: float
    prob_below_90: float
    corr_time_epochs: float
    replicas: int


def statistic_autocorrelation(per_run: np.ndarray) -> np.ndarray:
    """Autocorrelation (E,) in time of a per-run statistic (R, E), lag 0 first.

    Each epoch is standardised across runs (its mean and spread over the runs
    removed), so the flight's phases do not read as correlation. Each lag's
    products are averaged over the pairs of finite epochs it has in all runs
    (the unbiased estimate; NaN epochs are left out). 1 at lag 0.
    """
    q = np.asarray(per_run, dtype=float)
    if q.ndim != 2 or q.shape[0] < 2 or q.shape[1] < 2:
        raise ValueError(f"per_run must be (runs >= 2, epochs >= 2), got shape {q.shape}")
    fin = np.isfinite(q)
    cnt = fin.sum(axis=0)
    x = np.where(fin, q, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu = x.sum(axis=0) / cnt
        sd = np.sqrt(np.where(fin, (x - mu) ** 2, 0.0).sum(axis=0) / (cnt - 1))
        z = (x - mu) / sd
    ok = fin & (cnt >= 2) & (sd > 0)
    z = np.where(ok, z, 0.0)
    n = q.shape[1]

    def lagged_sums(a: np.ndarray) -> np.ndarray:
        f = np.fft.rfft(a, 2 * n, axis=1)
        return np.fft.irfft((f * f.conj()).real.sum(axis=0), 2 * n)[:n]

    # unbiased: each lag's sum over the pairs it has (a constant statistic reads 1 at every lag)
    pairs = np.rint(lagged_sums(ok.astype(float)))
    ac = np.where(pairs > 0, lagged_sums(z) / np.maximum(pairs, 1.0), 0.0)
    if ac[0] <= 0:
        raise ValueError("the statistic does not vary across runs; no autocorrelation")
    return ac / ac[0]


def consistent_share(
    per_run: np.ndarray,
    dim: int,
    replicas: int = DEFAULT_REPLICAS,
    seed: int = DEFAULT_SEED,
) -> ShareReference:
    """The share inside the 95 % bounds a consistent filter reaches on this run set.

    Parameters
    ----------
    per_run : array (R, E)
        The statistic (NEES or NIS of ``dim`` degrees of freedom) of each of R
        runs at E epochs; NaN where a run has none. Only its correlation in time
        is used, and which epochs count (those with a finite run average).
    dim : int
        Degrees of freedom of the statistic.
    replicas : int
        Consistent run sets drawn.
    seed : int
        Seed of the draws (``numpy.random.default_rng``).

    Returns
    -------
    ShareReference
    """
    q = np.asarray(per_run, dtype=float)
    if dim < 1 or replicas < 1:
        raise ValueError(f"dim and replicas must be >= 1, got {dim}, {replicas}")
    rho = statistic_autocorrelation(q)
    runs, n = q.shape
    counted = np.isfinite(q).any(axis=0)
    cut = int(np.argmax(rho <= 0.0)) if np.any(rho <= 0.0) else n
    below = rho < np.exp(-1.0)
    corr_time = float(np.argmax(below)) if np.any(below) else float(n)
    rho_g = np.zeros(n)
    rho_g[:cut] = np.sqrt(rho[:cut])
    # circulant embedding of the Gaussian components' autocorrelation (length 2E - 2:
    # exact for a statistic constant in time, where a longer padded one is not)
    c = np.concatenate([rho_g, rho_g[-2:0:-1]])
    m = c.shape[0]
    amp = np.sqrt(np.clip(np.fft.rfft(c).real, 0.0, None))
    var = float(np.fft.irfft(amp**2, m)[0])  # > 1 where negative eigenvalues were cut
    amp = amp.astype(np.float32)  # single precision: half the memory (tactical's joint 44 -> 39 s)
    lo, hi = chi2_bounds(dim, runs)
    rng = np.random.default_rng(seed)
    shares = np.empty(replicas)
    for k in range(replicas):
        w = rng.standard_normal((runs * dim, m), dtype=np.float32)
        g = np.fft.irfft(np.fft.rfft(w, axis=1) * amp, m, axis=1)[:, :n]
        avg = (g**2).reshape(runs, dim, n).sum(axis=1).mean(axis=0) / var
        a = avg[counted]
        shares[k] = np.mean((a >= lo) & (a <= hi))
    return ShareReference(
        float(np.median(shares)),
        float(np.percentile(shares, 5)),
        float(np.mean(shares < TARGET_SHARE)),
        corr_time,
        replicas,
    )
