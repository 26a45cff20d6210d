import numpy as np
import pytest

from ngnav.compensation import compensate
from ngnav.frontend import ArraySolver
from ngnav.layout import nine_accelerometer_cube
from ngnav.mounting import MountingErrors
from ngnav.predictors import GreyPredictor, LastValuePredictor, OraclePredictor
from ngnav.records import ArraySamples
from ngnav.sim.turntable import fixed_axis_turn

SHIFT = np.repeat([2.1, 245.0, 24.5], 3)


def _setup(noise=0.0, seed=1):
    rng = np.random.default_rng([seed, 0])
    layout = nine_accelerometer_cube(0.1)
    truth = fixed_axis_turn(
        np.deg2rad(120.0),
        duration_s=3.0,
        rest_before_s=0.5,
        rest_after_s=0.5,
        rate_hz=100.0,
        axis_b=np.array([0.2, -0.3, 1.0]),
        pivot_b_m=np.array([0.05, 0.05, 0.05]),
    )
    err = MountingErrors(rng.normal(0, 0.004, (9, 3)), rng.normal(0, 0.01, (9, 2)))
    a = err.real_layout(layout).outputs(truth.omega_dot_b_rps2, truth.f_b_mps2, truth.omega_b_rps)
    a = a + noise * rng.normal(size=a.shape)
    return layout, truth, err, ArraySamples(truth.t_s, a)


def test_true_errors_with_oracle_remove_mounting_error_exactly():
    layout, truth, err, samples = _setup()
    out = compensate(
        samples, ArraySolver(layout), err.error_matrix(layout), OraclePredictor(truth.loop_state())
    )
    np.testing.assert_allclose(out.omega_dot_b_rps2, truth.omega_dot_b_rps2, atol=1e-10)
    np.testing.assert_allclose(out.f_b_mps2, truth.f_b_mps2, atol=1e-10)
    raw = compensate(samples, ArraySolver(layout), None, LastValuePredictor())
    assert (
        np.max(np.abs(raw.omega_dot_b_rps2 - truth.omega_dot_b_rps2)) > 0.05
    )  # there was an error


def test_with_noise_compensation_reaches_noise_floor():
    """Residual error of the compensated solve equals that of a solve of error-free outputs."""
    sigma = 0.01
    layout, truth, err, samples = _setup(noise=sigma, seed=2)
    solver = ArraySolver(layout)
    e = err.error_matrix(layout)
    for pred in (OraclePredictor(truth.loop_state()), GreyPredictor(5, shift=SHIFT)):
        out = compensate(samples, solver, e, pred)
        resid = out.omega_dot_b_rps2 - truth.omega_dot_b_rps2
        # noise floor: the LS bound for omega_dot with this sigma
        floor = np.sqrt(np.diag(solver.covariance())[:3]) * sigma
        n = resid.shape[0]
        # the sample variance of n white samples lies within +-5 sqrt(2/n) of the truth (chi-square)
        ratio = resid.var(axis=0) / floor**2
        assert np.all(np.abs(ratio - 1) < 5 * np.sqrt(2 / n) + 0.05), (pred.name, ratio)
        assert np.all(np.abs(resid.mean(axis=0)) < 5 * floor / np.sqrt(n) + 0.02)


def test_invalid_sample_is_held_or_rejected():
    layout, _truth, err, samples = _setup()
    a = samples.accel_mps2.copy()
    a[50, 2] = np.nan
    bad = ArraySamples(samples.t_s, a)
    solver, e = ArraySolver(layout), err.error_matrix(layout)
    with pytest.raises(ValueError, match="sample 50"):
        compensate(bad, solver, e, GreyPredictor(5, shift=SHIFT))
    out = compensate(bad, solver, e, GreyPredictor(5, shift=SHIFT), on_invalid="hold")
    assert out.n_held == 1 and np.all(np.isfinite(out.state()))
    good = compensate(samples, solver, e, GreyPredictor(5, shift=SHIFT))
    assert np.max(np.abs(out.omega_b_rps - good.omega_b_rps)) < 1e-3


