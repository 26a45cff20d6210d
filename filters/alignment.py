"""The filter's start: static or configured alignment, the first fix, the compensation's seed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from filters.ekf import NavFilter
from filters.forecast import (
    FORECAST_ERROR_PERSISTENCE,
    GM_WINDOW,
    RATE_RANGE_RPS,
    WDOT_SMOOTHING_S,
    make_predictor,
)
from filters.noise import filter_noise, static_mean_walk_s
from filters.rest import RestDetector
from filters.smoother import SmootherLog
from filters.supervision import (
    COURSE_MIN_SPEED_MPS,
    GATE_PROBABILITY,
)
from filters.vehicle_model import (
    CALM_AIR_SIGMA_DEG,
    SIDESLIP_RATE_HZ,
    ZERO_LIFT_AOA_DEG,
    ZERO_LIFT_AOA_SIGMA_DEG,
)
from ngnav.conventions import G0_MPS2
from ngnav.layout import rate_quadratics
from ngnav.predictors import noise_gain
from ngnav.rotation import dcm_from_quat, quat_from_euler


def _static_tilt(f_b: np.ndarray) -> tuple[float, float]:
    roll = float(np.arctan2(-f_b[1], -f_b[2]))
    pitch = float(np.arctan2(f_b[0], np.hypot(f_b[1], f_b[2])))
    return roll, pitch


def _gps_course(
    vel_ned_mps: np.ndarray, vel_sigma_mps: float, n_sigma: float = 3.0
) -> tuple[float, float] | None:
    """GPS course (rad) and a sigma ``atan(n_sigma sigma_v / speed)``; None below the min speed.

    The course's own noise is the cross-track velocity's over the speed (``n_sigma = 1``: a
    measurement of the heading); where it puts the heading outright (the start, a fixed-wing's
    contradicted heading) its sigma is three times that (no measurement of the factor)."""
    speed = float(np.hypot(vel_ned_mps[0], vel_ned_mps[1]))
    if not speed > COURSE_MIN_SPEED_MPS:  # slow, or no horizontal velocity (NaN)
        return None
    return float(np.arctan2(vel_ned_mps[1], vel_ned_mps[0])), float(
        np.arctan2(n_sigma * vel_sigma_mps, speed)
    )


class AlignmentMixin:
    """Build and initialise the filter from the samples before the start and the first fix."""

    def _start(self, i_start: int, first: tuple) -> None:
        self.counts["gps fix that started the filter"] += 1
        cfg = self.cfg
        ini = cfg.initial
        w0 = np.deg2rad(cfg.initial.rate_dps) if cfg.initial.alignment == "config" else np.zeros(3)
        # before the start nothing is dropped (base 0); channels isolated already are out
        sa = self._features(0, self._n, self._excluded, w0)
        invalid = (self._chmask[: self._n] & ~self._excluded) != 0
        self._count_held(0, i_start + 1, self._excluded)  # the blocks count the rest
        t = self._t[: self._n]
        se = self._se
        dt = self.dt
        noise = filter_noise(self._smat, cfg, None if se is None else se[:, 0:6])
        if self.method == "oracle":
            # no DR states: the oracle removes the whole geometry error (nothing left)
            noise = replace(noise, position_sigma_m=0.0)
        self.noise = noise
        veh = cfg.vehicle
        hold_s = veh.coast_remainder_updates / SIDESLIP_RATE_HZ
        aoa_prior_sigma_deg = ZERO_LIFT_AOA_SIGMA_DEG if veh.fixed_wing else 0.0
        nf = NavFilter(
            noise,
            self._pairs,
            cfg.antenna_b_m,
            GATE_PROBABILITY,
            sensor_axes_b=cfg.layout.axes_b,
            sensor_positions_b_m=cfg.layout.positions_b_m,
            solve_matrix=self._smat,
            aoa_prior_sigma_rad=float(np.deg2rad(aoa_prior_sigma_deg)),
            aoa_rw_rad_rts=float(np.deg2rad(veh.aoa_walk_deg_rts)),
            aoa_lift_k_m=veh.lift_k_m,
            liftoff_speed_mps=veh.liftoff_speed_mps,
            aoa_lift_k_sigma_m=veh.lift_k_sigma_m,
            quad_feedback=None if se is None else se[6:, 6:12],
            feature_quad_feedback=None if se is None else se[0:6, 6:12],
            remainder_updates=veh.remainder_updates,
            attitude_remainder_updates=veh.attitude_remainder_updates,
            coast_remainder_updates=veh.coast_remainder_updates,
            # a coast's remainder lasts its count of updates after the coast
            coast_hold_s=hold_s,
            # a hand-over's attitude errors are a coast's, and so are those the models
            # first meet after a static alignment (the configured heading's): counted
            # so for as long from the models' first update
            handover_hold_s=hold_s,
            count_by_prior_weight=veh.fixed_wing,
            body_velocity_error=veh.body_velocity_error,
        )
        nf.body_velocity_log = self.body_velocity_log
        self.nf = nf
        nq = self._pairs.shape[0]
        self._nq = nq
        g_ranges = np.repeat(
            [
                RATE_RANGE_RPS,
                cfg.range_mps2 / (cfg.layout.lever_arm_m or 0.1),
                cfg.range_mps2,
            ],
            3,
        )
        self.predictor = make_predictor(self.method, GM_WINDOW, g_ranges)
        window = self.predictor.window if self.predictor is not None else 1
        self._window = window
        f_t, f_ned, f_vel, f_sig, f_vacc, _ = first

        # --- initial attitude
        yaw0 = np.deg2rad(ini.yaw_deg)
        if ini.alignment == "static":
            span = slice(0, max(i_start, 1) + 1)
            ok = ~invalid[span]
            if not np.any(ok):
                raise ValueError("no valid array sample in the static alignment period")
            f_mean = sa[span][ok].mean(axis=0)
            # at rest the mounting term is E_ff f: the force is (I + E_ff)^-1 of the
            # mean, so the force bias b_f leaves (I + E_ff)^-1 b_f in f_b and
            # -E_f (I + E_ff)^-1 b_f in the others
            k_feat = self._k
            f_of_bias = np.zeros((3, k_feat))  # f_b's error per bias error (the tilt's)
            f_of_bias[:, 3:6] = np.eye(3)
            static_effect = np.eye(k_feat)
            if se is not None:
                f_of_bias[:, 3:6] = np.linalg.inv(np.eye(3) + se[3:6, 3:6])
                static_effect -= se[:, 3:6] @ f_of_bias
            f_b = f_of_bias[:, 3:6] @ f_mean[3:6]
            roll0, pitch0 = _static_tilt(f_b)
            # at rest the angular-acceleration and rate-product means are their biases,
            # the mounting term taken out
            static_mean = f_mean - (se[:, 3:6] @ f_b if se is not None else 0.0)
            n_avg = int(np.count_nonzero(ok))
            # the static mean has no forecast loop: its noise is the raw solve's per
            # sample (not the propagation's, mapped through the loop), / n
            sample_cov = self.solver.covariance()
            # the states are the biases at the start, which the mean's random walk
            # spreads from (the span's samples, the invalid ones too)
            walk_s = static_mean_walk_s(dt, i_start + 1)
            f_cov = sample_cov[3:6, 3:6] / n_avg + nf.noise.bias_rw_cov[3:6, 3:6] * walk_s
            f_noise = f_of_bias[:, 3:6] @ f_cov @ f_of_bias[:, 3:6].T
            tilt_noise = np.sqrt(0.5 * (f_noise[0, 0] + f_noise[1, 1])) / G0_MPS2
            att_sigma = np.array([tilt_noise, tilt_noise, np.deg2rad(ini.heading_sigma_deg)])
        else:
            roll0, pitch0 = np.deg2rad(ini.roll_deg), np.deg2rad(ini.pitch_deg)
            ts = np.deg2rad(ini.tilt_sigma_deg)
            att_sigma = np.array([ts, ts, np.deg2rad(ini.heading_sigma_deg)])
        #: The heading is the GPS course (``initial.heading_source = "gps"``); until the
        #: first one it is the configured heading with its sigma (docs/design.md, "Heading").
        self._heading_is_course = ini.heading_source == "gps"
        self._heading_pending = self._heading_is_course
        #: The vehicle flies along its course: a fixed-wing (no sideslip) or one whose heading
        #: is its course. A start again takes its heading from the course, and a heading as
        #: unknown as a lost tilt is a lost track.
        self._flies_on_course = cfg.vehicle.fixed_wing or self._heading_is_course
        q0 = quat_from_euler(roll0, pitch0, yaw0)
        c0 = dcm_from_quat(q0)
        nf.initialise(
            t[i_start],
            f_ned - c0 @ cfg.antenna_b_m,
            f_vel,
            q0,
            np.deg2rad(ini.rate_dps) if ini.alignment == "config" else np.zeros(3),
            f_sig,
            f_vacc,
            att_sigma,
            np.deg2rad(ini.rate_sigma_dps),
            aoa_rad=float(np.deg2rad(ZERO_LIFT_AOA_DEG if veh.fixed_wing else 0.0)),
        )
        if ini.alignment == "static":
            # the levelled attitude absorbs the horizontal force bias: correlate them exactly
            jm = np.zeros((2, 3))
            jm[0, 1] = 1.0 / G0_MPS2
            jm[1, 0] = -1.0 / G0_MPS2
            j = np.zeros((2, nf.layout.n))
            j[:, nf.layout.bias] = jm @ c0 @ f_of_bias
            cal_effect = None
            if nf.layout.n_cal:
                # the sensing-axis errors read the rest's force too (no forecast loop):
                # in the levelling and in the biases' means, as a bias does
                cal_rest = nf.calibration_jacobian(f_b, np.zeros(3), np.zeros(3), False)
                j[:, nf.layout.cal] = jm @ c0 @ f_of_bias @ cal_rest
                cal_effect = static_effect @ cal_rest
            p = nf.P
            p[6:8, :] = j @ p
            p[:, 6:8] = p[6:8, :].T
            jc = jm @ c0
            p[6:8, 6:8] = j @ nf.P @ j.T + jc @ f_noise @ jc.T
            p[6:8, 8] = 0.0
            p[8, 6:8] = 0.0
            nf.P = p
            nf.update_static_biases(
                static_mean, n_avg, static_effect, sample_cov, walk_s, cal_effect
            )
            nf.check_covariance("static alignment")
        self.last_gps_t = f_t

        # --- bound: the same covariance recursion, linearised at the truth
        self._p_bound = None
        truth = self.truth
        if truth is not None and truth.t_s.shape[0] < self._n:
            raise ValueError("truth must be sampled at the array's sample times")
        if self.bound:
            self._p_bound = nf.P.copy()
            self._c_true = dcm_from_quat(truth.q_nb)

        k_reg = max(1, round(1.0 / (cfg.filter.rate_hz * dt)))
        self._k_reg = k_reg
        self._i_start = i_start
        self._i0 = i_start
        self._next_grid = i_start + k_reg
        lo = max(0, i_start - k_reg)
        if self.smooth:
            self.smoother = SmootherLog(nf.layout.n)
            nf.lag = self.smoother.lag
        self._hist = np.empty((window + 1024, 9))
        self._seed_compensation(sa[lo : i_start + 1], ~invalid[lo : i_start + 1])
        self._record()
        self._with_geo = nf.layout.n_dr > 0 or nf.layout.n_cal > 0
        # the fixed-wing's calm-air models (none for a free vehicle)
        calm_air_sigma_deg = CALM_AIR_SIGMA_DEG if cfg.vehicle.fixed_wing else 0.0
        self._slip_sigma = np.deg2rad(calm_air_sigma_deg)
        self._aoa_sigma = np.deg2rad(calm_air_sigma_deg)
        self._t_last_slip = -np.inf
        self._f_load_prev: np.ndarray | None = None
        self._k_load_prev = 1  # samples measured in the block f_load_prev came from
        self._kk_load_prev = 1  # that block's length in samples (its mean's time)
        self._sg_load_prev: np.ndarray | None = None  # that block's S G force rows
        self._load_noise_cov = nf.noise.feature_cov[3:6, 3:6].copy()
        self._t_last_reopen = -np.inf
        self._wd_smooth = np.zeros(3)
        self._smooth_gain = min(1.0, 1.0 / (WDOT_SMOOTHING_S * cfg.filter.rate_hz))
        self._phi_hat = np.zeros(12) if self.predictor is not None else None
        #: kernels.block_means's outputs (nq,) and (k,), kept: written every block
        self._mean_bufs = (np.zeros(self._nq), np.zeros(self._k))
        # the forecast's error (see _forecast_noise): its noise floor, the block means'
        # own noise plus what the forecast carries of the history's
        comp = cfg.compensation
        self._fe_correct = bool(comp.forecast_correction) and se is not None
        # the error left in the state is counted as noise only without the correction
        use_noise = se is not None and not self._fe_correct
        self._fe_persistence = FORECAST_ERROR_PERSISTENCE if use_noise else 0.0
        self._fe_d2 = np.zeros(6)
        #: The noise in :attr:`last_forecast_error` of a block of one sample, (6,):
        #: ``(1 + g) N`` with ``N`` the raw feature noise variance per sample and ``g``
        #: the forecast's noise gain; a block of ``k`` samples has ``1 / k`` of it.
        self.forecast_error_floor = np.zeros(6)
        n_sample = np.diag(self.solver.covariance())[0:6]
        s = self._smooth_gain
        #: The noise variance of the angular acceleration the sensor positions' Jacobian
        #: reads, times the block's samples (3,): the forecast's ``g N`` (the smoother's
        #: ``s / (2 - s) N`` without one).
        self.wdot_jacobian_var = s / (2.0 - s) * n_sample[0:3]
        if self.predictor is not None:
            gain = noise_gain(self.predictor, self._hist[:window, 0:9])[3:9]
            self.forecast_error_floor = (1.0 + gain) * n_sample
            self.wdot_jacobian_var = gain[0:3] * n_sample[0:3]
        self._full_check_every = max(1, round(cfg.filter.rate_hz))  # Cholesky once a second
        # the zero-rate update at detected rest (rest.rate_sigma_dps > 0)
        self._rest_sigma = float(np.deg2rad(cfg.rest.rate_sigma_dps))
        self.rest: RestDetector | None = None
        if self._rest_sigma > 0.0:
            # the blocks' own noise: the raw solve's (a little less with the forecast's
            # correction, which leaves the test a little conservative)
            self.rest = RestDetector(self.solver.covariance()[0:6, 0:6], k_reg * dt, k_reg)
            if ini.alignment == "static":
                # the alignment's rest goes on: its mean [wdot, f] with the mounting
                # term at rest out, as the compensated blocks hold them
                self.rest.start_at_rest(nf.t_s, static_mean[0:6], n_avg / k_reg)
        self._e = 0
        self._t_hold = 0.0  # seconds of held samples in the current run
        self.started = True

    def _seed_compensation(self, seed_block: np.ndarray, seed_ok: np.ndarray) -> None:
        """Start the compensation's history on the features (K, k) of the samples up to
        the start (``seed_ok`` (K,): the valid ones), the last row the start's own."""
        nf = self.nf
        se = self._se
        window = self._window
        seed_mean = seed_block[seed_ok].mean(axis=0) if np.any(seed_ok) else np.zeros(self._k)
        # the seed's motion [wdot, f]: its raw features less the bias estimates hold the
        # mounting term too, (I + E_6) of it plus E of the rate's quadratics, so invert
        # that (without it the first forecasts held E f, about an axis error times g
        # over the arm on the angular acceleration, and their error opened the
        # forecast-error noise at every start)
        seed_motion = seed_mean[0:6] - nf.bias[0:6]
        if se is not None:
            seed_motion = np.linalg.solve(
                np.eye(6) + se[0:6, 0:6], seed_motion - se[0:6, 6:12] @ rate_quadratics(nf.w)
            )
        if nf.layout.n_aoa and np.any(seed_ok):
            # the lift law needs a load before the first block: the seed's (without it
            # the first epoch's angle of attack was the law's offset alone, 2.5-3.5 deg
            # off on tactical at 1 g and 60 m/s)
            nf.set_load(
                seed_motion[3:6],
                load_cov=nf.noise.feature_cov[3:6, 3:6] / int(np.count_nonzero(seed_ok)),
            )
        self._h_n = window  # rows used
        # the forecast history holds motion: block means less the current bias estimates
        self._hist[:window] = np.concatenate([nf.w, seed_motion])
        self._last_mean = seed_mean.copy()
        first_row = seed_block[-1] if seed_ok[-1] else seed_mean
        if se is not None:
            h0 = self._hist[0]
            first_row = first_row - se @ np.concatenate(
                [h0[3:6], h0[6:9], rate_quadratics(h0[0:3])]
            )
        nf.set_last_sample(first_row[0:3], first_row[3:6])
