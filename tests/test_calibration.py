import numpy as np
import pytest
from scipy.stats import t as student_t

from ngnav.calibration import (
    calibrate_multiposition,
    eq27_axis_error,
    eq27_positions,
    multiposition_directions,
)
from ngnav.layout import nine_accelerometer_cube
from ngnav.mounting import MountingErrors


def _readings(real, up, bias, scale, s=100.0):
    z = np.zeros((up.shape[0], 3))
    return bias + s * scale * real.outputs(z, up * 9.80665, z) / 9.80665


def test_multiposition_exact_without_noise():
    rng = np.random.default_rng(3)
    nominal = nine_accelerometer_cube()
    ang = rng.normal(0, 0.01, (9, 2))
    real = MountingErrors(np.zeros((9, 3)), ang).real_layout(nominal)
    bias, scale = rng.normal(0, 5, 9), 1 + rng.normal(0, 0.01, 9)
    up = multiposition_directions()
    cal = calibrate_multiposition(up, _readings(real, up, bias, scale), nominal)
    np.testing.assert_allclose(cal.axis_error_rad, ang, atol=1e-12)
    np.testing.assert_allclose(cal.bias_mv, bias, atol=1e-9)
    np.testing.assert_allclose(cal.scale, scale, atol=1e-12)


def test_multiposition_sigma_covers_truth():
    """Share of |error| <= 2 sigma over 200 x 18 angles is 95 % within a binomial bound."""
    nominal = nine_accelerometer_cube()
    up = multiposition_directions()
    inside = []
    for i in range(200):
        rng = np.random.default_rng([11, i])
        ang = rng.normal(0, 0.01, (9, 2))
        real = MountingErrors(np.zeros((9, 3)), ang).real_layout(nominal)
        v = _readings(real, up, rng.normal(0, 5, 9), 1.0) + rng.normal(0, 0.05, (18, 9))
        cal = calibrate_multiposition(up, v, nominal)
        inside.append(np.abs(cal.axis_error_rad - ang) <= 2 * cal.axis_error_sigma_rad)
    share = np.mean(inside)
    n = np.size(inside)
    # the noise comes from 14-dof residuals and sigma is the t error's standard deviation,
    # s sqrt(14 / 12): 2 sigma covers P(|t_14| < 2 sqrt(14 / 12)); 4 binomial sigmas
    p = 1.0 - 2.0 * student_t.sf(2.0 * np.sqrt(14.0 / 12.0), 14)
    assert abs(share - p) < 4 * np.sqrt(p * (1.0 - p) / n)


def test_eq27_recovers_angle_from_exact_readings():
    nominal = nine_accelerometer_cube()
    ang = np.zeros((9, 2))
    ang[:, 0] = np.deg2rad(np.linspace(-3, 3, 9))
    real = MountingErrors(np.zeros((9, 3)), ang).real_layout(nominal)
    pos = eq27_positions(nominal)
    est = []
    for i in range(9):
        v = _readings(real, pos[i], 0.0, 1.0)[:, i]
        est.append(eq27_axis_error(v[0], v[1], np.sign(v[2] - v[3])))
    # V1 holds sin(a), not the zero: eq. 27 reads arccos(min(1, |cos a - sin a|)) for an axis
    # tilted towards e1 (its flaw: a negative tilt reads 0); exact readings give exactly that:
    a = ang[:, 0]
    np.testing.assert_allclose(
        np.array(est),
        np.sign(a) * np.arccos(np.clip(np.abs(np.cos(a) - np.sin(a)), 0, 1)),
        atol=1e-9,
    )


def test_eq27_conditioning_figures():
    assert 100 * (1 - np.cos(np.deg2rad(1))) == pytest.approx(0.0152, abs=1e-4)
    assert np.rad2deg(eq27_axis_error(0.0, 99.9, 1.0)) == pytest.approx(2.56, abs=0.01)


def test_multiposition_bad_input():
    nominal = nine_accelerometer_cube()
    with pytest.raises(ValueError, match="at least 7"):
        calibrate_multiposition(np.eye(3), np.zeros((3, 9)), nominal)
    with pytest.raises(ValueError, match="span"):
        calibrate_multiposition(np.tile([0, 0, 1.0], (8, 1)), np.zeros((8, 9)), nominal)