def test_channel_count_mismatch():
    layout, _truth, _err, samples = _setup()
    with pytest.raises(ValueError, match="channels"):
        compensate(
            ArraySamples(samples.t_s, samples.accel_mps2[:, :8]),
            ArraySolver(layout),
            None,
            LastValuePredictor(),
        )


def _channel_config(corrected: bool):
    """What ``filter_noise`` reads of a RunConfig: the channel model (unit noise, as the
    tests' solvers weigh, 1 mg turn-on bias, 1e-5 m/s^2/sqrt(s) walk) and whether the
    forecast's error is corrected."""
    from types import SimpleNamespace

    return SimpleNamespace(
        noise_sigma_mps2=np.ones(9),
        turn_on_bias_mps2=np.full(9, 0.0098),
        bias_rw_mps2_rts=np.full(9, 1e-5),
        position_sigma_m=0.0,
        carries_calibration_error=False,
        compensation=SimpleNamespace(forecast_correction=corrected),
    )


def _loop_errors(
    e6: np.ndarray, sigma: float, n: int, rng: np.random.Generator, corrected: bool = False
) -> np.ndarray:
    """The compensated block means' errors (n, 6) of the GM(1,1) forecast loop.

    The sensors read ``(I + E) phi + n`` (white ``n`` of 1-sigma ``sigma``); the
    compensation subtracts ``E`` times the forecast made from the compensated means.
    ``corrected`` also takes ``E`` of the block's forecast error out (the pipeline's
    ``compensation.forecast_correction``).
    """
    phi = np.array([0.3, -0.2, 0.1, 0.5, -0.4, 9.0])
    window = 5
    gp = GreyPredictor(window=window, shift=np.full(6, 20.0))
    hist = np.tile(phi, (window, 1))
    errs = np.empty((n, 6))
    for k in range(n):
        forecast, _ = gp.forecast(hist[-window:], k)
        comp = phi + e6 @ phi + sigma * rng.standard_normal(6) - e6 @ forecast
        if corrected:
            comp = comp - e6 @ (comp - forecast)
        errs[k] = comp - phi
        hist = np.vstack([hist[1:], comp])
    return errs


def test_forecast_feedback_scales_the_long_run_noise_by_the_closed_loop():
    """The loop the filter's noise model assumes (``filters.pipeline.filter_noise``).

    The sensors read ``(I + E) phi + n``; the compensation subtracts ``E``
    times the GM(1,1) forecast made from the compensated block means. Over
    many blocks the compensated error must then be ``(I + E)^-1 n``: the
    segment means of 200 blocks are tested against that covariance with a
    chi-square bound, and against the raw covariance, which must fail.
    """
    from scipy.stats import chi2

    rng = np.random.default_rng(11)
    e6 = 0.3 * np.eye(6) + 0.03 * rng.standard_normal((6, 6))
    a = np.linalg.inv(np.eye(6) + e6)
    sigma = 0.05
    n_seg, seg = 150, 200
    errs = _loop_errors(e6, sigma, n_seg * seg, rng)
    means = errs.reshape(n_seg, seg, 6).mean(axis=1)

    def statistic(cov_per_block: np.ndarray) -> float:
        inv = np.linalg.inv(cov_per_block / seg)
        return float(np.einsum("si,ij,sj->", means, inv, means))

    lo, hi = chi2.ppf([0.0005, 0.9995], 6 * n_seg)
    closed = statistic(a @ (sigma**2 * np.eye(6)) @ a.T)
    raw = statistic(sigma**2 * np.eye(6))
    assert lo < closed < hi
    assert raw < lo


