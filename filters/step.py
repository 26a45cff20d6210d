"""One filter step (block): compensation, propagation, rate update, fixes, vehicle models."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update

from filters import kernels
from filters.alignment import _gps_course
from filters.forecast import (
    FORECAST_ERROR_BLOCKS,
    FORECAST_ERROR_GATE,
    HOLD_FORCE_SIGMA_MPS2,
    HOLD_WDOT_SIGMA_RPS2,
)
from filters.supervision import (
    COURSE_MIN_SPEED_MPS,
    GPS_GAP_RESET_S,
    LOST_TILT_SIGMA_DEG,
    MODEL_PAUSE_AFTER_VELOCITY_REJECTS,
    REOPEN_AFTER_VELOCITY_REJECTS,
    REOPEN_MIN_INTERVAL_S,
    REOPEN_RATE_SIGMA_RPS,
    REOPEN_TILT_SIGMA_RAD,
    RESET_AFTER_REJECTS,
    heading_sigma_rad,
    tilt_sigma_rad,
)
from filters.updates import update_correlated
from filters.vehicle_model import (
    LATERAL,
    SIDESLIP_RATE_HZ,
    VERTICAL,
    load_extrapolation_weights,
)
from ngnav.errors import LostTrackError
from ngnav.rotation import dcm_from_quat

#: How far (in its noise's sigmas) the angular acceleration the sensor positions' Jacobian
#: reads must stand from zero to be read at all (see ``StepMixin._block``).
WDOT_JACOBIAN_CLEAR_SIGMAS = 3.0
#: Its square, as :func:`filters.kernels.shrink` takes it (``algebra.shrink_to_size``).
_WDOT_CLEAR2 = WDOT_JACOBIAN_CLEAR_SIGMAS * WDOT_JACOBIAN_CLEAR_SIGMAS


class StepMixin:
    """The block's chain, and the noise the forecast and held samples add."""

    def _block(self, i1: int) -> None:
        nf = self.nf
        dt = self.dt
        se = self._se
        truth = self.truth
        p_bound = self._p_bound
        nq = self._nq
        i0 = self._i0
        b = self._base
        excluded = 0
        if self._excluded:  # a channel excluded somewhere (the marks only ever grow)
            excluded = int(np.bitwise_or.reduce(self._excl[i0 + 1 - b : i1 + 1 - b]))
        if excluded != self._filter_mask:
            self._switch_solve(excluded)
            se = self._se
        xs = self._features(i0 + 1, i1 + 1, excluded, nf.w)
        bad, n_bad = self._count_held(i0 + 1, i1 + 1, excluded)
        kk = xs.shape[0]
        window = self._window
        e = self._e + 1
        row = self._h_n
        phi_hat = self._phi_hat
        if self.predictor is not None:
            x_hat, nfb = self.predictor.forecast(self._hist[row - window : row], e - 1)
            self.n_fallbacks += nfb
            self.block_fallbacks = nfb
            kernels.compensate(xs, x_hat, se, phi_hat)
        self.block_faulty = excluded
        if n_bad:
            fill = self._last_mean if phi_hat is None else phi_hat[self._cols] + nf.bias
            xs[bad] = fill
            self.block_faulty |= int(np.bitwise_or.reduce(self._chmask[i0 + 1 - b : i1 + 1 - b]))
        n_ok = kk - n_bad
        sg = sg_true = None
        if self._with_geo:
            # The sensor-position states see the block's angular acceleration as
            # forecast from the *previous* blocks (the compensation's forecast, or a
            # smoothed history without one): this block's own noise would correlate
            # the Jacobian with the rate measurement's noise and drag dr. Shrunk by its
            # noise: on uav-survey that noise (0.013 rad/s^2) outweighs the rate terms
            # (|w|^2 0.008 rad^2/s^2), and read as motion it made the 27 states and the
            # attitude over-sure (docs/design.md, "the sensor positions' Jacobian").
            # The sensing-axis states read the specific force at each sensor, from the
            # same forecast (the last block's mean less the biases without one).
            # Within WDOT_JACOBIAN_CLEAR_SIGMAS of its noise it reads zero: that noise is in
            # the rate's error too (the rate integrates it), so the rate products'
            # innovation and this Jacobian shared it and the states drifted (the lever arms
            # 0.6-0.9 % long by uav-survey's end on a truth without mounting errors; notes,
            # "The turns' forward-velocity error").
            wd_sg = self._wd_smooth if phi_hat is None else phi_hat[0:3]
            if nf.layout.n_cal:
                wd_sg = kernels.shrink(wd_sg, self.wdot_jacobian_var * (1.0 / kk), _WDOT_CLEAR2)
                f_sg = self._last_mean[3:6] - nf.bias[3:6] if phi_hat is None else phi_hat[3:6]
                sg = nf.geometry_sg(f_sg, wd_sg, nf.w + 0.5 * kk * dt * wd_sg)
            else:  # the positions alone: the same, in one kernel
                sg = kernels.position_sensitivity(
                    wd_sg,
                    self.wdot_jacobian_var,
                    1.0 / kk,
                    _WDOT_CLEAR2,
                    nf.w,
                    0.5 * kk * dt,
                    nf.sensor_axes_b,
                    nf._solve_rep,
                )
            if p_bound is not None:
                blk = slice(i0 + 1, i1 + 1)
                sg_true = nf.geometry_sg(
                    truth.f_b_mps2[blk].mean(axis=0),
                    truth.omega_dot_b_rps2[blk].mean(axis=0),
                    truth.omega_b_rps[blk].mean(axis=0),
                )
        rest = self.rest
        if rest is not None:
            ok = False
            if rest.at_rest:
                # the rate at the block's start (the last block's end) is zero
                _, ok = nf.update_zero_rate(self._rest_sigma)
                if not ok:
                    rest.interrupt(nf.t_s)
            # reset to zero, the rate's error over this block is this block's noise
            nf.rate_reset_each_block = ok
            if ok and p_bound is not None:
                _, p_bound = kf_update(
                    np.zeros(nf.layout.n),
                    p_bound,
                    np.zeros(3),
                    np.eye(3) * self._rest_sigma**2,
                    nf.rate_at_rest_model(),
                )
        log = self.smoother
        if log is not None:
            log.posterior(nf)
        w_blk = nf.propagate(xs[:, 0:3], xs[:, 3:6], dt, sg)
        if n_ok < kk or self._t_hold > 0.0:
            self._hold_noise(bad, dt)
        if p_bound is not None:
            c_true = self._c_true
            f_n_true = np.mean(
                np.einsum("kij,kj->ki", c_true[i0 + 1 : i1 + 1], truth.f_b_mps2[i0 + 1 : i1 + 1]),
                axis=0,
            )
            fb, qb = nf.propagation_matrices(kk, dt, c_true[i0], f_n_true, sg_true)
            _, p_bound = kf_predict(np.zeros(nf.layout.n), p_bound, fb, qb)
        quad_mean, r_all = self._mean_bufs  # the mean rate products, the error's share
        self._last_mean, d, corrected = kernels.block_means(
            xs,
            bad,
            n_ok,
            nq,
            nf.bias[0:6],
            kernels.NO_VECTOR if phi_hat is None else phi_hat[0:6],
            kernels.ABSENT if self._se is None else self._se[:, 0:6],
            self._fe_correct,
            quad_mean,
            r_all,
        )
        if phi_hat is not None:
            self.last_forecast_error = d
            if self._fe_persistence > 0.0:
                self._forecast_noise(d, n_ok, kk * dt)
            if corrected:
                # what the forecast's error left in the block, out of the state and history
                # before the rate products are compared, from them too (kernels.block_means
                # took it out of the means): left in, the rate update took the rate error it
                # made for the sensor positions' doing (their NEES, 27 dof, rose from 30 to
                # 51 over tactical's flight, 24 runs; 38 so; design notes, "the forecast's
                # error out before the rate products")
                w_blk = nf.remove_feature_residual(r_all[0:6], kk * dt, w_blk, dt)
        if n_ok and nq:
            held = bad if n_ok < kk else None
            nis = nf.update_rate(quad_mean, w_blk, n_ok, sg, held)
            self.last_rate_nis = np.nan if nis is None else nis
            if nis is not None:
                self.monitor.observe_parity(
                    nf.t_s, nf.last_rate_innovation, nf.last_rate_innovation_cov
                )
                for channels, t_s in self.monitor.take_ambiguous():
                    self._suspect(channels, t_s)
                self._test_suspects()
                for channel, onset_s in self.monitor.take_isolations():
                    self._exclude_from(channel, onset_s)
            if self.keep_estimates:
                self._rate_nis.append(self.last_rate_nis)
                self._rate_nis_t.append(nf.t_s)
                self._rate_nis_dof.append(nf.rate_dof)
            if p_bound is not None and nis is not None and nis <= nf.gate_q:
                _, hb = nf.rate_model(truth.omega_b_rps[i0 + 1 : i1 + 1], sg_true)
                rows = nf.rate_rows  # the products still solved (channels excluded)
                cross = nf.rate_noise_cross(kk, dt, c_true[i0], held)
                _, p_bound = update_correlated(
                    np.zeros(nf.layout.n),
                    p_bound,
                    np.zeros(int(rows.sum())),
                    nf.noise.feature_cov[6:, 6:][np.ix_(rows, rows)] / n_ok,
                    hb[rows],
                    None if cross is None else cross[:, rows],
                )
        if row == self._hist.shape[0]:
            # a sliding window: keep the rows the next forecasts read
            self._hist[:window] = self._hist[row - window : row]
            row = window
        # the history's row: the rate and the block's [wdot, f], biases removed (with the
        # angle-of-attack state, in the same kernel as the load below)
        hist_row = self._hist[row]
        self._h_n = row + 1
        if rest is not None:
            rest.observe_block(nf.t_s, self._last_mean[0:6], n_ok)
        if not nf.layout.n_aoa:
            kernels.history_row(
                hist_row, nf.w, self._last_mean, nf.bias, self._wd_smooth, self._smooth_gain
            )
        else:
            # the block mean lags the block end by (k - 1) / 2 samples: extrapolate it
            # there (load_extrapolation_weights)
            # (measured: the lift law on tactical's 100 Hz block means was up to 0.07 deg
            # behind the truth in the roll-ins, exact on the block-end force)
            # (its noise: the block means' feature_cov / k, as the weights combine them)
            # (with sensor-position states the load, as the propagation, loses S G dr_hat,
            # and the angle's Jacobian sees dr through it)
            k_now = n_ok if 0 < n_ok < kk else kk  # the rows in the mean
            first = self._f_load_prev is None
            if first:
                w_now, w_prev, w2 = 1.0, 0.0, 1.0 / k_now
            else:
                w_now, w_prev = load_extrapolation_weights(kk, self._kk_load_prev)
                w2 = w_now**2 / k_now + w_prev**2 / self._k_load_prev
            sg_f = None if sg is None else sg[3:6]
            sg_prev = self._sg_load_prev
            f_mean, f_load, sg_load = kernels.history_and_load(
                hist_row,
                nf.w,
                self._last_mean,
                nf.bias,
                self._wd_smooth,
                self._smooth_gain,
                kernels.ABSENT if sg_f is None else sg_f,
                nf.geometry_estimates(),
                first,
                w_now,
                w_prev,
                kernels.NO_VECTOR if first else self._f_load_prev,
                kernels.ABSENT if sg_prev is None else sg_prev,
            )
            nf.set_load(
                f_load, load_cov=w2 * self._load_noise_cov, sg_f=None if sg_f is None else sg_load
            )
            self._f_load_prev, self._k_load_prev = f_mean, k_now
            self._kk_load_prev = kk
            self._sg_load_prev = sg_f
        fixes = []
        while self._pending and self._pending[0][0] == i1:
            fixes.append(self._pending.pop(0)[2])
        fixes.extend(self._late)
        self._late = []
        for fix in fixes:
            self._fuse_fix(fix, i1, p_bound)
            p_bound = self._p_bound
        if (
            (self._slip_sigma > 0 or self._aoa_sigma > 0)
            and self.use_gps
            and nf.t_s - self._t_last_slip >= 1.0 / SIDESLIP_RATE_HZ - dt / 2
            and nf.consecutive_velocity_rejects < MODEL_PAUSE_AFTER_VELOCITY_REJECTS
        ):
            # the vehicle model holds with or without fixes (outages included), but
            # not while the GPS velocities contradict the state (see the constant)
            self._t_last_slip = nf.t_s
            nis_s = nis_a = None
            if self._slip_sigma > 0:
                nis_s = nf.update_sideslip(self._slip_sigma, COURSE_MIN_SPEED_MPS)
            if self._aoa_sigma > 0:
                nis_a = nf.update_angle_of_attack(self._aoa_sigma, COURSE_MIN_SPEED_MPS)
            if p_bound is not None:
                v_true = truth.vel_ned_mps[i1]
                for axis, nis, sigma_v in (
                    (LATERAL, nis_s, np.hypot(v_true[0], v_true[1]) * np.tan(self._slip_sigma)),
                    (VERTICAL, nis_a, np.linalg.norm(v_true) * np.tan(self._aoa_sigma)),
                ):
                    if nis is not None and nis <= nf.gate1:
                        # the truth's angle of attack: the body x-z direction of its velocity
                        v_b = dcm_from_quat(truth.q_nb[i1]).T @ v_true
                        aoa_true = float(np.arctan2(v_b[2], v_b[0])) if nf.layout.n_aoa else 0.0
                        _, hs = nf.body_velocity_model(truth.q_nb[i1], v_true, axis, aoa_true)
                        r = sigma_v**2
                        if axis == VERTICAL:  # the load's noise is there at the truth too
                            r += nf.load_noise_var(truth.q_nb[i1], v_true, aoa_true)
                        _, p_bound = kf_update(
                            np.zeros(nf.layout.n), p_bound, np.zeros(1), np.array([[r]]), hs
                        )
        self._p_bound = p_bound
        if self._suspects is not None:
            self.block_faulty |= sum(1 << c for c in self._suspects[0])
        nf.check_covariance("block", full=bool(fixes) or e % self._full_check_every == 0)
        self._e = e
        self._i0 = i1
        if i1 >= self._next_grid:
            self._next_grid += self._k_reg
        self._record()
        if self.on_epoch is not None:
            self.on_epoch(self.latest)

    def _forecast_noise(self, d: np.ndarray, n_ok: int, t_s: float) -> None:
        """Add the error the compensation's forecast left in this block (the forecast's error).

        ``d`` (6,) is the block's compensated ``[wdot, f]`` mean less the bias estimates
        less its forecast: the forecast's error ``Delta`` (to ``(I + E) Delta``, ``E``
        a few per cent) plus noise, the block mean's own and what the forecast carries
        of its history's (``(1 + g) N / k`` per channel, ``g`` from
        :func:`ngnav.predictors.noise_gain`). Through a manoeuvre's onset ``Delta``
        is many times that noise; in steady flight it is below it. Its variance is
        tracked as a running mean of ``d^2`` over :data:`FORECAST_ERROR_BLOCKS` blocks
        less the noise floor, kept where positive (once some channel's mean passes
        :data:`FORECAST_ERROR_GATE` times its floor), and the compensation leaves
        ``E_6 Delta`` of it in the features (``E_6`` the compensation matrix's
        ``[wdot, f]`` block): the filter adds that covariance times
        ``filters.forecast.FORECAST_ERROR_PERSISTENCE`` over the block
        (:meth:`filters.ekf.NavFilter.add_forecast_noise`). The noise part of the
        forecast's error is already in the feature noise (:func:`filter_noise`).
        """
        if not np.all(np.isfinite(d)) or n_ok <= 0:
            return
        d2 = self._fe_d2
        d2 += (d * d - d2) * (1.0 / FORECAST_ERROR_BLOCKS)
        floor = self.forecast_error_floor * (1.0 / n_ok)
        if not np.any(d2 > FORECAST_ERROR_GATE * floor):
            return
        e6 = self._se[0:6, 0:6]
        cov = (e6 * np.maximum(d2 - floor, 0.0)) @ e6.T
        self.nf.add_forecast_noise(cov * self._fe_persistence, t_s)

    def _hold_noise(self, bad: np.ndarray, dt: float) -> None:
        """Add the forecast's error over the held runs of this block (see FilterSettings)."""
        t_run = self._t_hold
        for held in bad.tolist():
            if held:
                t_new = t_run + dt
                self.nf.add_hold_noise(t_run, t_new, HOLD_WDOT_SIGMA_RPS2, HOLD_FORCE_SIGMA_MPS2)
                t_run = t_new
            else:
                t_run = 0.0
        self._t_hold = t_run

    def _fuse_fix(self, fix: tuple, i1: int, p_bound: np.ndarray | None) -> None:
        if not self.use_gps:
            self.counts["gps fixes ignored (no GPS)"] += 1
            return
        self.counts["gps fixes through the gates"] += 1
        nf = self.nf
        truth = self.truth
        t_fix, ned, vel, sig, vacc, _ = fix
        gap_reset_s = GPS_GAP_RESET_S
        gap = gap_reset_s > 0 and nf.t_s - nf.t_last_position_fix > gap_reset_s
        resets_before = nf.counters.gps_resets + nf.counters.gps_gap_resets
        res = nf.update_gps(ned, vel, sig, vacc, t_fix - nf.t_s, reset=gap)
        if self.rest is not None:
            self.rest.observe_fix(t_fix, vel, vacc)
        if self.keep_estimates:
            self._inn.append((t_fix, res.nis_pos, res.nis_vel, res.pos_accepted, res.vel_accepted))
        self.last_gps = res
        self.last_gps_t = t_fix
        tilt_sd = tilt_sigma_rad(nf.P)
        if tilt_sd > np.deg2rad(LOST_TILT_SIGMA_DEG):
            raise LostTrackError(
                f"tilt 1-sigma {np.rad2deg(tilt_sd):.0f} deg after the fix at t = {t_fix:.3f} s "
                f"(beyond {LOST_TILT_SIGMA_DEG:g} deg: no attitude left to linearise about)"
            )
        if p_bound is not None:
            _, _, hp, hv = nf.gps_model(truth.q_nb[i1], truth.omega_b_rps[i1])
            for ok, h, var, given in (
                (res.pos_accepted, hp, sig**2, np.isfinite(ned)),
                (res.vel_accepted, hv, np.full(3, vacc**2), np.isfinite(vel)),
            ):
                if ok:
                    m = int(given.sum())
                    _, p_bound = kf_update(
                        np.zeros(nf.layout.n), p_bound, np.zeros(m), np.diag(var[given]), h[given]
                    )
            self._p_bound = p_bound
        if nf.consecutive_position_rejects >= RESET_AFTER_REJECTS:
            nf.reset_to_fix(ned, vel, sig, vacc)
            nf.counters.gps_resets += 1
        elif nf.consecutive_velocity_rejects >= REOPEN_AFTER_VELOCITY_REJECTS:
            # the velocity prediction runs away from every fix: the tilt or the rate is
            # lost (gravity leaks through a wrong tilt). Put position and velocity on the
            # fix and give tilt and rate back the variance the next fixes need to fix them
            since = nf.t_s - self._t_last_reopen
            if since < REOPEN_MIN_INTERVAL_S:
                raise LostTrackError(
                    f"tilt or rate lost again {since:.1f} s after it was reopened, "
                    f"at t = {nf.t_s:.3f} s ({REOPEN_AFTER_VELOCITY_REJECTS} GPS velocities "
                    "rejected in a row)"
                )
            self._t_last_reopen = nf.t_s
            nf.reset_to_fix(ned, vel, sig, vacc)
            nf.counters.gps_resets += 1
            nf.reopen_attitude(REOPEN_TILT_SIGMA_RAD, REOPEN_RATE_SIGMA_RPS)
        was_reset = nf.counters.gps_resets + nf.counters.gps_gap_resets != resets_before
        if self._slip_sigma > 0 and not self._heading_pending:
            # with the no-sideslip model the heading is the course: after a reset of
            # position and velocity, a run of rejected sideslip updates with the
            # velocity accepted, or a state that flies backwards (a heading 180 deg off
            # satisfies both vehicle models, and a tilt relearned from tens of degrees
            # can settle there), a heading that contradicts the GPS course goes onto it
            slip_stuck = res.vel_accepted and nf.consecutive_sideslip_rejects >= RESET_AFTER_REJECTS
            course = _gps_course(vel, vacc)
            if course is not None and (was_reset or slip_stuck or nf.flies_backwards()):
                nf.check_heading_against_course(*course)
        if self._heading_pending:
            course = _gps_course(vel, vacc)
            if course is not None:
                nf.set_heading(*course)
                self._heading_pending = False
        elif self._heading_is_course and was_reset:
            # a vehicle that moves along its body axis measures its heading by the course
            # when position and velocity go onto a fix after a coast or a run of rejects:
            # the reset dropped what the fixes had told the heading through the velocity,
            # and the coast's heading has drifted (learned again through the linearised
            # velocity from there, it left `ground`'s tunnel exit over-sure; docs/design.md)
            course = _gps_course(vel, vacc, n_sigma=1.0)
            if course is not None and not nf.update_heading(*course)[1]:
                nf.set_heading(*_gps_course(vel, vacc))  # a heading the course contradicts
                nf.counters.heading_resets += 1
        # a heading as unknown as a lost tilt, where a start again takes it from the course
        heading_sd = heading_sigma_rad(nf.P)
        if (
            heading_sd > np.deg2rad(LOST_TILT_SIGMA_DEG)
            and self._flies_on_course
            and _gps_course(vel, vacc) is not None
        ):
            raise LostTrackError(
                f"heading 1-sigma {np.rad2deg(heading_sd):.0f} deg after the fix at t = "
                f"{t_fix:.3f} s (beyond {LOST_TILT_SIGMA_DEG:g} deg, and the course gives it)"
            )
