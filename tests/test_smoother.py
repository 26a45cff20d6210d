"""The Rauch-Tung-Striebel pass (filters.smoother) against filterpy's own smoother,
and ``ngnav run --smooth`` end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import rts_smoother

from filters.output import read_estimates_csv, read_estimates_npz
from filters.smoother import SmootherLog, boxminus, boxplus
from filters.state import ATT, N_NAV, StateLayout
from filters.updates import Measurement, update_correlated
from ngnav.rotation import quat_from_rotvec

LAYOUT = StateLayout(3, 0, 0)  # 12 navigation states and 9 biases
R_FIX = 0.09 * np.eye(6)  # a reset's fix: position and velocity variance


class LinearFilter(SimpleNamespace):
    """A stand-in for the navigation filter whose nominal state is a linear KF's mean."""

    def set_mean(self, x: np.ndarray) -> None:
        self.pos, self.vel = x[0:3].copy(), x[3:6].copy()
        self.q = quat_from_rotvec(x[ATT])
        self.w, self.bias = x[9:12].copy(), x[12:].copy()


def _fake(n: int) -> LinearFilter:
    nf = LinearFilter(
        layout=LAYOUT,
        dr=np.zeros(0),
        dg=np.zeros(0),
        aoa_b=0.0,
        aoa_k=0.0,
        t_s=0.0,
        P=np.eye(n),
        in_body_frame=lambda: False,
    )
    nf.set_mean(np.zeros(n))
    return nf


def _linear_run(steps: int, break_at: int | None = None, correlated: bool = False):
    """A linear-Gaussian run through filterpy, logged as the pipeline logs its blocks.

    F is the identity below its navigation rows (as the navigation filter's), the
    attitude is neither driven, coupled nor measured (its mean stays 0, the
    exponential map exact), everything else is random. With ``correlated`` each
    measurement's noise is correlated with the propagation noise of the step before it
    (as the rate products' are with their block's). Returns the log, the filter's
    posteriors, F, Q, H, R, the noise cross-covariance and the measurements.
    """
    rng = np.random.default_rng(7)
    n, nz = LAYOUT.n, 6
    keep = np.ones(n, dtype=bool)
    keep[ATT] = False
    f = np.eye(n)
    f[:N_NAV] += 0.05 * rng.standard_normal((N_NAV, n))
    f[ATT, :] = f[:, ATT] = 0.0
    f[ATT, ATT] = np.eye(3)
    g = rng.standard_normal((n + nz, n + nz)) * 0.1
    joint = g @ g.T + 1e-2 * np.eye(n + nz)  # [[Q, M], [M^T, R]]
    joint[ATT, :] = joint[:, ATT] = 0.0
    joint[ATT, ATT] = 1e-4 * np.eye(3)
    q, r = joint[:n, :n], joint[n:, n:]
    m = joint[:n, n:] if correlated else np.zeros((n, nz))
    joint[:n, n:], joint[n:, :n] = m, m.T
    h = rng.standard_normal((nz, n))
    h[:, ATT] = 0.0
    x, p = np.zeros(n), np.eye(n)
    nf = _fake(n)
    log = SmootherLog(n)
    nf.lag = log.lag
    xs, ps, zs = [x.copy()], [p.copy()], []
    truth = rng.standard_normal(n) * keep
    chol = np.linalg.cholesky(joint)
    for k in range(steps):
        nf.P = p
        nf.set_mean(x)
        log.posterior(nf)
        log.lag.start(p, f)
        x, p = kf_predict(x, p, f, q)
        wv = chol @ rng.standard_normal(n + nz)
        truth = f @ truth + wv[:n]
        z = h @ truth + wv[n:]
        zs.append(z)
        meas = Measurement(z - h @ x, h, r, m if correlated else None)
        log.lag.update(meas, p)
        x, p = update_correlated(x, p, z, r, h, meas.cross)
        if k == break_at:
            # position and velocity put on a fix, their correlations dropped (the filter's
            # reset_to_fix): not a measurement
            reset = (x.copy(), p.copy(), truth[:6] + 0.3 * rng.standard_normal(6))
            p = p.copy()
            p[:6, :] = 0.0
            p[:, :6] = 0.0
            p[:6, :6] = R_FIX
            x = x.copy()
            x[:6] = reset[2]
            nf.lag.forget(slice(0, 6))
        xs.append(x.copy())
        ps.append(p.copy())
    nf.P = p
    nf.set_mean(x)
    log.posterior(nf)
    if break_at is not None:
        return log, np.array(xs), np.array(ps), (f, q), reset
    return log, np.array(xs), np.array(ps), (f, q, h, r, m, np.array(zs))