@pytest.mark.parametrize("corrected", [False, True])
def test_one_blocks_own_noise_is_raw_unless_the_forecast_is_corrected(corrected):
    """What the rate sees over one block while a zero-rate update resets it at every
    block (``FilterNoise.block_wdot_cov``).

    The loop's ``A = (I + E)^-1`` holds for errors integrated over many blocks (the
    test above); one block's own error is the raw noise plus ``E`` of the forecast's,
    about raw. The forecast's correction (``compensation.forecast_correction``) takes ``E``
    of the block's forecast error out, its own noise included: ``(I - E) n``, about
    ``A n``. 30000 blocks, per-channel variance against both models (``E`` 0.07 on
    the diagonal, as ``uav-survey``'s 6 mm offset: the models 13 % apart).
    """

    from filters.noise import filter_noise

    rng = np.random.default_rng(13)
    e6 = 0.07 * np.eye(6) + 0.01 * rng.standard_normal((6, 6))
    a = np.linalg.inv(np.eye(6) + e6)
    sigma = 0.05
    errs = _loop_errors(e6, sigma, 30000, rng, corrected)
    var = errs.var(axis=0)
    raw = np.full(6, sigma**2)
    mapped = np.diag(a @ a.T) * sigma**2
    right, wrong = (mapped, raw) if corrected else (raw, mapped)
    # the variance of 30000 correlated blocks: a few per cent at most
    assert np.all(np.abs(var / right - 1.0) < 0.04), var / right
    assert np.all(np.abs(var / wrong - 1.0) > 0.08), var / wrong

    cfg = _channel_config(corrected)
    solver = ArraySolver(nine_accelerometer_cube(0.1))
    s = solver.solve_matrix
    noise = filter_noise(s, cfg, 0.05 * rng.standard_normal((s.shape[0], 6)))
    if corrected:
        assert noise.block_wdot_cov is None
    else:
        np.testing.assert_allclose(noise.block_wdot_cov, solver.covariance()[0:3, 0:3])


def test_forecast_feedback_returns_the_bias_estimates_error():
    """What the filter's bias states do to the features (``FilterNoise.bias_effect``).

    The features carry a bias ``b``; the filter subtracts its estimate ``b_hat``
    and the forecast history holds the compensated means less ``b_hat``. Once the
    loop settles the compensated features less ``b_hat`` are off by
    ``A (b - b_hat)``, ``A = (I + E)^-1``: a change of the estimate moves the
    features by ``A`` of it. The earlier model (``A b - b_hat``, the estimate
    outside the loop) must fail, and ``filter_noise`` must give this ``A``.
    """

    from filters.noise import filter_noise

    rng = np.random.default_rng(12)
    e6 = 0.07 * np.eye(6) + 0.03 * rng.standard_normal((6, 6))
    a = np.linalg.inv(np.eye(6) + e6)
    phi = np.array([0.3, -0.2, 0.1, 0.5, -0.4, 9.0])
    b = np.array([0.08, -0.05, 0.03, 0.007, -0.009, 0.004])
    b_hat = np.array([0.05, 0.01, -0.02, 0.002, 0.003, -0.006])
    window = 5
    gp = GreyPredictor(window=window, shift=np.full(6, 20.0))
    hist = np.tile(phi, (window, 1))
    for k in range(200):
        forecast, _ = gp.forecast(hist[-window:], k)
        comp = phi + e6 @ phi + b - e6 @ forecast
        hist = np.vstack([hist[1:], comp - b_hat])
    err = comp - b_hat - phi
    np.testing.assert_allclose(err, a @ (b - b_hat), rtol=0, atol=1e-9)
    assert np.max(np.abs(err - (a @ b - b_hat))) > 1e-3

    # the pipeline's noise model: T = [[A, 0], [-E_q A, I]] on the raw biases
    cfg = _channel_config(False)
    solver = ArraySolver(nine_accelerometer_cube(0.1))
    k = solver.solve_matrix.shape[0]
    feedback = 0.05 * rng.standard_normal((k, 6))
    noise = filter_noise(solver.solve_matrix, cfg, feedback)
    a_k = np.linalg.inv(np.eye(6) + feedback[0:6])
    np.testing.assert_allclose(noise.bias_effect[0:6, 0:6], a_k, atol=1e-12)
    np.testing.assert_allclose(noise.bias_effect[6:, 0:6], -feedback[6:] @ a_k, atol=1e-12)
    np.testing.assert_allclose(noise.bias_effect[:, 6:], np.eye(k)[:, 6:], atol=1e-12)
    raw = solver.solve_matrix @ np.diag(np.maximum(cfg.turn_on_bias_mps2, 1e-6) ** 2)
    np.testing.assert_allclose(noise.bias_prior_cov, raw @ solver.solve_matrix.T, rtol=1e-12)


