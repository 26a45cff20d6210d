"""The filter's noise model in the solved-feature space, and the static mean's walk."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.mounting import perpendicular_basis
from ngnav.runconfig import RunConfig


def static_mean_walk_s(dt_s: float, n_samples: int) -> float:
    """The weight (s) of a random walk's spread between its last sample and its mean.

    For ``n_samples`` samples ``dt_s`` apart of a walk with spectral density ``q``
    (per second), ``b_last - mean(b)`` has variance ``q * walk_s`` with
    ``walk_s = dt_s (n - 1)(2 n - 1) / (6 n)``: a third of the span for many samples,
    zero for one. :meth:`NavFilter.update_static_biases` reads its mean with it.
    """
    n = int(n_samples)
    if n < 1 or not dt_s >= 0.0:
        raise ValueError(f"need n_samples >= 1 and dt_s >= 0, got {n_samples}, {dt_s}")
    return float(dt_s) * (n - 1) * (2 * n - 1) / (6.0 * n)


@dataclass(frozen=True)
class FilterNoise:
    """Noise model of the filter, in the solved-feature space.

    Attributes
    ----------
    feature_cov : array (k, k)
        Per-sample covariance of the solved features ``[wdot(3), f(3), quad(nq)]``.
    bias_prior_cov : array (k, k)
        Prior covariance of the feature biases (turn-on bias mapped through S).
    bias_rw_cov : array (k, k)
        Random-walk spectral density of the feature biases, per second.
    position_sigma_m : float
        Prior 1-sigma of each residual sensor-position error (per axis, m);
        0 leaves the ``DR`` block out (see :mod:`filters.state`).
    quad_cross_cov : array (6, nq), optional
        Per-sample covariance of the ``[wdot, f]`` noise with the quadratic terms'
        noise, as solved from the same channel samples (the solve mixes every
        channel into every feature: on the nine-cube the correlations are 0.25 and
        0.5). A block's rate measurement then shares noise with the propagation
        that led to it; :meth:`NavFilter.update_rate` carries that cross-covariance.
        None treats them as independent.
    bias_effect : array (k, k), optional
        What an error of the bias states (true less estimated, the raw feature biases
        ``S b``) leaves in the compensated features the filter propagates and
        measures with. A forecast compensation feeds its own history back, and that
        history holds the block means less the bias *estimates*: the estimates'
        error comes back through the loop like the noise does, and over many blocks
        the features carry ``T (S b - b_hat)`` with ``T = [[A, 0], [-E_q A, I]]``,
        ``A = (I + E_6)^-1`` (:func:`filters.pipeline.filter_noise`). The transition's
        bias columns, the rate measurement's and the lift law's force-bias term use
        it. None: the identity (no forecast feedback).
    block_wdot_cov : array (3, 3), optional
        Per-sample covariance of the angular acceleration as one block's own samples
        carry it: the raw solve's. ``feature_cov`` maps the noise through a forecast
        compensation's loop, which holds for errors integrated over many blocks; an
        error that lives one block (the rate while a zero-rate update resets it at
        every block, :attr:`NavFilter.rate_reset_each_block`) sees this one. None:
        ``feature_cov``'s.
    """

    feature_cov: np.ndarray
    bias_prior_cov: np.ndarray
    bias_rw_cov: np.ndarray
    position_sigma_m: float = 0.0
    quad_cross_cov: np.ndarray | None = None
    bias_effect: np.ndarray | None = None
    block_wdot_cov: np.ndarray | None = None
    cal_prior_cov: np.ndarray | None = None


def filter_noise(
    solve_matrix: np.ndarray, cfg: RunConfig, feedback: np.ndarray | None = None
) -> FilterNoise:
    """Feature noise and bias model from the channel model, mapped through the solve.

    Parameters
    ----------
    solve_matrix : array (k, N)
        The solve ``S`` (features from channels): the nominal geometry's
        (:attr:`ngnav.frontend.ArraySolver.solve_matrix`), or with channels excluded the
        reduced one (:mod:`filters.reduced`; zero columns for the excluded channels,
        zero rows for the features they leave unsolved).
    cfg : RunConfig
        Channel noise, turn-on bias and bias random walk.
    feedback : array (k, 6), optional
        With a forecast compensation (GM(1,1), line, last), the sensitivity
        ``E`` of the solved features to the forecast angular acceleration and
        force (the first six columns of the compensation matrix). The forecast
        is made from the compensated block means, so the features' own past
        noise and bias error come back through it: over many blocks (what the
        propagation integrates) the compensated angular acceleration and force
        errors are ``A = (I + E_6)^-1`` of the raw ones and the quadratic
        terms' are offset by ``-E_q A`` of them, ``T = [[A, 0], [-E_q A, I]]``.
        The process-noise blocks are mapped through ``T``; the quadratic block
        of ``feature_cov`` stays raw, because each rate measurement uses one
        block's mean, whose forecast part comes from earlier blocks
        (independent noise). In uav-survey (6 mm outward offset, ``E_6``
        diagonal about 0.07) the raw model left the rate and attitude about
        13 % pessimistic in variance. The history holds the block means less
        the bias *estimates*, so what returns is the bias states' error, true
        less estimated: the bias states are the raw ``S b`` (prior and random
        walk unmapped) and ``T`` is their effect on the features
        (``FilterNoise.bias_effect``). Mapping the prior instead (the states
        ``T S b``) left the estimate's own corrections out of the loop: a
        correction ``d`` moves the features by ``T d``, not ``d``, and the
        angular-acceleration bias estimate converged on ``S b`` with ``T S b``
        as its truth (tactical, 40 runs: 6-8 sigma off by 4 s).

        ``block_wdot_cov`` (the rate's noise over one block, what a zero-rate update
        at rest sees) is the raw angular-acceleration noise, without the forecast's
        correction (``filter.forecast_correction``): the loop's ``A`` holds for errors
        integrated over many blocks only. With the correction the block's own noise
        reaches the state as ``(I - E_6) n``, about ``A n``, and it stays None.
    """
    s = np.asarray(solve_matrix, dtype=float)
    # a floor of 1e-6 m/s^2 keeps the prior positive definite when a config says "no bias"
    b0 = np.maximum(cfg.turn_on_bias_mps2, 1e-6)
    # per sample: the weighted least squares' (H^T R^-1 H)^-1, for the full solve
    feature_cov = (s * np.asarray(cfg.noise_sigma_mps2, dtype=float) ** 2) @ s.T
    bias_prior_cov = s @ np.diag(b0**2) @ s.T
    bias_rw_cov = s @ np.diag(cfg.bias_rw_mps2_rts**2) @ s.T
    # one sample's [wdot, f] noise with its quadratic terms' (the same block's: raw)
    quad_cross_cov = feature_cov[0:6, 6:].copy()
    bias_effect = None
    block_wdot_cov = None
    if feedback is not None:
        if not cfg.compensation.forecast_correction:
            # one block's own angular-acceleration noise is the raw solve's; with the
            # forecast's correction it is not: the correction takes E_6 of the block's
            # forecast error out, its own noise included, which leaves (I - E_6) n ~ A n
            block_wdot_cov = feature_cov[0:3, 0:3].copy()
        k = s.shape[0]
        a = np.linalg.inv(np.eye(6) + feedback[0:6])
        t = np.eye(k)
        t[0:6, 0:6] = a
        t[6:, 0:6] = -feedback[6:] @ a
        raw_qq = feature_cov[6:, 6:].copy()
        feature_cov = t @ feature_cov @ t.T
        feature_cov[6:, 6:] = raw_qq
        bias_effect = t
    return FilterNoise(
        cal_prior_cov=calibration_prior_cov(cfg) if cfg.carries_calibration_error else None,
        feature_cov=feature_cov,
        bias_prior_cov=bias_prior_cov,
        bias_rw_cov=bias_rw_cov,
        position_sigma_m=cfg.position_sigma_m,
        quad_cross_cov=quad_cross_cov,
        bias_effect=bias_effect,
        block_wdot_cov=block_wdot_cov,
    )


def calibration_prior_cov(cfg: RunConfig) -> np.ndarray:
    """Prior covariance (3N, 3N) of the calibration's residual sensing-axis errors ``dg``.

    Channel ``i`` reads ``(theta_i + dg_i) . a_i`` where the filter assumes
    ``theta_i . a_i`` (``a_i`` the specific force at the sensor): ``dg_i`` is the scale's
    residual along the axis plus the two axis angles' across it,
    ``s_i^2 theta theta^T + a_i1^2 e1 e1^T + a_i2^2 e2 e2^T`` with ``e1, e2`` of
    :func:`ngnav.mounting.perpendicular_basis`. A zero sigma is floored at 1e-9 (a
    constant known exactly would leave the covariance singular).
    """
    axes = np.asarray(cfg.layout.axes_b, dtype=float)
    e1, e2 = perpendicular_basis(axes)
    ss = np.maximum(cfg.scale_sigma, 1e-9) ** 2
    sa = np.maximum(cfg.axis_error_sigma_rad, 1e-9) ** 2
    n = axes.shape[0]
    cov = np.zeros((3 * n, 3 * n))
    for i in range(n):
        blk = slice(3 * i, 3 * i + 3)
        cov[blk, blk] = (
            ss[i] * np.outer(axes[i], axes[i])
            + sa[i, 0] * np.outer(e1[i], e1[i])
            + sa[i, 1] * np.outer(e2[i], e2[i])
        )
    return cov
