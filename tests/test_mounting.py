import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ngnav.conventions import G0_MPS2
from ngnav.frontend import ArraySolver
from ngnav.layout import nine_accelerometer_cube
from ngnav.mounting import MountingErrors
from tests.conftest import rigid_body_outputs_direct


@given(seed=st.integers(0, 2**32 - 1))
def test_error_term_is_exact_eq9b_minus_eq9a(seed):
    rng = np.random.default_rng(seed)
    nominal = nine_accelerometer_cube(0.1)
    err = MountingErrors(rng.normal(0, 0.005, (9, 3)), rng.normal(0, 0.02, (9, 2)))
    wd, f, w = rng.normal(size=(3, 3)) * [[5], [10], [3]]
    real_axes = err.real_axes(nominal)
    a_nominal = rigid_body_outputs_direct(nominal.positions_b_m, nominal.axes_b, wd, f, w)
    a_real = rigid_body_outputs_direct(
        nominal.positions_b_m + err.position_error_b_m, real_axes, wd, f, w
    )
    e = err.error_matrix(nominal)
    phi = np.concatenate(
        [wd, f, [w[0] ** 2, w[1] ** 2, w[2] ** 2, w[1] * w[2], w[0] * w[2], w[0] * w[1]]]
    )
    np.testing.assert_allclose(e @ phi, a_real - a_nominal, atol=1e-12)


def test_axis_angle_definition():
    nominal = nine_accelerometer_cube()
    ang = np.zeros((9, 2))
    ang[0, 0] = np.deg2rad(1.0)
    u = MountingErrors(np.zeros((9, 3)), ang).real_axes(nominal)
    assert np.isclose(np.rad2deg(np.arccos(u[0] @ nominal.axes_b[0])), 1.0)


def test_one_degree_axis_error_reads_gravity_as_angular_acceleration():
    """SPEC section 2: g * dtheta / 2l, about 0.86 rad/s^2 for 1 deg on a 0.1 m arm."""
    nominal = nine_accelerometer_cube(0.1)
    ang = np.zeros((9, 2))
    ang[8, 1] = np.deg2rad(1.0)  # sensor 9 (z axis), tilted towards e2 = y: gravity leaks
    real = MountingErrors(np.zeros((9, 3)), ang).real_layout(nominal)
    z = np.zeros(3)
    a = real.outputs(z, np.array([0.0, -G0_MPS2, 0.0]), z)  # gravity along -y (body rolled 90 deg)
    wd = ArraySolver(nominal).solve_features(a)[:3]
    expected = G0_MPS2 * np.sin(np.deg2rad(1.0)) / (2 * 0.1)
    assert np.isclose(abs(wd[0]), expected, rtol=1e-9)
    assert abs(wd[0]) > 0.85