def test_forecast_feedback_returns_the_sensor_positions_through_the_loop():
    """What the filter's sensor-position states do to the features (``geometry_jacobian``).

    The channels carry a position error ``dr``: the solved features ``S G dr``. The
    forecast history holds the compensated means less the bias estimates only, so
    the loop returns ``S G dr`` itself: once it settles the compensated features are
    off by ``T S G dr`` (``T`` the bias states' effect, ``[[A, 0], [-E_q A, I]]``),
    and a filter holding ``dr_hat`` that subtracts ``geometry_jacobian @ dr_hat`` is
    left with ``geometry_jacobian @ (dr - dr_hat)``. The raw ``S G`` (the earlier
    model, which left tactical's 27 position states' NEES at 37.6 against 27) must
    fail it.
    """
    from filters.ekf import FilterNoise, NavFilter
    from filters.noise import filter_noise
    from tests.helpers import PAIRS

    rng = np.random.default_rng(21)
    layout = nine_accelerometer_cube(0.1)
    solver = ArraySolver(layout, np.full(9, 1e-3))
    k = solver.solve_matrix.shape[0]
    se = 0.07 * np.eye(k, 12) + 0.03 * rng.standard_normal((k, 12))
    noise = filter_noise(solver.solve_matrix, _channel_config(False), se[:, 0:6])

    def position_filter(bias_effect):
        cov = solver.covariance()
        return NavFilter(
            FilterNoise(cov, cov, cov * 1e-6, 0.0005, bias_effect=bias_effect),
            PAIRS,
            np.zeros(3),
            sensor_axes_b=layout.axes_b,
            solve_matrix=solver.solve_matrix,
        )

    wdot, w, f = np.array([0.3, -0.2, 0.1]), np.array([0.8, -0.5, 1.1]), np.array([0.5, -0.4, 9.0])
    products = np.array([w[0] ** 2, w[1] ** 2, w[2] ** 2, w[1] * w[2], w[0] * w[2], w[0] * w[1]])
    phi = np.concatenate([wdot, f, w[PAIRS[:, 0]] * w[PAIRS[:, 1]]])
    motion = np.concatenate([wdot, f, products])
    dr = rng.normal(0.0, 0.0005, 27)
    dr_hat = dr + rng.normal(0.0, 0.0002, 27)
    sg_raw = position_filter(None).geometry_jacobian(wdot, w)
    sg = position_filter(noise.bias_effect).geometry_jacobian(wdot, w)
    window = 5
    gp = GreyPredictor(window=window, shift=np.full(6, 20.0))
    hist = np.tile(phi[0:6], (window, 1))
    for n in range(200):
        forecast, _ = gp.forecast(hist[-window:], n)
        comp = phi + se @ motion + sg_raw @ dr - se @ np.concatenate([forecast, products])
        hist = np.vstack([hist[1:], comp[0:6]])
    np.testing.assert_allclose(comp - phi, noise.bias_effect @ sg_raw @ dr, rtol=0, atol=1e-9)
    np.testing.assert_allclose(comp - sg @ dr_hat - phi, sg @ (dr - dr_hat), rtol=0, atol=1e-9)
    assert np.max(np.abs(comp - sg_raw @ dr_hat - phi - sg_raw @ (dr - dr_hat))) > 1e-5
