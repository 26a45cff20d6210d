"""The perfect-array control (studies.control): exact, and chi-square by construction."""

import numpy as np
import pytest
from scipy.stats import chi2

from ngnav.geodesy import LocalTangentPlane
from ngnav.records import GpsFixes
from ngnav.sim.gps import GpsReceiverModel
from studies.control import fix_noise, perfect_array_control, process_noise_control


def _fixes(t_s: np.ndarray, h=1.5, v=3.0, va=0.1) -> GpsFixes:
    m = t_s.shape[0]
    ones = np.ones(m)
    return GpsFixes(
        t_s=t_s,
        lat_deg=34.0 * ones,
        lon_deg=-106.5 * ones,
        alt_m=1500.0 * ones,
        vel_ned_mps=np.zeros((m, 3)),
        h_acc_m=h * ones,
        v_acc_m=v * ones,
        vel_acc_mps=va * ones,
        latency_s=0.0 * ones,
    )


def _batch_nees(t_s, noise, sig, skip, k):
    """NEES of the weighted least-squares fit of ``p(t_k), v`` to the fixes 0..k (one
    axis pair per column): the batch solution a Kalman filter without process noise
    must reproduce."""
    use = [j for j in range(k + 1) if not skip[j]]
    out = []
    for ax in range(3):
        rows, z, w = [], [], []
        for j in use:
            rows += [[1.0, t_s[j] - t_s[k]], [0.0, 1.0]]
            z += [noise[j, ax], noise[j, 3 + ax]]
            w += [1 / sig[ax] ** 2, 1 / sig[3 + ax] ** 2]
        a, z, w = np.array(rows), np.array(z), np.array(w)
        info = a.T @ (w[:, None] * a)
        x = np.linalg.solve(info, a.T @ (w * z))
        out.append((x, np.linalg.inv(info)))
    # the three axes are independent: the blocks' NEES are sums over axes
    pos = sum(x[0] ** 2 / p[0, 0] for x, p in out)
    vel = sum(x[1] ** 2 / p[1, 1] for x, p in out)
    return pos, vel


def test_control_equals_the_batch_least_squares_fit():
    """At every fix the control's NEES equals that of the weighted least-squares fit
    to all fixes so far (rel 1e-9): through an uneven gap (an outage) and a skipped
    (glitched) fix."""
    rng = np.random.default_rng(3)
    t = np.concatenate([np.arange(0, 4, 0.2), np.arange(34, 38, 0.2)])
    sig = np.array([1.5, 1.5, 3.0, 0.1, 0.1, 0.1])
    noise = rng.standard_normal((t.shape[0], 6)) * sig
    skip = np.zeros(t.shape[0], dtype=bool)
    skip[7] = True
    c = perfect_array_control(_fixes(t), noise, skip)
    for k in range(t.shape[0]):
        pos, vel = _batch_nees(t, noise, sig, skip, k)
        assert c.nees_pos[k] == pytest.approx(pos, rel=1e-9), k
        assert c.nees_vel[k] == pytest.approx(vel, rel=1e-9), k


@pytest.mark.parametrize(
    "psd, runs, duration_s, ks",
    [(0.0, 400, 20.0, (0, 100, 199)), (1e-3, 200, 30.0, (0, 150, 299))],
    ids=["perfect-array", "process-noise"],
)
def test_control_nees_is_chi_square(psd, runs, duration_s, ks):
    """Draws of white fixes at the stated accuracies (fixed seeds), the control's own
    truth driven by white acceleration of ``psd`` m^2/s^3 (none: the perfect-array
    control): at the first, a middle and the last fix the NEES summed over draws lies
    between the 0.001 and 0.999 chi-square quantiles with 3 x runs dof, both blocks."""
    rng = np.random.default_rng(11)
    t = np.arange(0.0, duration_s, 0.1)
    sig = np.array([1.5, 1.5, 3.0, 0.1, 0.1, 0.1])
    fixes = _fixes(t)
    pos = np.empty((runs, t.shape[0]))
    vel = np.empty((runs, t.shape[0]))
    for i in range(runs):
        noise = rng.standard_normal((t.shape[0], 6)) * sig
        if psd:
            c = process_noise_control(fixes, noise, np.random.default_rng([7, i]), psd)
        else:
            c = perfect_array_control(fixes, noise)
        pos[i], vel[i] = c.nees_pos, c.nees_vel
    lo, hi = chi2.ppf([0.001, 0.999], 3 * runs)
    for k in ks:
        for block in (pos, vel):
            assert lo < block[:, k].sum() < hi, (k, block[:, k].mean())


def test_process_noise_control_rejects_a_bad_psd_or_a_missing_rng():
    with pytest.raises(ValueError, match="accel_psd_m2ps3"):
        process_noise_control(
            _fixes(np.arange(5.0)), np.zeros((5, 6)), np.random.default_rng(0), float("nan")
        )
    with pytest.raises(ValueError, match="needs an rng"):
        process_noise_control(_fixes(np.arange(5.0)), np.zeros((5, 6)), None, 1e-3)


def test_fix_noise_recovers_the_receivers_draws():
    """A receiver's fixes along a truth, back through :func:`fix_noise`: the errors are
    exactly the receiver's normal draws times its accuracies (the same seed replayed),
    to the geodetic round trip (1e-6 m)."""
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    sim = simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)
    ltp = LocalTangentPlane(34.0, -106.5, 1500.0)
    rx = GpsReceiverModel(rate_hz=10.0, h_acc_m=1.5, v_acc_m=3.0, antenna_b_m=(-0.4, 0.1, -0.05))
    fixes, _ = rx.simulate(sim.truth, ltp, np.random.default_rng(7))
    got = fix_noise(fixes, sim.truth, ltp, rx.antenna_b_m)
    rng = np.random.default_rng(7)
    m = len(fixes)
    pos = rng.normal(0.0, 1.0, (m, 3)) * np.array([1.5, 1.5, 3.0])
    vel = rng.normal(0.0, 0.1, (m, 3))
    np.testing.assert_allclose(got[:, 0:3], pos, atol=1e-6)
    np.testing.assert_allclose(got[:, 3:6], vel, atol=1e-12)
    late = GpsFixes(**{**fixes.__dict__, "t_s": fixes.t_s + 1e-4})
    with pytest.raises(ValueError, match="not on the truth's sample times"):
        fix_noise(late, sim.truth, ltp, rx.antenna_b_m)


def test_control_rejects_a_noise_array_of_the_wrong_shape():
    with pytest.raises(ValueError, match=r"expected \(5, 6\)"):
        perfect_array_control(_fixes(np.arange(5.0)), np.zeros((5, 3)))
