import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ngnav.conventions import G0_MPS2
from ngnav.frontend import ArraySolver, nine_cube_closed_form
from ngnav.layout import ArrayLayout, nine_accelerometer_cube, six_accelerometer_cube
from ngnav.records import ArraySamples
from tests.conftest import rigid_body_outputs_direct

vec = arrays(np.float64, 3, elements=st.floats(-20, 20))


def test_level_body_at_rest_reads_minus_g_on_down_axes():
    layout = nine_accelerometer_cube()
    z = np.zeros(3)
    a = layout.outputs(z, np.array([0.0, 0.0, -G0_MPS2]), z)
    np.testing.assert_allclose(a[6:], -G0_MPS2, atol=1e-15)
    np.testing.assert_allclose(a[:6], 0.0, atol=1e-15)


@given(wd=vec, f=vec, w=vec, lever=st.floats(0.01, 1.0))
def test_design_matrix_equals_paper_eq3(wd, f, w, lever):
    layout = nine_accelerometer_cube(lever)
    direct = rigid_body_outputs_direct(layout.positions_b_m, layout.axes_b, wd, f, w)
    np.testing.assert_allclose(layout.outputs(wd, f, w), direct, rtol=1e-12, atol=1e-9)


@given(wd=vec, f=vec, w=vec)
def test_nine_cube_round_trip_and_closed_form(wd, f, w):
    layout = nine_accelerometer_cube(0.1)
    a = layout.outputs(wd, f, w)
    phi = ArraySolver(layout).solve_features(a)
    truth = np.concatenate([wd, f, [w[1] * w[2], w[0] * w[2], w[0] * w[1]]])
    ls = phi[[0, 1, 2, 3, 4, 5, 9, 10, 11]]
    np.testing.assert_allclose(ls, truth, atol=1e-9 * (1 + np.abs(truth).max()))
    np.testing.assert_allclose(
        nine_cube_closed_form(a, 0.1), ls, atol=1e-9 * (1 + np.abs(ls).max())
    )
    assert np.all(np.isnan(phi[6:9]))  # the nine-cube never excites squared rates


@given(wd=vec, f=vec, w=vec)
def test_six_cube_rate_aided_round_trip(wd, f, w):
    layout = six_accelerometer_cube(0.1)
    solver = ArraySolver(layout)
    assert solver.rate_aided
    phi = solver.solve_features(layout.outputs(wd, f, w), omega_b_rps=w)
    np.testing.assert_allclose(
        phi[:6], np.concatenate([wd, f]), atol=1e-9 * (1 + np.abs(w).max() ** 2)
    )


@settings(max_examples=30)
@given(seed=st.integers(0, 2**32 - 1))
def test_redundant_random_layout_solves_all_rate_terms(seed):
    rng = np.random.default_rng(seed)
    r = rng.normal(0, 0.1, (15, 3))
    t = rng.normal(size=(15, 3))
    layout = ArrayLayout(r, t / np.linalg.norm(t, axis=1, keepdims=True))
    solver = ArraySolver(layout)
    assert not solver.rate_aided and len(solver.solved_features) == 12
    wd, f, w = rng.normal(size=(3, 3))
    phi = solver.solve_features(layout.outputs(wd, f, w))
    np.testing.assert_allclose(phi[:6], np.concatenate([wd, f]), atol=1e-8)


def test_rank_deficient_layout_names_missing_direction():
    layout = ArrayLayout(np.zeros((6, 3)), np.repeat(np.eye(3), 2, axis=0))
    with pytest.raises(ValueError, match="omega_dot"):
        ArraySolver(layout)


def test_six_cube_without_rate_says_what_it_needs():
    solver = ArraySolver(six_accelerometer_cube())
    with pytest.raises(ValueError, match="omega_b_rps"):
        solver.solve_features(np.zeros(6))


def test_wrong_channel_count_and_nan_and_time():
    solver = ArraySolver(nine_accelerometer_cube())
    with pytest.raises(ValueError, match="9 channels"):
        solver.solve(np.zeros((3, 8)))
    bad = np.zeros((3, 9))
    bad[1, 4] = np.nan
    with pytest.raises(ValueError, match="sample 1"):
        solver.solve(bad)
    with pytest.raises(ValueError, match="increase strictly"):
        ArraySamples(np.array([0.0, 0.01, 0.01]), np.zeros((3, 9)))
    with pytest.raises(ValueError, match="unit vector"):
        ArrayLayout(np.zeros((1, 3)), np.array([[1.0, 1.0, 0.0]]))


def test_least_squares_is_efficient():
    """Empirical covariance over 20000 noisy samples matches (H^T S^-1 H)^-1 within 10 %."""
    rng = np.random.default_rng([2006, 1])
    layout = nine_accelerometer_cube(0.1)
    sigma = np.array([0.01, 0.02, 0.01, 0.03, 0.01, 0.02, 0.01, 0.02, 0.015])
    solver = ArraySolver(layout, noise_sigma_mps2=sigma)
    n = 20_000
    wd, f, w = np.array([0.3, -1.0, 2.0]), np.array([1.0, -2.0, -9.0]), np.array([0.5, 1.0, -0.4])
    a = layout.outputs(wd, f, w) + rng.normal(size=(n, 9)) * sigma
    x = solver.solve_features(a)[:, [0, 1, 2, 3, 4, 5, 9, 10, 11]]
    emp = np.cov(x, rowvar=False)
    bound = solver.covariance()
    np.testing.assert_allclose(np.diag(emp), np.diag(bound), rtol=0.10)
    # and the whole matrix, relative to the bound's scale
    scale = np.sqrt(np.outer(np.diag(bound), np.diag(bound)))
    assert np.max(np.abs(emp - bound) / scale) < 0.10
