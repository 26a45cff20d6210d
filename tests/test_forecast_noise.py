"""The compensation's forecast error as filter noise (``filters.forecast``)."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from filters.pipeline import Pipeline
from filters.state import RATE, VEL
from ngnav.predictors import GreyPredictor, LastValuePredictor, LinePredictor, noise_gain
from ngnav.rotation import dcm_from_quat, quat_from_rotvec
from ngnav.settings import CompensationSettings
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight
from tests.helpers import level_filter


@pytest.mark.parametrize("window", [2, 3, 5, 8])
def test_noise_gain_of_a_line_is_its_closed_form(window):
    """One step past n points of a least-squares line: 1/n + ((n + 1) / 2)^2 / S_xx."""
    x = np.arange(window, dtype=float)
    sxx = float(np.sum((x - x.mean()) ** 2))
    exact = 1.0 / window + ((window + 1) / 2.0) ** 2 / sxx
    hist = np.column_stack([np.linspace(0.0, 1.0, window), np.full(window, -3.0)])
    g = noise_gain(LinePredictor(window=window), hist)
    assert g == pytest.approx([exact, exact], rel=1e-6)
    assert noise_gain(LastValuePredictor(), hist[-1:]) == pytest.approx([1.0, 1.0], rel=1e-9)


def test_noise_gain_of_gm11_matches_its_monte_carlo_variance():
    """The linearised gain against the spread of GM(1,1) forecasts of noisy histories.

    2000 histories of a smooth positive signal plus 1e-3 white noise: the forecasts'
    variance over sigma^2 must match the gain within the chi-square 0.001 / 0.999
    quantiles of a 2000-sample variance.
    """
    pred = GreyPredictor(window=5, shift=np.zeros(1))
    clean = np.array([[2.0], [2.1], [2.25], [2.45], [2.7]])
    g = float(noise_gain(pred, clean)[0])
    rng = np.random.default_rng(11)
    sigma, n = 1e-3, 2000
    f0 = pred.forecast(clean, 0)[0][0]
    f = np.array(
        [pred.forecast(clean + rng.normal(0, sigma, clean.shape), 0)[0][0] for _ in range(n)]
    )
    ratio = float(np.sum((f - f0) ** 2) / n / sigma**2) / g
    lo, hi = chi2.ppf([0.001, 0.999], n) / n
    assert lo < ratio < hi
    assert 1.0 < g < 3.0  # more than the last value's, as an extrapolation


def test_noise_gain_rejects_a_flat_history():
    with pytest.raises(ValueError, match="history must be"):
        noise_gain(LinePredictor(window=3), np.zeros(3))


def test_forecast_noise_is_a_constant_error_over_the_block():
    """What it adds is the covariance of rate += t e_w and velocity += t C e_f."""
    nf, _, _ = level_filter()
    nf.q = quat_from_rotvec(np.array([0.3, -0.2, 1.1]))
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T * 1e-4
    t = 0.01
    p0 = nf.P.copy()
    nf.add_forecast_noise(cov, t)
    g = np.zeros((nf.layout.n, 6))
    g[RATE, 0:3] = t * np.eye(3)
    g[VEL, 3:6] = t * dcm_from_quat(nf.q)
    np.testing.assert_allclose(nf.P - p0, g @ cov @ g.T, atol=1e-15)
    np.testing.assert_array_equal(nf.P - p0, (nf.P - p0).T)


def _forecast_errors(
    scn, run: int = 0, t_end_s: float | None = None
) -> tuple[np.ndarray, np.ndarray, Pipeline]:
    """Each block's time and ``d^2 k`` (the forecast error squared times the block's
    samples), over the whole flight or up to ``t_end_s``."""
    sim = simulate_flight(scn, run)
    samples, fixes = sim.samples, sim.fixes
    if t_end_s is not None:
        keep = samples.t_s <= t_end_s
        samples = type(samples)(t_s=samples.t_s[keep], accel_mps2=samples.accel_mps2[keep])
        fixes = fixes.select(fixes.t_s <= t_end_s)
    out_t, out_d, out_k = [], [], []
    last = {"t": None}

    def grab(p: Pipeline) -> None:
        t = p.nf.t_s
        if last["t"] is not None:
            out_t.append(t)
            out_d.append(p.last_forecast_error.copy())
            out_k.append(round((t - last["t"]) / p.dt))
        last["t"] = t

    pipe = Pipeline(sim.config)
    pipe.on_epoch = lambda _est: grab(pipe)
    pipe.replay(samples, fixes)
    d = np.array(out_d)
    return np.array(out_t), d * d * np.array(out_k)[:, None], pipe


def test_forecast_error_at_rest_is_its_noise_floor():
    """At rest the forecast's error is noise alone: d^2 k averages to (1 + g) N per channel.

    ``static`` (120 s at rest, 100 Hz blocks). The blocks share the forecast's
    window, so the 11 000 squares are taken as 11 000 / 5 independent ones for the
    chi-square 0.001 / 0.999 bounds of their mean.
    """
    t, d2k, pipe = _forecast_errors(load_flight("static"))
    keep = t > 5.0 + 1.0  # after the alignment and the history's first window
    ratio = d2k[keep].mean(axis=0) / pipe.forecast_error_floor
    dof = keep.sum() / 5
    lo, hi = chi2.ppf([0.001, 0.999], dof) / dof
    assert np.all((lo < ratio) & (ratio < hi)), ratio


@pytest.mark.parametrize(
    ("scenario", "sets", "t_end_s"),
    [("static", [], 6.5), ("tactical", ["run.rate_hz=200"], 1.5)],
)
def test_the_first_forecasts_errors_are_noise(scenario, sets, t_end_s):
    """The forecast's history starts from the seed block's motion, its mounting term
    taken out: the first ten blocks' forecast errors are noise, after a static alignment
    (``static``) and after a hand-over in flight (``tactical``).

    Seeded with the raw features less the biases, the history held ``E f`` (an axis
    error times g over the arm on the angular acceleration): the first blocks' errors
    read 13-700 times the noise floor and opened the forecast-error noise at every start.
    The ten blocks share the forecast's window of 5, so each channel's mean of
    ``d^2 k / floor`` is taken as chi-square with 2 dof (0.999 quantile)."""
    t, d2k, pipe = _forecast_errors(load_flight(scenario, sets), t_end_s=t_end_s)
    ratio = (d2k[:10] / pipe.forecast_error_floor).mean(axis=0)
    assert t.shape[0] >= 10
    assert np.all(ratio < chi2.ppf(0.999, 2) / 2), ratio


def test_forecast_noise_grows_the_rate_covariance_in_a_roll_out_not_in_a_dive(monkeypatch):
    """tactical's roll-out of the climbing turn (47 s) against its steady dive (33 s), the
    uncorrected forecast's error counted twice (its persistence) against not at all."""
    import filters.alignment

    scn = load_flight("tactical", ["run.rate_hz=200"])
    sim = simulate_flight(scn, 0)
    cfg = replace(
        sim.config, compensation=replace(sim.config.compensation, forecast_correction=False)
    )
    rate_var = {}
    for persistence in (0.0, 2.0):
        seen = {}

        def grab(p: Pipeline, seen=seen) -> None:
            for tk in (33.0, 48.0):
                if tk not in seen and p.nf.t_s >= tk:
                    seen[tk] = float(np.trace(p.nf.P[RATE, RATE]))

        with monkeypatch.context() as mp:
            mp.setattr(filters.alignment, "FORECAST_ERROR_PERSISTENCE", persistence)
            pipe = Pipeline(cfg)
            pipe.on_epoch = lambda _est, pipe=pipe, grab=grab: grab(pipe)
            pipe.replay(sim.samples, sim.fixes)
        rate_var[persistence] = seen
    steady = rate_var[2.0][33.0] / rate_var[0.0][33.0]
    roll_out = rate_var[2.0][48.0] / rate_var[0.0][48.0]
    assert steady < 1.05
    assert roll_out > 1.2


