"""One run through the whole chain: array solve, compensation, EKF, GPS updates.

``run_filter`` takes what a user has (array samples, GPS fixes, the run's
configuration) and returns estimates with their covariance, the GPS
innovations, and counts of everything skipped, held or rejected. The same
function serves simulated and recorded runs.

Compensation (paper eq. 22) works at the filter rate: the motion of the next
block (rate, angular acceleration, specific force: the block means) is
forecast from the last ``window`` blocks by the chosen predictor, and the
mounting-error term ``S E phi_hat`` is removed from every sample of the block.
At the paper's 100 Hz this is exactly its one-step-ahead forecast; at a 1 kHz
array each block's samples share the forecast of their mean. The rate history
is the filter's own rate estimate, so the compensation does not drift.

- ``gm11``, ``line``, ``last``: nominal solve, calibrated ``E``, that predictor;
- ``none``: nominal solve, no correction;
- ``oracle``: the solve of the *true* geometry (simulation only): no
  mounting error at all, the best any compensation could do.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update

from filters.ekf import FilterNoise, NavFilter
from filters.state import ATT, B_F, POS, RATE, VEL
from ngnav.compensation import _QUAD_I, _QUAD_J
from ngnav.conventions import G0_MPS2
from ngnav.flight import FlightTruth, quat_from_euler
from ngnav.frontend import ArraySolver
from ngnav.geodesy import LocalTangentPlane
from ngnav.gps import GpsFixes
from ngnav.layout import ArrayLayout, kinematic_features, rate_quadratics
from ngnav.predictors import GreyPredictor, LastValuePredictor, LinePredictor
from ngnav.records import ArraySamples, freeze_fields
from ngnav.rotation import dcm_from_quat, euler_from_quat
from ngnav.runconfig import RunConfig

#: Consecutive rejected GPS positions after which the filter is put back on the fix.
RESET_AFTER_REJECTS = 25
#: Time constant of the angular acceleration the position states' Jacobian uses, s.
WDOT_SMOOTHING_S = 0.05
#: Rate of the zero-sideslip pseudo-measurement (when configured), Hz.
SIDESLIP_RATE_HZ = 5.0
#: Horizontal speed above which a GPS course can set the heading, m/s.
COURSE_MIN_SPEED_MPS = 5.0


@dataclass(frozen=True)
class Estimates:
    """Filter output at every block end (E epochs).

    Attributes
    ----------
    t_s : array (E,)
    pos_ned_m, vel_ned_mps, omega_b_rps : arrays (E, 3)
    q_nb : array (E, 4)
    bias : array (E, k)
        Feature-bias estimates ``[wdot(3), f(3), quad(nq)]``.
    cov_nav : array (E, 12, 12)
        Covariance of the navigation error states (position, velocity,
        attitude (NED), rate), see :mod:`filters.state`.
    bound_nav : array (E, 12, 12) or None
        The same filter's covariance linearised at the truth (simulations).
    """

    t_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    q_nb: np.ndarray
    omega_b_rps: np.ndarray
    bias: np.ndarray
    cov_nav: np.ndarray
    bound_nav: np.ndarray | None = None

    def __post_init__(self) -> None:
        freeze_fields(
            self,
            {"t_s": (), "pos_ned_m": (3,), "vel_ned_mps": (3,), "q_nb": (4,), "omega_b_rps": (3,)},
        )


@dataclass(frozen=True)
class GpsInnovations:
    """Innovation statistics of every fix the filter saw (M,)."""

    t_s: np.ndarray
    nis_pos: np.ndarray
    nis_vel: np.ndarray
    pos_accepted: np.ndarray
    vel_accepted: np.ndarray


@dataclass(frozen=True)
class RunResult:
    """Estimates, GPS innovations, rate-measurement NIS and the run's counters.

    ``rate_dim`` is the rate measurement's size, ``state_size`` the error state's.
    """

    estimates: Estimates
    innovations: GpsInnovations
    rate_nis: np.ndarray
    counts: dict[str, int]
    compensation: str
    rate_dim: int = field(default=3)
    state_size: int = 0


def _predictor(name: str, window: int, shift: np.ndarray):
    if name == "gm11":
        return GreyPredictor(window=window, shift=shift)
    if name == "line":
        return LinePredictor(window=window)
    if name == "last":
        return LastValuePredictor()
    return None


def filter_noise(solver: ArraySolver, cfg: RunConfig) -> FilterNoise:
    """Feature noise and bias model from the channel model, mapped through the solver."""
    s = solver.solve_matrix
    # a floor of 1e-6 m/s^2 keeps the prior positive definite when a config says "no bias"
    b0 = np.maximum(cfg.turn_on_bias_mps2, 1e-6)
    return FilterNoise(
        feature_cov=solver.covariance(),
        bias_prior_cov=s @ np.diag(b0**2) @ s.T,
        bias_rw_cov=s @ np.diag(cfg.bias_rw_mps2_rts**2) @ s.T,
        position_sigma_m=cfg.position_sigma_m,
    )


def _static_tilt(f_b: np.ndarray) -> tuple[float, float]:
    roll = float(np.arctan2(-f_b[1], -f_b[2]))
    pitch = float(np.arctan2(f_b[0], np.hypot(f_b[1], f_b[2])))
    return roll, pitch


def run_filter(
    samples: ArraySamples,
    fixes: GpsFixes,
    cfg: RunConfig,
    *,
    compensation: str | None = None,
    use_gps: bool = True,
    true_layout: ArrayLayout | None = None,
    truth: FlightTruth | None = None,
    bound: bool = False,
    progress=None,
) -> RunResult:
    """Run the GPS/array filter over a whole run.

    Parameters
    ----------
    samples : ArraySamples
        Channel outputs (T, N), m/s^2, uniformly sampled; non-finite rows are held.
    fixes : GpsFixes
        GPS fixes; the first one at or after the alignment sets position and velocity.
    cfg : RunConfig
        What the filter knows (see :mod:`ngnav.runconfig`).
    compensation : str, optional
        Override ``cfg.filter.compensation``.
    use_gps : bool
        False runs the array alone after initialisation (the drift).
    true_layout : ArrayLayout, optional
        The true geometry; required by ``compensation="oracle"``.
    truth : FlightTruth, optional
        Exact truth on the samples' times; required by ``compensation="oracle"``.
    bound : bool
        Also run the covariance recursion linearised at ``truth`` (the bound).
    progress : callable, optional
        Called with the fraction done (0..1) now and then.

    Raises
    ------
    ValueError
        Bad configuration, a rate-aided layout, no usable GPS fix, no valid sample.
    filters.ekf.CovarianceError
        If the covariance stops being symmetric positive definite.
    """
    method = compensation or cfg.filter.compensation
    n = cfg.layout.n_sensors
    if samples.n_channels != n:
        raise ValueError(f"config layout has {n} channels, the array data has {samples.n_channels}")
    if method == "oracle" and (true_layout is None or truth is None):
        raise ValueError("compensation 'oracle' needs the true geometry and motion (simulations)")
    solver = ArraySolver(cfg.layout, cfg.noise_sigma_mps2)
    if solver.rate_aided:
        raise ValueError(
            f"layout {cfg.layout.name!r} cannot solve its rate terms; the filter needs a layout "
            "that solves angular acceleration, force and rate products (e.g. nine-cube)"
        )
    cols = solver.solved_columns
    quad_cols = cols[cols >= 6] - 6
    pairs = np.column_stack([_QUAD_I[quad_cols], _QUAD_J[quad_cols]])
    smat = solver.solve_matrix
    se = None
    if method in ("gm11", "line", "last"):
        se = smat @ cfg.known_errors.error_matrix(cfg.layout)  # (k, 12)

    raw = samples.accel_mps2
    t = samples.t_s
    n_t = t.shape[0]
    dt = float(np.median(np.diff(t)))
    counts: dict[str, int] = {}
    finite = np.all(np.isfinite(raw), axis=1)
    with np.errstate(invalid="ignore"):
        saturated = finite & np.any(np.abs(raw) >= cfg.range_mps2 * (1 - 1e-9), axis=1)
    invalid = ~finite | saturated
    counts["samples held (non-finite)"] = int(np.count_nonzero(~finite))
    counts["samples held (saturated)"] = int(np.count_nonzero(saturated))
    a = (np.where(invalid[:, None], cfg.offset_mps2, raw) - cfg.offset_mps2) / cfg.scale
    sa = a @ smat.T  # (T, k) solved features, before compensation
    if method == "oracle":
        # the exact mounting-error term: true geometry, true motion
        e_true = true_layout.design - cfg.layout.design
        phi_true = kinematic_features(truth.omega_dot_b_rps2, truth.f_b_mps2, truth.omega_b_rps)
        sa -= phi_true @ (smat @ e_true).T

    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    fix_ned = (
        ltp.to_ned(fixes.lat_deg, fixes.lon_deg, fixes.alt_m) if len(fixes) else np.zeros((0, 3))
    )
    fix_sig = np.column_stack([fixes.h_acc_m, fixes.h_acc_m, fixes.v_acc_m])
    fix_idx = np.clip(np.rint((fixes.t_s - t[0]) / dt).astype(int), 0, n_t - 1)
    inside = (fixes.t_s >= t[0] - dt / 2) & (fixes.t_s <= t[-1] + dt / 2)
    counts["gps fixes outside the array's time span"] = int(np.count_nonzero(~inside))

    ini = cfg.initial
    i_align = 0
    if ini.alignment == "static":
        i_align = int(np.searchsorted(t, t[0] + ini.static_s))
    cand = np.flatnonzero(inside & (fix_idx >= i_align))
    if cand.size == 0:
        raise ValueError("no GPS fix after the alignment period: cannot set position and velocity")
    first = int(cand[0])
    i_start = int(fix_idx[first])

    noise = filter_noise(solver, cfg)
    if method == "oracle":
        # the oracle removes the whole geometry error: nothing left to estimate
        noise = replace(noise, position_sigma_m=0.0)
    nf = NavFilter(
        noise,
        pairs,
        cfg.antenna_b_m,
        cfg.filter.gate_probability,
        sensor_axes_b=cfg.layout.axes_b,
        solve_matrix=smat,
    )
    nq = pairs.shape[0]
    g_ranges = np.repeat(
        [
            np.deg2rad(cfg.filter.rate_range_dps),
            cfg.range_mps2 / (cfg.layout.lever_arm_m or 0.1),
            cfg.range_mps2,
        ],
        3,
    )
    predictor = _predictor(method, cfg.filter.window, g_ranges)
    window = predictor.window if predictor is not None else 1

    # --- initial attitude
    yaw0 = np.deg2rad(ini.yaw_deg)
    if ini.alignment == "static":
        span = slice(0, max(i_start, 1) + 1)
        ok = ~invalid[span]
        if not np.any(ok):
            raise ValueError("no valid array sample in the static alignment period")
        f_mean = sa[span][ok].mean(axis=0)
        if se is not None:
            phi = np.zeros(12)
            for _ in range(3):
                phi[3:6] = f_mean[3:6] - (se @ phi)[3:6]
            f_b = phi[3:6]
        else:
            f_b = f_mean[3:6]
        roll0, pitch0 = _static_tilt(f_b)
        # at rest the angular-acceleration and rate-product means are their biases
        static_mean = f_mean - (se @ phi if se is not None else 0.0)
        n_avg = int(np.count_nonzero(ok))
        tilt_noise = np.sqrt(noise.feature_cov[3, 3] / n_avg) / G0_MPS2
        att_sigma = np.array([tilt_noise, tilt_noise, np.deg2rad(ini.heading_sigma_deg)])
    else:
        roll0, pitch0 = np.deg2rad(ini.roll_deg), np.deg2rad(ini.pitch_deg)
        ts = np.deg2rad(ini.tilt_sigma_deg)
        att_sigma = np.array([ts, ts, np.deg2rad(ini.heading_sigma_deg)])
    heading_pending = ini.heading_source == "gps"
    if heading_pending:
        att_sigma[2] = np.deg2rad(30.0)
    q0 = quat_from_euler(roll0, pitch0, yaw0)
    c0 = dcm_from_quat(q0)
    nf.initialise(
        t[i_start],
        fix_ned[first] - c0 @ cfg.antenna_b_m,
        fixes.vel_ned_mps[first],
        q0,
        np.zeros(3),
        fix_sig[first],
        fixes.vel_acc_mps[first],
        att_sigma,
        np.deg2rad(ini.rate_sigma_dps),
    )
    if ini.alignment == "static":
        # the levelled attitude absorbs the horizontal force bias: correlate them exactly
        jm = np.zeros((2, 3))
        jm[0, 1] = 1.0 / G0_MPS2
        jm[1, 0] = -1.0 / G0_MPS2
        j = np.zeros((2, nf.layout.n))
        j[:, B_F] = jm @ c0
        p = nf.P
        p[6:8, :] = j @ p
        p[:, 6:8] = p[6:8, :].T
        p[6:8, 6:8] = j @ nf.P @ j.T + np.eye(2) * tilt_noise**2
        p[6:8, 8] = 0.0
        p[8, 6:8] = 0.0
        nf.P = p
        nf.update_static_biases(static_mean, n_avg)
        nf.check_covariance("static alignment")

    # --- bound: the same covariance recursion, linearised at the truth
    if truth is not None:
        if truth.t_s.shape != t.shape or not np.allclose(truth.t_s, t):
            raise ValueError("truth must be sampled at the array's sample times")
    p_bound = None
    if bound:
        if truth is None:
            raise ValueError("the bound needs the truth")
        p_bound = nf.P.copy()
        w_true = truth.omega_b_rps
        c_true = dcm_from_quat(truth.q_nb)

    # --- block boundaries: every K samples and at every fix
    k_reg = max(1, round(1.0 / (cfg.filter.rate_hz * dt)))
    ends = set(range(i_start + k_reg, n_t, k_reg))
    use_fix = np.zeros(len(fixes), dtype=bool)
    use_fix[cand] = True
    use_fix[first] = False
    ends.update(int(i) for i in fix_idx[use_fix] if i > i_start)
    ends.add(n_t - 1)
    ends_arr = np.array(sorted(e for e in ends if e > i_start))
    fixes_at: dict[int, list[int]] = {}
    for m in np.flatnonzero(use_fix):
        fixes_at.setdefault(int(fix_idx[m]), []).append(int(m))

    n_e = ends_arr.shape[0] + 1
    k_feat = cols.shape[0]
    est_t = np.empty(n_e)
    est_p = np.empty((n_e, 3))
    est_v = np.empty((n_e, 3))
    est_q = np.empty((n_e, 4))
    est_w = np.empty((n_e, 3))
    est_b = np.empty((n_e, k_feat))
    est_cov = np.empty((n_e, 12, 12))
    est_bound = np.empty((n_e, 12, 12)) if p_bound is not None else None

    def record(e: int) -> None:
        est_t[e] = nf.t_s
        est_p[e], est_v[e], est_q[e], est_w[e] = nf.pos, nf.vel, nf.q, nf.w
        est_b[e] = nf.bias
        est_cov[e] = nf.P[:12, :12]
        if est_bound is not None:
            est_bound[e] = p_bound[:12, :12]

    record(0)
    seed_block = sa[max(0, i_start - k_reg) : i_start + 1]
    seed_ok = ~invalid[max(0, i_start - k_reg) : i_start + 1]
    seed_mean = seed_block[seed_ok].mean(axis=0) if np.any(seed_ok) else np.zeros(k_feat)
    hist = np.empty((n_e + window, 9))
    # the forecast history holds motion: block means less the current bias estimates
    hist[:window] = np.concatenate([nf.w, seed_mean[0:6] - nf.bias[0:6]])
    last_mean = seed_mean.copy()
    first_row = sa[i_start] if not invalid[i_start] else seed_mean
    if se is not None:
        h0 = hist[0]
        first_row = first_row - se @ np.concatenate([h0[3:6], h0[6:9], rate_quadratics(h0[0:3])])
    nf.set_last_sample(first_row[0:3], first_row[3:6])
    inn_t, inn_p, inn_v, inn_pa, inn_va = [], [], [], [], []
    rate_nis = []
    n_fallbacks = 0
    with_dr = nf.layout.n_dr > 0
    slip_sigma = np.deg2rad(cfg.filter.sideslip_sigma_deg)
    gap_reset_s = cfg.filter.gps_gap_reset_s
    t_last_slip = -np.inf
    wd_smooth = np.zeros(3)
    smooth_gain = min(1.0, 1.0 / (WDOT_SMOOTHING_S * cfg.filter.rate_hz))
    phi_hat = np.zeros(12) if predictor is not None else None
    full_check_every = max(1, round(cfg.filter.rate_hz))  # the Cholesky check once a second
    i0 = i_start
    for e, i1 in enumerate(ends_arr, start=1):
        xs = sa[i0 + 1 : i1 + 1].copy()
        bad = invalid[i0 + 1 : i1 + 1]
        kk = xs.shape[0]
        if predictor is not None:
            x_hat, nfb = predictor.forecast(hist[e - 1 : e - 1 + window], e - 1)
            n_fallbacks += nfb
            wx, wy, wz = x_hat[0:3].tolist()
            phi_hat[0:6] = x_hat[3:9]
            phi_hat[6:] = (wx * wx, wy * wy, wz * wz, wy * wz, wx * wz, wx * wy)
            xs -= se @ phi_hat
        if np.any(bad):
            fill = last_mean if phi_hat is None else phi_hat[cols] + nf.bias
            xs[bad] = fill
        n_ok = kk - int(np.count_nonzero(bad))
        sg = sg_true = None
        if with_dr:
            # The sensor-position states see the block's angular acceleration as
            # forecast from the *previous* blocks (the compensation's forecast, or a
            # smoothed history without one): this block's own noise would correlate
            # the Jacobian with the rate measurement's noise and drag dr.
            wd_sg = wd_smooth if phi_hat is None else phi_hat[0:3]
            sg = nf.geometry_jacobian(wd_sg, nf.w + 0.5 * kk * dt * wd_sg)
            if p_bound is not None:
                blk = slice(i0 + 1, i1 + 1)
                sg_true = nf.geometry_jacobian(
                    truth.omega_dot_b_rps2[blk].mean(axis=0), w_true[blk].mean(axis=0)
                )
        w_blk = nf.propagate(xs[:, 0:3], xs[:, 3:6], dt, sg)
        if p_bound is not None:
            f_n_true = np.mean(
                np.einsum("kij,kj->ki", c_true[i0 + 1 : i1 + 1], truth.f_b_mps2[i0 + 1 : i1 + 1]),
                axis=0,
            )
            fb, qb = nf.propagation_matrices(kk, dt, c_true[i0], f_n_true, sg_true)
            _, p_bound = kf_predict(np.zeros(nf.layout.n), p_bound, fb, qb)
        if n_ok and nq:
            quad = xs[:, 6:] if n_ok == kk else xs[~bad, 6:]
            nis = nf.update_rate(quad.sum(axis=0) * (1.0 / n_ok), w_blk, n_ok, sg)
            rate_nis.append(np.nan if nis is None else nis)
            if p_bound is not None and nis is not None and nis <= nf.gate_q:
                _, hb = nf.rate_model(w_true[i0 + 1 : i1 + 1], sg_true)
                _, p_bound = kf_update(
                    np.zeros(nf.layout.n),
                    p_bound,
                    np.zeros(nq),
                    noise.feature_cov[6:, 6:] / n_ok,
                    hb,
                )
        good = xs[~bad] if 0 < n_ok < kk else xs
        last_mean = good.sum(axis=0) * (1.0 / good.shape[0])
        hist[e - 1 + window] = np.concatenate([nf.w, last_mean[0:6] - nf.bias[0:6]])
        wd_smooth += smooth_gain * (last_mean[0:3] - nf.bias[0:3] - wd_smooth)
        for m in fixes_at.get(int(i1), []):
            if not use_gps:
                continue
            gap = gap_reset_s > 0 and nf.t_s - nf.t_last_position_fix > gap_reset_s
            res = nf.update_gps(
                fix_ned[m],
                fixes.vel_ned_mps[m],
                fix_sig[m],
                fixes.vel_acc_mps[m],
                fixes.t_s[m] - nf.t_s,
                reset=gap,
            )
            inn_t.append(fixes.t_s[m])
            inn_p.append(res.nis_pos)
            inn_v.append(res.nis_vel)
            inn_pa.append(res.pos_accepted)
            inn_va.append(res.vel_accepted)
            if p_bound is not None:
                _, _, hp, hv = nf.gps_model(truth.q_nb[i1], w_true[i1])
                if res.pos_accepted:
                    _, p_bound = kf_update(
                        np.zeros(nf.layout.n), p_bound, np.zeros(3), np.diag(fix_sig[m] ** 2), hp
                    )
                if res.vel_accepted:
                    _, p_bound = kf_update(
                        np.zeros(nf.layout.n),
                        p_bound,
                        np.zeros(3),
                        np.eye(3) * fixes.vel_acc_mps[m] ** 2,
                        hv,
                    )
            if nf.consecutive_position_rejects >= RESET_AFTER_REJECTS:
                nf.reset_to_fix(fix_ned[m], fixes.vel_ned_mps[m], fix_sig[m], fixes.vel_acc_mps[m])
            if heading_pending:
                vh = fixes.vel_ned_mps[m][:2]
                speed = float(np.hypot(*vh))
                if speed > COURSE_MIN_SPEED_MPS:
                    course_sigma = float(np.arctan2(3 * fixes.vel_acc_mps[m], speed))
                    nf.set_heading(float(np.arctan2(vh[1], vh[0])), course_sigma)
                    heading_pending = False
        if slip_sigma > 0 and use_gps and nf.t_s - t_last_slip >= 1.0 / SIDESLIP_RATE_HZ - dt / 2:
            # the vehicle model holds with or without fixes (outages included)
            t_last_slip = nf.t_s
            nis_s = nf.update_sideslip(slip_sigma, COURSE_MIN_SPEED_MPS)
            if p_bound is not None and nis_s is not None and nis_s <= nf.gate1:
                v_true = truth.vel_ned_mps[i1]
                _, hs = nf.sideslip_model(truth.q_nb[i1], v_true)
                r_s = (np.hypot(v_true[0], v_true[1]) * np.tan(slip_sigma)) ** 2
                _, p_bound = kf_update(
                    np.zeros(nf.layout.n), p_bound, np.zeros(1), np.array([[r_s]]), hs
                )
        nf.check_covariance("block", full=int(i1) in fixes_at or e % full_check_every == 0)
        record(e)
        i0 = i1
        if progress is not None and e % 2000 == 0:
            progress(e / len(ends_arr))
    counts.update(
        {
            "blocks": nf.counters.blocks,
            "samples used": nf.counters.samples,
            "samples before the filter start": i_start,
            "gps fixes used": nf.counters.gps_used,
            "gps positions rejected (gate)": nf.counters.gps_rejected_pos,
            "gps velocities rejected (gate)": nf.counters.gps_rejected_vel,
            "gps resets after rejections": nf.counters.gps_resets,
            "gps resets after an outage": nf.counters.gps_gap_resets,
            "rate updates": nf.counters.rate_updates,
            "rate updates rejected (gate)": nf.counters.rate_rejected,
            "sideslip updates": nf.counters.sideslip_used,
            "sideslip updates rejected (gate)": nf.counters.sideslip_rejected,
            "grey forecasts fallen back": n_fallbacks,
        }
    )
    estimates = Estimates(est_t, est_p, est_v, est_q, est_w, est_b, est_cov, est_bound)
    innovations = GpsInnovations(
        np.array(inn_t),
        np.array(inn_p),
        np.array(inn_v),
        np.array(inn_pa, dtype=bool),
        np.array(inn_va, dtype=bool),
    )
    return RunResult(estimates, innovations, np.array(rate_nis), counts, method, nq, nf.layout.n)


def geodetic_estimates(est: Estimates, cfg: RunConfig) -> tuple[np.ndarray, ...]:
    """Latitude, longitude (deg) and altitude (m) of the estimated positions."""
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    return ltp.to_geodetic(est.pos_ned_m)


def euler_deg(q_nb: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (deg) of quaternions (..., 4)."""
    return np.rad2deg(euler_from_quat(q_nb))


__all__ = [
    "ATT",
    "POS",
    "RATE",
    "VEL",
    "Estimates",
    "GpsInnovations",
    "RunResult",
    "filter_noise",
    "run_filter",
]
