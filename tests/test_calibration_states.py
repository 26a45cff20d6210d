"""The calibration's residual sensing-axis errors as states (block ``cal``).

A bench calibration leaves each channel's scale and axis angles a few ppm and
microradians off; the channel then reads ``dg_i . a_i`` more (``a_i`` the specific
force at the sensor), which follows the load. These tests check the sensitivity
against the array's exact outputs, the prior against the calibration's 1-sigmas, the
configuration keys, and that a filter carrying the states learns the residual in
flight and stays inside its covariance where the one without them does not.
"""

from __future__ import annotations

import numpy as np
import pytest

from filters.evaluate import run_errors
from filters.kernels import load_jacobian
from filters.noise import calibration_prior_cov
from filters.pipeline import run_filter
from filters.state import ATT, RATE
from ngnav.frontend import ArraySolver
from ngnav.layout import nine_accelerometer_cube
from ngnav.mounting import MountingErrors, perpendicular_basis
from ngnav.runconfig import read_run_config_text, run_config_text
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight


def _dg(axes: np.ndarray, scale_err: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """First-order sensing-axis error (N, 3) of a scale error and two axis angles."""
    e1, e2 = perpendicular_basis(axes)
    return scale_err[:, None] * axes + angles[:, :1] * e1 + angles[:, 1:] * e2


def test_load_jacobian_is_the_channels_exact_change():
    """``S diag(a_i^T) dg`` is the solved features' change when the real sensors have the
    scale and axis errors behind ``dg`` (the layout's exact outputs), to first order."""
    rng = np.random.default_rng(7)
    lay = nine_accelerometer_cube(0.1)
    s = ArraySolver(lay).solve_matrix
    scale_err = rng.normal(0.0, 1e-5, lay.n_sensors)
    angles = rng.normal(0.0, 1e-5, (lay.n_sensors, 2))
    real = MountingErrors(np.zeros((lay.n_sensors, 3)), angles).real_layout(lay)
    for _ in range(5):
        wdot, f, w = rng.normal(0.0, 3.0, 3), rng.normal(0.0, 50.0, 3), rng.normal(0.0, 8.0, 3)
        exact = (1.0 + scale_err) * real.outputs(wdot, f, w) - lay.outputs(wdot, f, w)
        sg = load_jacobian(f, wdot, w, lay.positions_b_m, np.repeat(s, 3, axis=1))
        model = sg @ _dg(lay.axes_b, scale_err, angles).ravel()
        # second order: 1e-5 of the change itself
        np.testing.assert_allclose(model, s @ exact, rtol=0, atol=1e-4 * np.abs(s @ exact).max())


def test_calibration_prior_is_the_fits_sigmas_on_their_directions():
    """Each sensor's 3 x 3 block holds the scale's variance along the axis and each
    angle's across it, and nothing between sensors."""
    text = run_config_text(simulate_flight(load_flight("tactical"), 0).config)
    cfg = read_run_config_text(
        text.replace("[sensor]", "scale_sigma = 4e-6\naxis_error_sigma_rad = 3e-6\n[sensor]"),
        "config.toml",
    )
    assert cfg.carries_calibration_error
    cov = calibration_prior_cov(cfg)
    e1, e2 = perpendicular_basis(cfg.layout.axes_b)
    for i, t in enumerate(cfg.layout.axes_b):
        blk = cov[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]
        assert t @ blk @ t == pytest.approx(16e-12)
        assert e1[i] @ blk @ e1[i] == pytest.approx(9e-12)
        assert e2[i] @ blk @ e2[i] == pytest.approx(9e-12)
        assert abs(t @ blk @ e1[i]) < 1e-20
    off = cov.copy()
    for i in range(cfg.layout.n_sensors):
        off[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = 0.0
    assert not off.any()


def test_config_carries_the_calibration_sigmas_and_names_a_bad_shape():
    cfg = simulate_flight(load_flight("tactical"), 0).config
    assert not cfg.carries_calibration_error  # tactical declares none
    text = run_config_text(cfg)
    assert "scale_sigma" not in text
    n = cfg.layout.n_sensors
    declared = text.replace(
        "[sensor]",
        f"scale_sigma = {[1e-6 * (i + 1) for i in range(n)]}\n"
        f"axis_error_sigma_rad = {[[2e-6, 3e-6]] * n}\n[sensor]",
    )
    back = read_run_config_text(declared, "config.toml")
    np.testing.assert_array_equal(back.scale_sigma, 1e-6 * np.arange(1, n + 1))
    np.testing.assert_array_equal(back.axis_error_sigma_rad, [[2e-6, 3e-6]] * n)
    again = run_config_text(back)
    assert "scale_sigma" in again
    assert run_config_text(read_run_config_text(again, "config.toml")) == again
    bad = text.replace("[sensor]", "axis_error_sigma_rad = [1e-6, 2e-6]\n[sensor]")
    with pytest.raises(ValueError, match=r"axis_error_sigma_rad must have shape \(9, 2\)"):
        read_run_config_text(bad, "config.toml")


@pytest.fixture(scope="module")
def poorly_calibrated():
    """`projectile` run 0 with a short bench calibration (500 samples a pose: residuals
    of some 30 urad and ppm, at the boost's 24 g about 0.7 mg per channel), filtered
    with and without the calibration's 1-sigmas declared; and the same flight with the
    residual removed (10^9 samples a pose), the reference for what the array can do."""
    out = {}
    for name, samples, declared in (
        ("with", 500, "true"),
        ("without", 500, "false"),
        ("ideal", 10**9, "false"),
    ):
        scn = load_flight(
            "projectile",
            [
                f"mounting.calibration_samples={samples}",
                f"mounting.declare_calibration_sigmas={declared}",
            ],
        )
        sim = simulate_flight(scn, 0)
        out[name] = (sim, run_filter(sim.samples, sim.fixes, sim.config))
    return out


def _late_rms(sim, res) -> tuple[float, float]:
    """Attitude (rad) and rate (rad/s) RMS after the boost (from 8 s)."""
    d = run_errors(res.estimates, sim.truth).stacked()
    late = res.estimates.t_s > 8.0
    att = np.sqrt(np.mean(np.sum(d[late, ATT] ** 2, axis=1)))
    rate = np.sqrt(np.mean(np.sum(d[late, RATE] ** 2, axis=1)))
    return float(att), float(rate)


def test_the_filter_learns_the_sensing_axes_in_flight(poorly_calibrated):
    """With the states the flight teaches the filter the residual (its estimate moves
    toward the truth, its covariance shrinks), and attitude and rate after the boost come
    close to those of the same flight without the residual; without them they do not."""
    sim, res = poorly_calibrated["with"]
    fin = res.final
    assert dict(fin.state_blocks)["cal"] == 27
    assert "cal" not in dict(poorly_calibrated["without"][1].final.state_blocks)
    cfg = sim.config
    known_axes = cfg.known_errors.real_axes(cfg.layout)
    true_axes = sim.true_errors.real_axes(cfg.layout)
    # what the calibrated channel reads over what the filter assumes, per unit load
    dg_true = ((sim.true_scale / cfg.scale)[:, None] * true_axes - known_axes).ravel()
    e = dg_true - fin.axis_error_b
    assert np.linalg.norm(e) < 0.9 * np.linalg.norm(dg_true)
    assert np.trace(fin.block_cov("cal")) < 0.7 * np.trace(calibration_prior_cov(cfg))
    att_with, rate_with = _late_rms(*poorly_calibrated["with"])
    att_without, rate_without = _late_rms(*poorly_calibrated["without"])
    att_ideal, rate_ideal = _late_rms(*poorly_calibrated["ideal"])
    assert att_with < 1.5 * att_ideal and rate_with < 1.5 * rate_ideal
    assert att_without > 2.0 * att_ideal and rate_without > 3.0 * rate_ideal