def _batch(model, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """The exact smoother: every state given every measurement, by Gaussian conditioning
    of the whole run at once (prior x_0 ~ N(0, I); noises ``[w_k, v_k+1]`` joint)."""
    f, q, h, r, m, zs = model
    n, nz = f.shape[0], h.shape[0]
    nu = n + steps * (n + nz)
    sig = np.zeros((nu, nu))
    sig[:n, :n] = np.eye(n)
    blk = np.block([[q, m], [m.T, r]])
    a = np.zeros(((steps + 1) * n, nu))  # states from the primitive noises
    b = np.zeros((steps * nz, nu))  # measurements from them
    a[:n, :n] = np.eye(n)
    for k in range(steps):
        o = n + k * (n + nz)
        sig[o : o + n + nz, o : o + n + nz] = blk
        a[(k + 1) * n : (k + 2) * n] = f @ a[k * n : (k + 1) * n]
        a[(k + 1) * n : (k + 2) * n, o : o + n] += np.eye(n)
        b[k * nz : (k + 1) * nz] = h @ a[(k + 1) * n : (k + 2) * n]
        b[k * nz : (k + 1) * nz, o + n : o + n + nz] += np.eye(nz)
    sxz = a @ sig @ b.T
    szz = b @ sig @ b.T
    gain = np.linalg.solve(szz, sxz.T).T
    mean = gain @ zs.ravel()
    cov = a @ sig @ a.T - gain @ sxz.T
    means = mean.reshape(steps + 1, n)
    covs = np.array([cov[k * n : (k + 1) * n, k * n : (k + 1) * n] for k in range(steps + 1)])
    return means, covs


def _as_state(row: tuple) -> np.ndarray:
    _t, pos, vel, quat, w, bias, _cov = row
    x = np.concatenate([pos, vel, np.zeros(3), w, bias])
    x[ATT] = boxminus(
        np.concatenate([np.zeros(6), quat, np.zeros(x.size - 9)]),
        np.concatenate([np.zeros(6), [1.0, 0, 0, 0], np.zeros(x.size - 9)]),
    )[ATT]
    return x


def test_equals_filterpy_rts_smoother_on_a_linear_run():
    steps = 40
    log, xs, ps, (f, q, *_) = _linear_run(steps)
    rows, restarts = log.smooth(LAYOUT)
    log.close()
    assert restarts == 0 and len(rows) == steps + 1
    # filterpy's smoother over the same posteriors (its Fs[k] moves epoch k to k + 1)
    x_ref, p_ref, _, _ = rts_smoother(
        xs, ps, np.array([f] * (steps + 1)), np.array([q] * (steps + 1))
    )
    got = np.array([_as_state(r) for r in rows])
    np.testing.assert_allclose(got, x_ref, rtol=0, atol=1e-9)
    cov = np.array([r[6] for r in rows])
    np.testing.assert_allclose(cov, p_ref[:, :12, :12], rtol=0, atol=1e-9)
    # the smoother gained: every epoch but the last is tighter than the filter's
    trace = np.trace(cov, axis1=1, axis2=2)
    assert np.all(trace[:-1] < np.trace(ps[:-1, :12, :12], axis1=1, axis2=2))


def test_equals_the_batch_solution_with_correlated_noise():
    steps = 15
    log, xs, ps, model = _linear_run(steps, correlated=True)
    rows, restarts = log.smooth(LAYOUT)
    assert restarts == 0
    means, covs = _batch(model, steps)
    np.testing.assert_allclose(np.array([_as_state(r) for r in rows]), means, atol=1e-9)
    np.testing.assert_allclose(np.array([r[6] for r in rows]), covs[:, :12, :12], atol=1e-9)
    # the textbook pass, blind to the correlation, is not the answer here
    f, q = model[0], model[1]
    x_ref, _, _, _ = rts_smoother(xs, ps, np.array([f] * (steps + 1)), np.array([q] * (steps + 1)))
    assert np.max(np.abs(x_ref - means)) > 1e-3


def test_a_reset_is_smoothed_across_as_a_jump_then_a_fix():
    """A reset onto a fix is the limit of a jump (huge process noise on position and
    velocity) followed by a measurement of them: filterpy's smoother over that sequence,
    the jump an extra epoch, is the reference."""
    k = 9
    log, xs, ps, (f, q), (x_pre, p_pre, _) = _linear_run(20, break_at=k)
    rows, restarts = log.smooth(LAYOUT)
    assert restarts == 0
    n = xs.shape[1]
    jump = np.zeros((n, n))
    jump[:6, :6] = 1e6 * np.eye(6)  # huge beside the states, still well conditioned
    ref_x = np.concatenate([xs[: k + 1], x_pre[None], xs[k + 1 :]])
    ref_p = np.concatenate([ps[: k + 1], p_pre[None], ps[k + 1 :]])
    fs = np.array([f] * ref_x.shape[0])
    qs = np.array([q] * ref_x.shape[0])
    fs[k + 1], qs[k + 1] = np.eye(n), jump  # filterpy: Fs[i] moves epoch i to i + 1
    x_ref, p_ref, _, _ = rts_smoother(ref_x, ref_p, fs, qs)
    keep = np.r_[0 : k + 1, k + 2 : ref_x.shape[0]]  # all but the epoch before the jump
    np.testing.assert_allclose(np.array([_as_state(r) for r in rows]), x_ref[keep], atol=1e-6)
    np.testing.assert_allclose(np.array([r[6] for r in rows]), p_ref[keep, :12, :12], atol=1e-6)
    # the epochs before the reset learn from the ones after it (through the other states)
    assert np.trace(rows[k][6]) < np.trace(
        rts_smoother(xs[: k + 1], ps[: k + 1], np.array([f] * (k + 1)), np.array([q] * (k + 1)))[1][
            k
        ][:12, :12]
    )


@pytest.mark.parametrize("body", [False, True])
def test_boxplus_inverts_boxminus_with_large_attitude_errors(body):
    rng = np.random.default_rng(3)
    for _ in range(20):
        x = rng.standard_normal(22)
        y = rng.standard_normal(22)
        x[6:10] = quat_from_rotvec(rng.uniform(-2, 2, 3))
        y[6:10] = quat_from_rotvec(rng.uniform(-2, 2, 3))
        back = boxplus(y, boxminus(x, y, body), body)
        if back[6] * x[6] < 0:
            back[6:10] *= -1
        np.testing.assert_allclose(back, x, atol=1e-12)


@pytest.mark.parametrize("body", [False, True])
def test_the_smoothed_covariance_is_about_the_smoothed_nominal(body):
    """A backward correction as large as a filter's attitude error (0.1 rad) turns the
    error coordinates: the exact errors of states drawn about the filter's nominal,
    measured from the smoothed one (the exact maps, not the first-order ones), are what
    the smoothed covariance describes (mean NEES 12 over the navigation block). Without
    the correction's reset Jacobian the tight pitch takes the roll's variance (NEES far
    above 12), which is what this test would see."""
    rng = np.random.default_rng(11)
    n = LAYOUT.n
    nf = _fake(n)
    nf.in_body_frame = lambda: body
    nf.set_mean(np.r_[np.zeros(3), [60.0, 0.0, 0.0], np.zeros(n - 6)])
    log = SmootherLog(n)
    log.posterior(nf)
    x_j = SmootherLog.nominal(nf)
    sd = np.r_[[1.0, 1.0, 2.0], [0.05, 0.01, 0.02], [0.005, 0.0002, 0.0005], np.full(n - 9, 0.01)]
    corr_unit = rng.standard_normal((n, n)) * 0.1 + np.eye(n)
    p_start = corr_unit @ corr_unit.T
    p_start = p_start / np.sqrt(np.outer(np.diag(p_start), np.diag(p_start))) * np.outer(sd, sd)
    d = np.zeros(n)
    d[ATT] = [0.02, -0.03, 0.1]
    d[3:6] = [0.3, -0.2, 0.1]
    log.lag.start(p_start, np.eye(n))
    log.lag.d_start = d
    log.lag.cross = 0.1 * p_start
    nf.t_s = 0.01
    log.posterior(nf)  # the next epoch: smoothed = filtered, so row 0 is x_j [+] d, p_start
    rows, restarts = log.smooth(LAYOUT)
    assert restarts == 0
    _t, pos, vel, quat, w, _bias, cov = rows[0]
    draws = rng.multivariate_normal(d, p_start, size=20000)
    errs = []
    for delta in draws:
        x_true = boxplus(x_j, delta, body)
        att = boxminus(
            np.r_[np.zeros(6), x_true[6:10], np.zeros(n - 9)],
            np.r_[np.zeros(6), quat, np.zeros(n - 9)],
        )[ATT]
        errs.append(np.r_[x_true[0:3] - pos, x_true[3:6] - vel, att, x_true[10:13] - w])
    errs = np.array(errs)
    nees = np.einsum("ei,ei->e", errs, np.linalg.solve(cov, errs.T).T)
    # 20000 draws of a chi-square(12): the mean's sd is 0.035
    assert abs(nees.mean() - 12.0) < 0.2
    raw = np.einsum("ei,ei->e", errs, np.linalg.solve(p_start[:12, :12], errs.T).T)
    assert raw.mean() > 13.0


def _ngnav(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ngnav", *args], capture_output=True, text=True, cwd=cwd
    )


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("smooth") / "run"
    # the array at 200 Hz: the whole flight in a few seconds
    got = _ngnav(
        "simulate", "--scenario", "tactical", "--set", "run.rate_hz=200", "--out", str(run)
    )
    assert got.returncode == 0, got.stderr
    return run


def test_run_smooth_writes_smoothed_estimates_better_than_the_filter(short_run):
    got = _ngnav("run", str(short_run), "--smooth")
    assert got.returncode == 0, got.stderr
    filt = read_estimates_csv(short_run / "estimates.csv")
    sm = read_estimates_csv(short_run / "estimates.smoothed.csv")
    np.testing.assert_array_equal(sm.t_s, filt.t_s)
    est, final = read_estimates_npz(short_run / "estimates.smoothed.npz")
    assert est.cov_nav.shape == (sm.t_s.shape[0], 12, 12) and final is not None
    lines = {
        ln.split(" against")[0].strip(): ln for ln in got.stdout.splitlines() if "against" in ln
    }
    rms = {k: float(v.split("roll/pitch/yaw RMS ")[1].split("/")[0]) for k, v in lines.items()}
    # fixed seed: the smoothed roll is at least twice as good as the filter's
    assert rms["smoothed"] < 0.5 * rms["filter"], got.stdout


def test_run_smooth_refuses_a_tlog_output(short_run, tmp_path):
    got = _ngnav("run", str(short_run), "--smooth", "--out", str(tmp_path / "x.tlog"))
    assert got.returncode != 0
    assert "--smooth writes CSV and NPZ" in got.stderr and "Traceback" not in got.stderr


def test_consistency_judges_the_smoothed_estimates(tmp_path):
    got = _ngnav(
        "consistency",
        "--scenario",
        "tactical",
        "--set",
        "run.rate_hz=200",
        "--runs",
        "2",
        "--first",
        "3",
        "--workers",
        "1",
        "--smooth",
        "--json",
        "--save",
        str(tmp_path),
    )
    assert got.returncode == 0, got.stderr
    out = json.loads(got.stdout)
    # another draw: runs 3 and 4
    assert out["first_run"] == 3 and out["runs"] == 2
    assert sorted(p.name for p in tmp_path.glob("run_*.npz")) == ["run_00003.npz", "run_00004.npz"]
    sm = out["smoothed"]
    # fixed seeds: the smoother beats the filter on both runs; no posterior failed
    assert 0 < sm["att_rms_ratio_max"] < 1 and 0 < sm["rate_rms_ratio_max"] < 1
    assert sm["restarts"] == 0


def test_the_python_api_runs_a_smoothed_campaign():
    from ngnav import api

    out = api.consistency("tactical", 2, overrides=["run.rate_hz=200"], workers=1, smooth=True)
    assert out["runs"] == 2 and not out["diverged"]
    assert 0 < out["smoothed"]["att_rms_ratio_max"] < 1
