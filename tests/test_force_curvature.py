"""The attitude error's second-order action on the specific force, against sampled rotations.

A coasting free vehicle's tilt grows to ten degrees and its heading to tens; the velocity
then moves by the exact rotation's second order, which these tests sample.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from filters.algebra import force_curvature_variance, shrink_to_size
from filters.state import ATT, POS, VEL
from tests.helpers import level_filter

# tilt 6 and 8 deg, heading 25 deg, the north tilt correlated with the heading
SIGMA_RAD = np.radians([6.0, 8.0, 25.0])
P_ATT = np.diag(SIGMA_RAD**2)
P_ATT[0, 2] = P_ATT[2, 0] = 0.3 * SIGMA_RAD[0] * SIGMA_RAD[2]
F_TRUE_N = np.array([0.8, -0.5, -9.8])  # a hover tilted into a slow translation, m/s^2


def _draws(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.multivariate_normal(np.zeros(3), P_ATT, size=n)


def test_curvature_mean_is_the_nominals_correction():
    """About the estimate (``q_true = exp(dtheta) q_est``, ``dtheta ~ N(0, P)``) the truth's
    force ``R(dtheta) v`` averages ``(I + (P - tr(P) I) / 2) v``, the nominal's mean
    (:meth:`NavFilter.propagate`), within 5 standard errors; the other sign misses by
    more than 20. The exact rotations are sampled (tilt 3-4 deg, heading 12.5 deg)."""
    # half the sigmas: at 25 deg the fourth order (|dtheta|^4 g / 24) reaches the test's
    # resolution
    dth = 0.5 * _draws(400_000, 1)
    got = Rotation.from_rotvec(dth).apply(F_TRUE_N)
    se = got.std(axis=0) / np.sqrt(got.shape[0])
    a = 0.5 * (0.25 * P_ATT - np.trace(0.25 * P_ATT) * np.eye(3))
    assert np.all(np.abs(got.mean(axis=0) - (np.eye(3) + a) @ F_TRUE_N) < 5.0 * se)
    assert np.max(np.abs(got.mean(axis=0) - (np.eye(3) - a) @ F_TRUE_N) / se) > 20.0


def test_curvature_variance_is_the_quadratic_forms():
    """``force_curvature_variance`` against 400 000 draws of ``[dtheta]x^2 f / 2``, within
    5 standard errors of the sample variance (fourth moments)."""
    dth = _draws(400_000, 2)
    # [dtheta]x^2 f = dtheta (dtheta . f) - |dtheta|^2 f
    b = 0.5 * (dth * (dth @ F_TRUE_N)[:, None] - (dth * dth).sum(axis=1)[:, None] * F_TRUE_N)
    d = b - b.mean(axis=0)
    n = b.shape[0]
    var = (d * d).mean(axis=0)
    se = np.sqrt(((d**4).mean(axis=0) - var**2) / n)
    got = force_curvature_variance(F_TRUE_N, P_ATT)
    assert np.all(np.abs(got - var) < 5.0 * se)
    # the mean of b is what the nominal carries: (P - tr(P) I) f / 2
    mean = 0.5 * (P_ATT - np.trace(P_ATT) * np.eye(3)) @ F_TRUE_N
    assert np.all(np.abs(b.mean(axis=0) - mean) < 5.0 * np.sqrt(var / n))


def test_filter_carries_the_curvature_as_a_constant_until_a_gps_fix():
    """In a level filter with the attitude covariance of a long coast, blocks of the
    transition (``p += v t``) and the curvature's noise leave, on top of the transition's
    own, exactly a constant acceleration ``b`` of sigma ``sd``'s moments after ``T``:
    velocity ``sd^2 T^2``, position ``sd^2 T^4 / 4``, their covariance ``sd^2 T^3 / 2``;
    an accepted GPS fix starts it from zero."""
    nf, _, _ = level_filter()
    nf.P[ATT, ATT] = P_ATT
    f_n = np.array([0.0, 0.0, -9.80665])
    sd = np.sqrt(force_curvature_variance(f_n, P_ATT))
    t, blocks = 0.02, 50
    n = nf.P.shape[0]

    def transition(dt: float) -> np.ndarray:
        phi = np.eye(n)
        phi[POS, VEL] = dt * np.eye(3)
        return phi

    phi_all = transition(t * blocks)
    expected = phi_all @ nf.P @ phi_all.T
    for _ in range(blocks):
        phi = transition(t)
        nf.P = phi @ nf.P @ phi.T
        nf._add_curvature_noise(t, f_n)
    big_t = t * blocks
    expected[VEL, VEL] += np.diag(sd**2 * big_t**2)
    expected[POS, POS] += np.diag(sd**2 * big_t**4 / 4.0)
    expected[POS, VEL] += np.diag(sd**2 * big_t**3 / 2.0)
    expected[VEL, POS] += np.diag(sd**2 * big_t**3 / 2.0)
    assert np.allclose(nf.P, expected, rtol=1e-10, atol=1e-15)
    assert sd[2] > 0.1  # m/s^2: g |dtheta_h|^2 / 2 at these tilts
    nf.update_gps(nf.pos.copy(), nf.vel.copy(), np.full(3, 1.0), 0.1)
    assert not np.any(nf._curvature_sd_mps) and not np.any(nf._curvature_sd_m)


def test_the_transitions_force_is_shrunk_by_the_tilts_uncertainty():
    """A hover whose estimate is tilted 3 deg by its own error, tilt 10 deg uncertain: the
    horizontal force the transition reads is zero (the tilt alone explains it) and the
    vertical is kept; a 3 m/s^2 turn with the tilt known to 0.3 deg keeps its force but
    for the unbiased shrink. ``var_i`` written out for a diagonal ``P``:
    ``var_x = f_z^2 P_yy + f_y^2 P_zz`` and its cyclic permutations."""
    nf, _, _ = level_filter()
    g = 9.80665
    f_hover = np.array([g * np.sin(np.radians(3.0)), 0.0, -g * np.cos(np.radians(3.0))])
    nf.P[ATT, ATT] = np.diag(np.radians([10.0, 10.0, 30.0]) ** 2)
    got = nf.force_for_jacobian(f_hover)
    assert got[0] == 0.0 and got[1] == 0.0
    p = np.diagonal(nf.P[ATT, ATT])
    var_z = f_hover[1] ** 2 * p[0] + f_hover[0] ** 2 * p[1]
    assert got[2] == pytest.approx(-np.sqrt(f_hover[2] ** 2 - var_z), rel=1e-12)
    f_turn = np.array([3.0, -1.0, -9.9])
    nf.P[ATT, ATT] = np.diag(np.radians([0.3, 0.3, 2.0]) ** 2)
    p = np.diagonal(nf.P[ATT, ATT])
    var = np.array(
        [
            f_turn[2] ** 2 * p[1] + f_turn[1] ** 2 * p[2],
            f_turn[2] ** 2 * p[0] + f_turn[0] ** 2 * p[2],
            f_turn[1] ** 2 * p[0] + f_turn[0] ** 2 * p[1],
        ]
    )
    want = np.sign(f_turn) * np.sqrt(f_turn**2 - var)
    np.testing.assert_allclose(nf.force_for_jacobian(f_turn), want, rtol=1e-12)


def test_a_jacobians_motion_reads_zero_until_clear_of_its_noise():
    """``shrink_to_size``: each component to its unbiased size ``sqrt(x^2 - var)`` with its
    sign, zero within its noise, and with ``clear_sigmas`` zero until that size stands
    ``clear_sigmas`` noise sigmas from zero (the sensor positions' angular acceleration,
    whose noise the rate's error shares)."""
    var = np.array([1.0, 1.0, 4.0, 1.0])
    x = np.array([0.9, -2.0, 6.0, -3.5])
    got = shrink_to_size(x, var)
    assert np.array_equal(got, [0.0, -np.sqrt(3.0), np.sqrt(32.0), -np.sqrt(11.25)])
    cleared = shrink_to_size(x, var, clear_sigmas=3.0)
    # unbiased sizes 0, 1.73, 2.83 (sigma 2), 3.35: only the last is beyond 3 sigmas
    assert np.array_equal(cleared, [0.0, 0.0, 0.0, -np.sqrt(11.25)])
