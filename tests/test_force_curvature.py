"""The attitude error's second-order action on the specific force, against sampled rotations.

A coasting free vehicle's tilt grows to ten degrees and its heading to tens; the velocity
then moves by the exact rotation's second order, which these tests sample.
"""

import numpy as np
from scipy.spatial.transform import Rotation

from filters.algebra import force_curvature_variance, unbiased_force_rotation
from filters.state import ATT, VEL
from ngnav.rotation import dcm_from_quat, quat_from_euler
from tests.helpers import level_filter

# tilt 6 and 8 deg, heading 25 deg, the north tilt correlated with the heading
SIGMA_RAD = np.radians([6.0, 8.0, 25.0])
P_ATT = np.diag(SIGMA_RAD**2)
P_ATT[0, 2] = P_ATT[2, 0] = 0.3 * SIGMA_RAD[0] * SIGMA_RAD[2]
F_TRUE_N = np.array([0.8, -0.5, -9.8])  # a hover tilted into a slow translation, m/s^2


def _draws(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.multivariate_normal(np.zeros(3), P_ATT, size=n)


def test_nominal_force_is_the_truths_on_average():
    """The truth's force is fixed and the estimate's attitude off by ``dtheta ~ N(0, P)``
    (``q_true = exp(dtheta) q_est``): the nominal's rotated force averages the truth's
    within 5 standard errors, where the estimate's own rotation misses by 0.3 m/s^2."""
    c_true = dcm_from_quat(quat_from_euler(*np.radians([4.0, -3.0, 70.0])))
    f_b = c_true.T @ F_TRUE_N
    dth = _draws(50_000, 1)
    c_est = Rotation.from_rotvec(dth).inv().as_matrix() @ c_true  # (n, 3, 3)
    got = np.stack([unbiased_force_rotation(c, P_ATT) @ f_b for c in c_est])
    se = got.std(axis=0) / np.sqrt(got.shape[0])
    assert np.all(np.abs(got.mean(axis=0) - F_TRUE_N) < 5.0 * se)
    # the estimate's rotation alone, and the opposite sign, are biased beyond doubt
    tr = np.trace(P_ATT)
    for m in (np.eye(3), np.eye(3) + 0.5 * (P_ATT - tr * np.eye(3))):
        other = np.einsum("ij,njk,k->ni", m, c_est, f_b)
        assert np.max(np.abs(other.mean(axis=0) - F_TRUE_N) / se) > 20.0


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
    # the mean of b is what unbiased_force_rotation takes out: (P - tr(P) I) f / 2
    mean = 0.5 * (P_ATT - np.trace(P_ATT) * np.eye(3)) @ F_TRUE_N
    assert np.all(np.abs(b.mean(axis=0) - mean) < 5.0 * np.sqrt(var / n))


def test_filter_carries_the_curvature_as_a_constant_until_a_gps_velocity():
    """In a level filter with the attitude covariance of a long coast, each block adds
    ``(s + sd t)^2 - s^2`` to each velocity variance (``s`` the sigma so far), and an
    accepted GPS velocity starts it from zero."""
    nf, _, _ = level_filter()
    nf.P[ATT, ATT] = P_ATT
    f_n = np.array([0.0, 0.0, -9.80665])
    sd = np.sqrt(force_curvature_variance(f_n, P_ATT))
    t = 0.02
    before = np.diag(nf.P[VEL, VEL]).copy()
    nf._add_curvature_noise(t, f_n)
    nf._add_curvature_noise(t, f_n)
    assert np.allclose(np.diag(nf.P[VEL, VEL]) - before, (2.0 * sd * t) ** 2, rtol=1e-12)
    assert sd[2] > 0.1  # m/s^2: g |dtheta_h|^2 / 2 at these tilts
    nf.update_gps(nf.pos.copy(), nf.vel.copy(), np.full(3, 1.0), 0.1)
    assert not np.any(nf._curvature_sd_mps)