def test_the_forecast_errors_persistence_follows_its_correction():
    """The filter counts the forecast's error as noise twice without the correction, and
    not at all with it (the correction takes it out of the state)."""
    short = "flight.legs=[{ duration_s = 3.0, ramp_s = 1.0, bank_deg = 30.0 }]"
    scn = load_flight("tactical", ["run.rate_hz=200", short])
    sim = simulate_flight(scn, 0)
    for corrected, want in ((True, 0.0), (False, 2.0)):
        comp = replace(sim.config.compensation, forecast_correction=corrected)
        pipe = Pipeline(replace(sim.config, compensation=comp))
        pipe.replay(sim.samples, sim.fixes)
        assert pipe._fe_persistence == want


@pytest.mark.parametrize("part", ["force", "angular acceleration"])
def test_remove_feature_residual_undoes_a_constant_feature_error(part):
    """A block propagated with ``[wdot, f] + r`` and then :meth:`remove_feature_residual`
    equals the block propagated without ``r`` (the previous block's last sample
    carrying it too): the force's velocity to the propagation's second-order
    attitude-covariance factor at a constant attitude, its
    position to the trapezoid's half-sample (2 % here), the angular acceleration's
    rate and attitude exactly. What an attitude residual does to the velocity through
    gravity (second order) is left."""
    r = np.zeros(6)
    if part == "force":
        r[3:6] = [0.03, -0.02, 0.05]
    else:
        r[0:3] = [0.02, -0.01, 0.03]
    k, dt = 10, 1e-3
    wdot = np.zeros((k, 3))
    f = np.tile([0.0, 0.0, -9.80665], (k, 1))
    clean, _, _ = level_filter()
    dirty, _, _ = level_filter()
    # the trapezoid's first interval starts on the previous block's last sample, which
    # carried the same residual (a residual constant over consecutive blocks)
    clean.set_last_sample(wdot[0], f[0])
    dirty.set_last_sample(wdot[0] + r[0:3], f[0] + r[3:6])
    clean.propagate(wdot, f, dt)
    dirty.propagate(wdot + r[0:3], f + r[3:6], dt)
    moved = np.abs(dirty.vel - clean.vel).max() + np.abs(dirty.w - clean.w).max()
    assert moved > 1e-6  # the residual did move the state
    pos_moved = np.abs(dirty.pos - clean.pos).max()
    dirty.remove_feature_residual(r, k * dt)
    np.testing.assert_allclose(dirty.w, clean.w, atol=1e-15)
    np.testing.assert_allclose(dirty.q, clean.q, atol=1e-12)
    if part == "force":
        # the propagation takes E[C f] (its attitude covariance's second-order factor,
        # 1e-4 of it here): the removal, C r t, leaves that part
        assert np.abs(dirty.vel - clean.vel).max() <= 1e-3 * np.abs(r[3:6]).max() * k * dt
        # the position: r t^2 / 2 against the trapezoid's own (K^2 + 1) dt^2 / 2
        assert np.abs(dirty.pos - clean.pos).max() <= 0.03 * pos_moved


def test_forecast_correction_is_a_setting_that_reaches_the_state():
    """``compensation.forecast_correction`` (off by default) changes the estimates of a
    forecast-compensated run, and only when on."""
    assert CompensationSettings().forecast_correction is False
    scn = load_flight(
        "tactical",
        ["run.rate_hz=200", "flight.legs=[{ duration_s = 3.0, ramp_s = 1.0, bank_deg = 30.0 }]"],
    )
    sim = simulate_flight(scn, 0)
    ends = {}
    for on in (False, True):
        comp = replace(sim.config.compensation, forecast_correction=on)
        cfg = replace(sim.config, compensation=comp)
        pipe = Pipeline(cfg)
        pipe.replay(sim.samples, sim.fixes)
        ends[on] = (pipe.nf.w.copy(), pipe.nf.vel.copy())
    assert not np.allclose(ends[True][0], ends[False][0], rtol=0.0, atol=1e-12)
