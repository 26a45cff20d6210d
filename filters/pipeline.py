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

import bisect
from dataclasses import replace

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update

from filters.ekf import FilterNoise, NavFilter, static_mean_walk_s
from filters.rest import RestDetector
from filters.state import ATT, POS, RATE, VEL
from filters.updates import update_correlated
from filters.vehicle_model import (
    CALM_AIR_SIGMA_DEG,
    LATERAL,
    VERTICAL,
    ZERO_LIFT_AOA_DEG,
    ZERO_LIFT_AOA_SIGMA_DEG,
    BodyVelocityRecord,
)
from ngnav.compensation import _QUAD_I, _QUAD_J
from ngnav.conventions import G0_MPS2
from ngnav.errors import CovarianceError, LostTrackError
from ngnav.flight import FlightTruth, quat_from_euler
from ngnav.frontend import ArraySolver
from ngnav.geodesy import LocalTangentPlane
from ngnav.gps import GpsFixes
from ngnav.layout import ArrayLayout, kinematic_features, rate_quadratics
from ngnav.predictors import GreyPredictor, LastValuePredictor, LinePredictor, noise_gain
from ngnav.records import ArraySamples, Estimates, GpsInnovations, NavEstimate, RunResult
from ngnav.rotation import dcm_from_quat, euler_from_quat
from ngnav.runconfig import RunConfig

#: The innovation gate: a measurement whose NIS exceeds the chi-square quantile of this
#: probability (for its own dof) is rejected and counted: about one good fix in 10^4.
GATE_PROBABILITY = 0.9999
#: The first fix after this long without an accepted GPS position is not fused but puts
#: position and velocity on it (PX4 EKF2's reset after a fusion timeout): a long coast
#: builds its cross-covariances on a drifted trajectory, and fusing a large innovation
#: through them left ``uav-survey``'s vertical velocity several sigma off for 30 s, s.
GPS_GAP_RESET_S = 5.0
#: The GM(1,1) forecast's window, blocks (the paper's).
GM_WINDOW = 5
#: The body-rate range the forecasts are held to, rad/s.
RATE_RANGE_RPS = float(np.deg2rad(200.0))
#: Held samples (invalid or saturated): the forecast that replaces them drifts from the
#: motion as a random walk of this angular acceleration, rad/s^2 per sqrt(s), and force,
#: m/s^2 per sqrt(s).
HOLD_WDOT_SIGMA_RPS2 = 2.0
HOLD_FORCE_SIGMA_MPS2 = 3.0
#: Consecutive rejected GPS positions after which the filter is put back on the fix.
RESET_AFTER_REJECTS = 25
#: Time constant of the angular acceleration the position states' Jacobian uses, s.
WDOT_SMOOTHING_S = 0.05
#: Consecutive rejected GPS velocities after which tilt and rate variance is added back.
REOPEN_AFTER_VELOCITY_REJECTS = 10
#: Tilt 1-sigma added back then (per NED tilt axis), rad.
REOPEN_TILT_SIGMA_RAD = float(np.deg2rad(10.0))
#: Rate 1-sigma added back then (per body axis), rad/s.
REOPEN_RATE_SIGMA_RPS = float(np.deg2rad(2.0))
#: A second reopen within this time is a divergence (:class:`filters.ekf.LostTrackError`), s.
REOPEN_MIN_INTERVAL_S = 10.0
#: Blocks the running mean of the forecast's squared error spans (``Pipeline._forecast_noise``):
#: a manoeuvre's onset lasts a few tenths of a second, so a few blocks at 100 Hz.
FORECAST_ERROR_BLOCKS = 5
#: The forecast's error counts only where its running mean square exceeds the noise floor
#: this many times: below, what it would add is at most ``E_6^2`` times the floor, about
#: 1 % of a block's feature noise (``E_6`` about 0.07), and skipping it saves the block's
#: covariance arithmetic (at rest a 5-block mean of squares passes 2 with chance 0.075).
FORECAST_ERROR_GATE = 2.0
#: Rate of the vehicle model's updates (sideslip and angle of attack, when configured)
#: over the hand-over and coasts (``NavFilter.counts_as_coast``), where the coast's count
#: is in updates at this rate; elsewhere too (the rate is fixed), Hz.
SIDESLIP_RATE_HZ = 5.0
#: GPS velocities rejected in a row after which the vehicle model (sideslip and angle
#: of attack) pauses until one is accepted again. A state the velocity fixes contradict
#: has a covariance that no longer describes its errors, and a tight constraint fused
#: through it moves the rates by what those wrong correlations say: on ``tactical``
#: started with its pitch 15 deg off but told as 1 deg, one angle-of-attack update
#: put the pitch right and the pitch rate 21 deg/s off (2 deg/s sigma).
MODEL_PAUSE_AFTER_VELOCITY_REJECTS = 2
#: Horizontal speed above which a GPS course can set the heading, m/s.
COURSE_MIN_SPEED_MPS = 5.0


def load_extrapolation_weights(k_now: int, k_prev: int) -> tuple[float, float]:
    """Weights ``(w_now, w_prev)`` that take two consecutive block means to the block end.

    A block of ``k_now`` samples ending at ``t_e`` (the filter's time) has its mean at
    ``t_e - (k_now - 1) dt / 2``; the block before, of ``k_prev`` samples, at
    ``t_e - k_now dt - (k_prev - 1) dt / 2``. The straight line through the two means,
    evaluated at ``t_e``, is ``w_now f_k + w_prev f_k-1`` with ``w_now = 1 + L``,
    ``w_prev = -L``, ``L = (k_now - 1) / (k_now + k_prev)``: 1.45 and -0.45 for
    ``tactical``'s blocks of 10 samples (1.5 / -0.5, the limit of long blocks, reaches
    half a sample past the block end: 0.5 ms, and at the level-off's load rate the
    angle of attack ran up to 0.6 sigma off the truth, the same way in every run;
    design notes, "the load's half-sample lead"). Exact for a load linear in time.

    Parameters
    ----------
    k_now, k_prev : int
        Samples in the current and the previous block (>= 1).

    Returns
    -------
    tuple of float
        ``(w_now, w_prev)``, summing to 1.
    """
    if k_now < 1 or k_prev < 1:
        raise ValueError(f"block sizes must be >= 1, got {k_now} and {k_prev}")
    lead = (k_now - 1) / (k_now + k_prev)
    return 1.0 + lead, -lead


def _predictor(name: str, window: int, shift: np.ndarray):
    if name == "gm11":
        return GreyPredictor(window=window, shift=shift)
    if name == "line":
        return LinePredictor(window=window)
    if name == "last":
        return LastValuePredictor()
    return None


def filter_noise(
    solver: ArraySolver, cfg: RunConfig, feedback: np.ndarray | None = None
) -> FilterNoise:
    """Feature noise and bias model from the channel model, mapped through the solver.

    Parameters
    ----------
    solver : ArraySolver
        The nominal-geometry solve (operator ``S``, shape (k, N)).
    cfg : RunConfig
        Channel noise, turn-on bias and bias random walk.
    feedback : array (k, 6), optional
        With a forecast compensation (GM(1,1), line, last), the sensitivity
        ``E`` of the solved features to the forecast angular acceleration and
        force (the first six columns of the compensation matrix). The forecast
        is made from the compensated block means, so the features' own past
        noise and bias error come back through it: over many blocks (what the
        propagation integrates) the compensated angular acceleration and force
        errors are ``A = (I + E_6)^-1`` of the raw ones and the quadratic
        terms' are offset by ``-E_q A`` of them, ``T = [[A, 0], [-E_q A, I]]``.
        The process-noise blocks are mapped through ``T``; the quadratic block
        of ``feature_cov`` stays raw, because each rate measurement uses one
        block's mean, whose forecast part comes from earlier blocks
        (independent noise). In uav-survey (6 mm outward offset, ``E_6``
        diagonal about 0.07) the raw model left the rate and attitude about
        13 % pessimistic in variance. The history holds the block means less
        the bias *estimates*, so what returns is the bias states' error, true
        less estimated: the bias states are the raw ``S b`` (prior and random
        walk unmapped) and ``T`` is their effect on the features
        (``FilterNoise.bias_effect``). Mapping the prior instead (the states
        ``T S b``) left the estimate's own corrections out of the loop: a
        correction ``d`` moves the features by ``T d``, not ``d``, and the
        angular-acceleration bias estimate converged on ``S b`` with ``T S b``
        as its truth (tactical, 40 runs: 6-8 sigma off by 4 s).

        ``block_wdot_cov`` (the rate's noise over one block, what a zero-rate update
        at rest sees) is the raw angular-acceleration noise, without the forecast's
        correction (``filter.forecast_correction``): the loop's ``A`` holds for errors
        integrated over many blocks only. With the correction the block's own noise
        reaches the state as ``(I - E_6) n``, about ``A n``, and it stays None.
    """
    s = solver.solve_matrix
    # a floor of 1e-6 m/s^2 keeps the prior positive definite when a config says "no bias"
    b0 = np.maximum(cfg.turn_on_bias_mps2, 1e-6)
    feature_cov = solver.covariance()
    bias_prior_cov = s @ np.diag(b0**2) @ s.T
    bias_rw_cov = s @ np.diag(cfg.bias_rw_mps2_rts**2) @ s.T
    # one sample's [wdot, f] noise with its quadratic terms' (the same block's: raw)
    quad_cross_cov = feature_cov[0:6, 6:].copy()
    bias_effect = None
    block_wdot_cov = None
    if feedback is not None:
        if not cfg.compensation.forecast_correction:
            # one block's own angular-acceleration noise is the raw solve's; with the
            # forecast's correction it is not: the correction takes E_6 of the block's
            # forecast error out, its own noise included, which leaves (I - E_6) n ~ A n
            block_wdot_cov = feature_cov[0:3, 0:3].copy()
        k = s.shape[0]
        a = np.linalg.inv(np.eye(6) + feedback[0:6])
        t = np.eye(k)
        t[0:6, 0:6] = a
        t[6:, 0:6] = -feedback[6:] @ a
        raw_qq = feature_cov[6:, 6:].copy()
        feature_cov = t @ feature_cov @ t.T
        feature_cov[6:, 6:] = raw_qq
        bias_effect = t
    return FilterNoise(
        feature_cov=feature_cov,
        bias_prior_cov=bias_prior_cov,
        bias_rw_cov=bias_rw_cov,
        position_sigma_m=cfg.position_sigma_m,
        quad_cross_cov=quad_cross_cov,
        bias_effect=bias_effect,
        block_wdot_cov=block_wdot_cov,
    )


def _static_tilt(f_b: np.ndarray) -> tuple[float, float]:
    roll = float(np.arctan2(-f_b[1], -f_b[2]))
    pitch = float(np.arctan2(f_b[0], np.hypot(f_b[1], f_b[2])))
    return roll, pitch


def _gps_course(vel_ned_mps: np.ndarray, vel_sigma_mps: float) -> tuple[float, float] | None:
    """GPS course (rad) and its 1-sigma ``atan(3 sigma_v / speed)``; None below the min speed."""
    speed = float(np.hypot(vel_ned_mps[0], vel_ned_mps[1]))
    if speed <= COURSE_MIN_SPEED_MPS:
        return None
    return float(np.arctan2(vel_ned_mps[1], vel_ned_mps[0])), float(
        np.arctan2(3 * vel_sigma_mps, speed)
    )


class Pipeline:
    """The whole chain run as a stream: push samples and fixes, get estimates.

    One block at a time: the compensation's forecast, the nominal propagation,
    the covariance prediction, the rate-product update, the GPS fixes that fall
    in the block (at their time of validity), the sideslip model, the checks.
    Estimates are recorded at every block end as a :class:`ngnav.records.NavEstimate`
    (:attr:`latest`); ``on_epoch(record)`` is called with each.

    Inputs may arrive in any interleaving (a live link delivers a fix
    ``latency`` after its time of validity): the filter's fusion horizon runs
    ``cfg.filter.fusion_lag_s`` behind the newest sample (PX4 EKF2's delayed
    horizon), so a fix that arrives within that lag is fused exactly where an
    offline run fuses it. A later fix is fused at the next block end with a
    ``v dt`` time shift and counted. The result therefore depends only on the
    samples, the fixes and the order of their arrival, not on how they were
    chunked or how fast they came: a tlog replay and the live link of the same
    run give the same estimates.

    Before the filter starts (a fix after the static alignment period, and the
    samples up to it plus the lag) everything is buffered.

    Parameters
    ----------
    cfg : RunConfig
        What the filter knows (see :mod:`ngnav.runconfig`).
    dt_s : float, optional
        The array's sample interval. Default: the median interval of the
        samples received before the filter starts.
    compensation, use_gps, true_layout, truth, bound
        As for :func:`run_filter`.
    on_epoch : callable, optional
        Called with the :class:`ngnav.records.NavEstimate` of every recorded epoch.
    keep_estimates : bool
        Keep every epoch for :meth:`result` (False for an endless live link:
        :meth:`result` then holds the latest epoch only).
    body_velocity_log : list, optional
        As for :func:`run_filter`.

    Raises
    ------
    ValueError
        Bad configuration or a rate-aided layout (at construction); no valid
        sample in the alignment period (at the start); no usable GPS fix (at
        :meth:`finish`).
    filters.ekf.CovarianceError
        If the covariance stops being symmetric positive definite.
    """

    #: The innovation gate's probability, for outputs that report test ratios.
    gate_probability = GATE_PROBABILITY
    #: How long after an accepted GPS position an estimate counts as GPS aided, s.
    gps_gap_s = GPS_GAP_RESET_S

    def __init__(
        self,
        cfg: RunConfig,
        *,
        dt_s: float | None = None,
        compensation: str | None = None,
        use_gps: bool = True,
        true_layout: ArrayLayout | None = None,
        truth: FlightTruth | None = None,
        bound: bool = False,
        on_epoch=None,
        keep_estimates: bool = True,
        body_velocity_log: list[BodyVelocityRecord] | None = None,
    ) -> None:
        method = compensation or cfg.compensation.method
        if method == "oracle" and (true_layout is None or truth is None):
            raise ValueError(
                "compensation 'oracle' needs the true geometry and motion (simulations)"
            )
        if bound and truth is None:
            raise ValueError("the bound needs the truth")
        solver = ArraySolver(cfg.layout, cfg.noise_sigma_mps2)
        if solver.rate_aided:
            raise ValueError(
                f"layout {cfg.layout.name!r} cannot solve its rate terms; the filter needs a "
                "layout that solves angular acceleration, force and rate products (e.g. nine-cube)"
            )
        if dt_s is not None and not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive number, got {dt_s}")
        self.cfg = cfg
        self.method = method
        self.use_gps = use_gps
        self.true_layout = true_layout
        self.truth = truth
        self.bound = bound
        self.on_epoch = on_epoch
        self.keep_estimates = keep_estimates
        self.body_velocity_log = body_velocity_log
        self.n_epochs = 0
        self.n_channels = cfg.layout.n_sensors
        self.solver = solver
        cols = solver.solved_columns
        self._cols = cols
        quad_cols = cols[cols >= 6] - 6
        self._pairs = np.column_stack([_QUAD_I[quad_cols], _QUAD_J[quad_cols]])
        self._smat = solver.solve_matrix
        self._se = None
        if method in ("gm11", "line", "last"):
            self._se = self._smat @ cfg.known_errors.error_matrix(cfg.layout)  # (k, 12)
        self._e_true = None
        if method == "oracle":
            self._e_true = self._smat @ (true_layout.design - cfg.layout.design)
        self.dt = dt_s
        self._k = cols.shape[0]
        # sample store: global index g lives at row g - base
        self._t = np.empty(0)
        self._sa = np.empty((0, self._k))
        self._inv = np.empty(0, dtype=bool)
        self._chmask = np.empty(0, dtype=np.int64)  # bit i: channel i invalid or saturated
        self._bits = 1 << np.arange(self.n_channels, dtype=np.int64)
        self._base = 0
        self._n = 0  # samples received (global count)
        self._fixes: list[tuple] = []  # (t, ned(3), vel(3), sig(3), vel_acc, arrival order)
        self._pending: list[tuple[int, int, tuple]] = []  # (idx, order, fix) after the start
        self._late: list[tuple] = []
        self._n_fix = 0
        self.counts: dict[str, int] = {
            "samples held (non-finite)": 0,
            "samples held (saturated)": 0,
            "gps fixes outside the array's time span": 0,
            "gps fixes before the filter start": 0,
            "gps fixes later than the fusion lag": 0,
        }
        self._ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
        self.started = False
        self.finished = False
        self.nf: NavFilter | None = None
        self.last_gps = None
        self.last_gps_t = -np.inf
        self.last_rate_nis = float("nan")
        self.block_faulty = 0
        self.block_fallbacks = 0
        #: The last block's compensated ``[wdot, f]`` mean (FRD; rad/s^2, m/s^2) less the
        #: bias estimates less its forecast, (6,): the forecast's error plus noise (NaN
        #: without a forecast compensation or before the first block).
        self.last_forecast_error = np.full(6, np.nan)
        #: The latest epoch's record (None before the first).
        self.latest: NavEstimate | None = None
        self._rec: list[NavEstimate] = []
        self._inn: list[tuple] = []
        self._rate_nis: list[float] = []
        self._rate_nis_t: list[float] = []
        self.n_fallbacks = 0

    # ------------------------------------------------------------------ input
    def push_samples(self, t_s: np.ndarray, accel_mps2: np.ndarray) -> int:
        """Take consecutive array samples (K,), (K, N) m/s^2; returns epochs recorded.

        The samples must continue the uniform grid (a gap is the caller's to
        fill with NaN rows, as the readers do); non-finite and saturated rows
        are held and counted.
        """
        if self.finished:
            raise ValueError("the pipeline has finished; it takes no more samples")
        t_s = np.asarray(t_s, dtype=float).reshape(-1)
        raw = np.asarray(accel_mps2, dtype=float).reshape(t_s.shape[0], -1)
        if raw.shape[1] != self.n_channels:
            raise ValueError(
                f"config layout has {self.n_channels} channels, the array data has {raw.shape[1]}"
            )
        if t_s.shape[0] == 0:
            return 0
        cfg = self.cfg
        finite = np.all(np.isfinite(raw), axis=1)
        with np.errstate(invalid="ignore"):
            saturated = finite & np.any(np.abs(raw) >= cfg.range_mps2 * (1 - 1e-9), axis=1)
        invalid = ~finite | saturated
        self.counts["samples held (non-finite)"] += int(np.count_nonzero(~finite))
        self.counts["samples held (saturated)"] += int(np.count_nonzero(saturated))
        a = (np.where(invalid[:, None], cfg.offset_mps2, raw) - cfg.offset_mps2) / cfg.scale
        sa = a @ self._smat.T  # (K, k) solved features, before compensation
        if self._e_true is not None:
            # the exact mounting-error term: true geometry, true motion
            tr = self.truth
            g = slice(self._n, self._n + t_s.shape[0])
            phi = kinematic_features(tr.omega_dot_b_rps2[g], tr.f_b_mps2[g], tr.omega_b_rps[g])
            sa -= phi @ self._e_true.T
        with np.errstate(invalid="ignore"):
            bad_ch = ~np.isfinite(raw) | (np.abs(raw) >= cfg.range_mps2 * (1 - 1e-9))
        self._append(t_s, sa, invalid, bad_ch @ self._bits)
        return self._advance()

    def push_fix(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vel_ned_mps: np.ndarray,
        h_acc_m: float,
        v_acc_m: float,
        vel_acc_mps: float,
    ) -> int:
        """Take one GPS fix (time of validity, WGS-84, NED velocity, 1-sigma); returns epochs."""
        if self.finished:
            raise ValueError("the pipeline has finished; it takes no more fixes")
        ned = self._ltp.to_ned(
            np.array([lat_deg], dtype=float),
            np.array([lon_deg], dtype=float),
            np.array([alt_m], dtype=float),
        )[0]
        fix = (
            float(t_s),
            ned,
            np.array(vel_ned_mps, dtype=float).reshape(3),
            np.array([h_acc_m, h_acc_m, v_acc_m], dtype=float),
            float(vel_acc_mps),
            self._n_fix,
        )
        self._n_fix += 1
        if not self.started:
            self._fixes.append(fix)
            return self._advance()
        self._place_fix(fix)
        return self._advance()

    def finish(self) -> int:
        """No more input: process the buffered tail; returns epochs recorded.

        Raises ValueError if the filter never started (no usable fix).
        """
        if self.finished:
            return 0
        if not self.started:
            if self._n < 2:
                raise ValueError(f"the run holds {self._n} array samples; at least 2 are needed")
            if not self._try_start(final=True):
                raise ValueError(
                    "no GPS fix after the alignment period: cannot set position and velocity"
                )
        self.finished = True
        n_before = self.n_epochs
        last = self._n - 1
        t_last = self._t[last - self._base]
        keep = []
        for idx, order, fix in self._pending:
            if idx > last:
                if fix[0] <= t_last + self.dt / 2:
                    keep.append((last, order, fix))
                else:
                    self.counts["gps fixes outside the array's time span"] += 1
            else:
                keep.append((idx, order, fix))
        self._pending = sorted(keep)
        self._run_blocks(final=True)
        return self.n_epochs - n_before

    # ---------------------------------------------------------------- start
    def _place_fix(self, fix: tuple) -> None:
        """File a fix that arrived after the start (pending, late or outside)."""
        t_fix = fix[0]
        if t_fix < self._t0 - self.dt / 2:
            self.counts["gps fixes outside the array's time span"] += 1
            return
        idx = int(np.rint((t_fix - self._t0) / self.dt))
        if idx <= self._i0:
            if idx <= self._i_start:
                self.counts["gps fixes before the filter start"] += 1
                return
            self.counts["gps fixes later than the fusion lag"] += 1
            self._late.append(fix)
            return
        bisect.insort(self._pending, (idx, fix[5], fix))

    def _advance(self) -> int:
        n_before = self.n_epochs
        if not self.started and not self._try_start(final=False):
            return 0
        self._run_blocks(final=False)
        return self.n_epochs - n_before

    def _try_start(self, final: bool) -> bool:
        cfg = self.cfg
        ini = cfg.initial
        t = self._t[: self._n]  # nothing is dropped before the start: base is 0
        if self._n < 2:
            return False
        if self.dt is None:
            if self._n < 9 and not final:
                return False
            self.dt = float(np.median(np.diff(t)))
            if not self.dt > 0:
                raise ValueError("array sample times do not increase")
        dt = self.dt
        t0 = t[0]
        if ini.alignment == "static":
            if t[-1] < t0 + ini.static_s and not final:
                return False
            i_align = int(np.searchsorted(t, t0 + ini.static_s))
        else:
            i_align = 0
        lag_n = self._lag_n()
        best = None
        for fix in self._fixes:
            inside = fix[0] >= t0 - dt / 2 and fix[0] <= t[-1] + dt / 2
            idx = min(int(np.rint((fix[0] - t0) / dt)), self._n - 1)
            if not inside or idx < i_align:
                continue
            if best is None or (fix[0], fix[5]) < (best[1][0], best[1][5]):
                best = (idx, fix)
        if best is None:
            return False
        i_start, first = best
        if not final and self._n - 1 < i_start + lag_n:
            return False  # an earlier fix may still arrive within the lag
        self._t0 = t0
        self._start(i_start, first)
        rest = [f for f in self._fixes if f is not first]
        self._fixes = []
        for fix in sorted(rest, key=lambda f: f[5]):
            self._place_fix(fix)
        return True

    def _lag_n(self) -> int:
        return int(np.ceil(self.cfg.filter.fusion_lag_s / self.dt - 1e-9))

    def _start(self, i_start: int, first: tuple) -> None:
        cfg = self.cfg
        ini = cfg.initial
        sa, invalid, t = self._sa[: self._n], self._inv[: self._n], self._t[: self._n]
        se = self._se
        dt = self.dt
        noise = filter_noise(self.solver, cfg, None if se is None else se[:, 0:6])
        if self.method == "oracle" or not cfg.filter.position_states:
            # no DR states: the oracle removes the whole geometry error (nothing left to
            # estimate), or the configuration leaves the scatter unmodelled
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
            solve_matrix=self._smat,
            aoa_prior_sigma_rad=float(np.deg2rad(aoa_prior_sigma_deg)),
            aoa_rw_rad_rts=float(np.deg2rad(veh.aoa_walk_deg_rts)),
            aoa_lift_k_m=veh.lift_k_m,
            liftoff_speed_mps=veh.liftoff_speed_mps,
            aoa_lift_k_sigma_m=veh.lift_k_sigma_m,
            quad_feedback=None if se is None else se[6:, 6:12],
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
        self.predictor = _predictor(self.method, GM_WINDOW, g_ranges)
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
        self._heading_pending = ini.heading_source == "gps"
        if self._heading_pending:
            att_sigma[2] = np.deg2rad(30.0)
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
            p = nf.P
            p[6:8, :] = j @ p
            p[:, 6:8] = p[6:8, :].T
            jc = jm @ c0
            p[6:8, 6:8] = j @ nf.P @ j.T + jc @ f_noise @ jc.T
            p[6:8, 8] = 0.0
            p[8, 6:8] = 0.0
            nf.P = p
            nf.update_static_biases(static_mean, n_avg, static_effect, sample_cov, walk_s)
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
        k_feat = self._k
        lo = max(0, i_start - k_reg)
        seed_block = sa[lo : i_start + 1]
        seed_ok = ~invalid[lo : i_start + 1]
        seed_mean = seed_block[seed_ok].mean(axis=0) if np.any(seed_ok) else np.zeros(k_feat)
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
        self._record()
        self._hist = np.empty((window + 1024, 9))
        self._h_n = window  # rows used
        # the forecast history holds motion: block means less the current bias estimates
        self._hist[:window] = np.concatenate([nf.w, seed_motion])
        self._last_mean = seed_mean.copy()
        first_row = sa[i_start] if not invalid[i_start] else seed_mean
        if se is not None:
            h0 = self._hist[0]
            first_row = first_row - se @ np.concatenate(
                [h0[3:6], h0[6:9], rate_quadratics(h0[0:3])]
            )
        nf.set_last_sample(first_row[0:3], first_row[3:6])
        self._with_dr = nf.layout.n_dr > 0
        # the fixed-wing's calm-air models (none for a free vehicle)
        calm_air_sigma_deg = CALM_AIR_SIGMA_DEG if cfg.vehicle.fixed_wing else 0.0
        self._slip_sigma = np.deg2rad(calm_air_sigma_deg)
        self._aoa_sigma = np.deg2rad(calm_air_sigma_deg)
        self._model_rate_hz = SIDESLIP_RATE_HZ
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
        # the forecast's error (see _forecast_noise): its noise floor, the block means'
        # own noise plus what the forecast carries of the history's
        comp = cfg.compensation
        self._fe_persistence = comp.forecast_error_persistence if se is not None else 0.0
        self._fe_correct = bool(comp.forecast_correction) and se is not None
        self._fe_d2 = np.zeros(6)
        #: The noise in :attr:`last_forecast_error` of a block of one sample, (6,):
        #: ``(1 + g) N`` with ``N`` the raw feature noise variance per sample and ``g``
        #: the forecast's noise gain; a block of ``k`` samples has ``1 / k`` of it.
        self.forecast_error_floor = np.zeros(6)
        if self.predictor is not None:
            gain = noise_gain(self.predictor, self._hist[:window, 0:9])[3:9]
            self.forecast_error_floor = (1.0 + gain) * np.diag(self.solver.covariance())[0:6]
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

    # --------------------------------------------------------------- blocks
    def _run_blocks(self, final: bool) -> None:
        last = self._n - 1
        lag_n = 0 if final else self._lag_n()
        while True:
            i1 = self._next_grid
            if self._pending and self._pending[0][0] < i1:
                i1 = self._pending[0][0]
            if final:
                if self._i0 >= last:
                    break
                i1 = min(i1, last)
            elif i1 + lag_n > last:
                break
            self._block(i1)

    def _append(self, t_s, sa, invalid, chmask) -> None:
        """Append rows to the sample store (amortised growth; processed rows dropped)."""
        m = t_s.shape[0]
        used = self._n - self._base
        if used + m > self._t.shape[0]:
            # drop what the blocks no longer need (keep the last processed sample)
            drop = max(0, self._i0 - self._base) if self.started else 0
            keep = slice(drop, used)
            cap = max(4096, 2 * (used - drop + m))
            for name in ("_t", "_sa", "_inv", "_chmask"):
                old = getattr(self, name)
                new = np.empty((cap, *old.shape[1:]), dtype=old.dtype)
                new[: used - drop] = old[keep]
                setattr(self, name, new)
            self._base += drop
            used -= drop
        r = slice(used, used + m)
        self._t[r] = t_s
        self._sa[r] = sa
        self._inv[r] = invalid
        self._chmask[r] = chmask
        self._n += m

    def _model_interval_s(self, nf: NavFilter) -> float:
        """Time between vehicle-model updates now, s.

        ``1 / SIDESLIP_RATE_HZ`` while the filter counts the remainder as a coast's
        (hand-over, coasts and their holds: ``coast_remainder_updates`` counts 5 Hz
        updates), ``1 / filter.vehicle_model_rate_hz`` otherwise.
        """
        rate = SIDESLIP_RATE_HZ if nf.counts_as_coast() else self._model_rate_hz
        return 1.0 / rate

    def _record(self) -> None:
        nf = self.nf
        pb = self._p_bound[:12, :12] if self._p_bound is not None else None
        self.n_epochs += 1
        if not self.keep_estimates:
            self._rec.clear()
        p12 = nf.P[:12, :12].copy()
        vel = nf.vel
        if nf.in_body_frame():
            # the NED velocity a user reads: its second-order part's mean and covariance
            mc, cc = nf.velocity_curvature()
            vel = vel + mc
            p12[VEL, VEL] += cc
        aoa = (nf.aoa, nf.aoa_sigma) if nf.layout.n_aoa else (None, None)
        c = nf.counters
        est = NavEstimate(
            nf.t_s,
            nf.pos,
            vel,
            nf.q,
            nf.w,
            nf.bias,
            p12,
            pb,
            *aoa,
            last_gps=self.last_gps,
            t_last_position_fix_s=nf.t_last_position_fix,
            resets=c.gps_resets + c.gps_gap_resets,
            rate_innovation=nf.last_rate_innovation,
            rate_nis=self.last_rate_nis,
            rate_rejected=bool(self.last_rate_nis > nf.gate_q),
            forecast_fallback=bool(self.block_fallbacks),
            forecast_fallbacks=self.n_fallbacks,
            held_samples=self.counts["samples held (non-finite)"]
            + self.counts["samples held (saturated)"],
            rate_updates_rejected=c.rate_rejected,
            faulty_channels=self.block_faulty,
        )
        self.latest = est
        self._rec.append(est)

    def _block(self, i1: int) -> None:
        nf = self.nf
        dt = self.dt
        se = self._se
        truth = self.truth
        p_bound = self._p_bound
        nq = self._nq
        i0 = self._i0
        b = self._base
        xs = self._sa[i0 + 1 - b : i1 + 1 - b].copy()
        bad = self._inv[i0 + 1 - b : i1 + 1 - b]
        kk = xs.shape[0]
        window = self._window
        e = self._e + 1
        row = self._h_n
        phi_hat = self._phi_hat
        if self.predictor is not None:
            x_hat, nfb = self.predictor.forecast(self._hist[row - window : row], e - 1)
            self.n_fallbacks += nfb
            self.block_fallbacks = nfb
            wx, wy, wz = x_hat[0:3].tolist()
            phi_hat[0:6] = x_hat[3:9]
            phi_hat[6:] = (wx * wx, wy * wy, wz * wz, wy * wz, wx * wz, wx * wy)
            xs -= se @ phi_hat
        self.block_faulty = 0
        if np.any(bad):
            fill = self._last_mean if phi_hat is None else phi_hat[self._cols] + nf.bias
            xs[bad] = fill
            self.block_faulty = int(np.bitwise_or.reduce(self._chmask[i0 + 1 - b : i1 + 1 - b]))
        n_ok = kk - int(np.count_nonzero(bad))
        sg = sg_true = None
        if self._with_dr:
            # The sensor-position states see the block's angular acceleration as
            # forecast from the *previous* blocks (the compensation's forecast, or a
            # smoothed history without one): this block's own noise would correlate
            # the Jacobian with the rate measurement's noise and drag dr.
            wd_sg = self._wd_smooth if phi_hat is None else phi_hat[0:3]
            sg = nf.geometry_jacobian(wd_sg, nf.w + 0.5 * kk * dt * wd_sg)
            if p_bound is not None:
                blk = slice(i0 + 1, i1 + 1)
                sg_true = nf.geometry_jacobian(
                    truth.omega_dot_b_rps2[blk].mean(axis=0), truth.omega_b_rps[blk].mean(axis=0)
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
        good = xs[~bad] if 0 < n_ok < kk else xs
        self._last_mean = good.sum(axis=0) * (1.0 / good.shape[0])
        quad_fix = None
        if phi_hat is not None:
            self.last_forecast_error = self._last_mean[0:6] - nf.bias[0:6] - phi_hat[0:6]
            if self._fe_persistence > 0.0:
                self._forecast_noise(self.last_forecast_error, n_ok, kk * dt)
            if self._fe_correct and np.all(np.isfinite(self.last_forecast_error)):
                # what the forecast's error left in the block, out of the state and history
                # before the rate products are compared, from them too: left in, the rate
                # update took the rate error it made for the sensor positions' doing (their
                # NEES, 27 dof, rose from 30 to 51 over tactical's flight, 24 runs; 38 so;
                # design notes, "the forecast's error out before the rate products")
                r_all = self._se[:, 0:6] @ self.last_forecast_error
                r6 = r_all[0:6]
                nf.remove_feature_residual(r6, kk * dt)
                w_blk = w_blk - np.outer(np.arange(1, kk + 1) * dt, r6[0:3])
                self._last_mean -= r_all
                quad_fix = r_all[6:]
        if n_ok and nq:
            quad = xs[:, 6:] if n_ok == kk else xs[~bad, 6:]
            held = bad if n_ok < kk else None
            quad_mean = quad.sum(axis=0) * (1.0 / n_ok)
            if quad_fix is not None:
                quad_mean = quad_mean - quad_fix
            nis = nf.update_rate(quad_mean, w_blk, n_ok, sg, held)
            self.last_rate_nis = np.nan if nis is None else nis
            if self.keep_estimates:
                self._rate_nis.append(self.last_rate_nis)
                self._rate_nis_t.append(nf.t_s)
            if p_bound is not None and nis is not None and nis <= nf.gate_q:
                _, hb = nf.rate_model(truth.omega_b_rps[i0 + 1 : i1 + 1], sg_true)
                _, p_bound = update_correlated(
                    np.zeros(nf.layout.n),
                    p_bound,
                    np.zeros(nq),
                    self.noise.feature_cov[6:, 6:] / n_ok,
                    hb,
                    nf.rate_noise_cross(kk, dt, c_true[i0], held),
                )
        if row == self._hist.shape[0]:
            # a sliding window: keep the rows the next forecasts read
            self._hist[:window] = self._hist[row - window : row]
            row = window
        self._hist[row] = np.concatenate([nf.w, self._last_mean[0:6] - nf.bias[0:6]])
        self._h_n = row + 1
        if rest is not None:
            rest.observe_block(nf.t_s, self._last_mean[0:6], n_ok)
        self._wd_smooth += self._smooth_gain * (
            self._last_mean[0:3] - nf.bias[0:3] - self._wd_smooth
        )
        if nf.layout.n_aoa:
            # the block mean lags the block end by (k - 1) / 2 samples: extrapolate it
            # there (load_extrapolation_weights)
            # (measured: the lift law on tactical's 100 Hz block means was up to 0.07 deg
            # behind the truth in the roll-ins, exact on the block-end force)
            # (its noise: the block means' feature_cov / k, as the weights combine them)
            # (with sensor-position states the load, as the propagation, loses S G dr_hat,
            # and the angle's Jacobian sees dr through it)
            f_mean = self._last_mean[3:6] - nf.bias[3:6]
            sg_f = None
            if sg is not None:
                sg_f = sg[3:6]
                f_mean = f_mean - sg_f @ nf.dr
            k_now = good.shape[0]
            if self._f_load_prev is None:
                f_load, w2, sg_load = f_mean, 1.0 / k_now, sg_f
            else:
                w_now, w_prev = load_extrapolation_weights(kk, self._kk_load_prev)
                f_load = w_now * f_mean + w_prev * self._f_load_prev
                w2 = w_now**2 / k_now + w_prev**2 / self._k_load_prev
                sg_load = sg_f
                if sg_f is not None and self._sg_load_prev is not None:
                    sg_load = w_now * sg_f + w_prev * self._sg_load_prev
            nf.set_load(f_load, load_cov=w2 * self._load_noise_cov, sg_f=sg_load)
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
            and nf.t_s - self._t_last_slip >= self._model_interval_s(nf) - dt / 2
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
        ``filter.forecast_error_persistence`` over the block
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
                self.nf.add_hold_noise(
                    t_run, t_new, HOLD_WDOT_SIGMA_RPS2, HOLD_FORCE_SIGMA_MPS2
                )
                t_run = t_new
            else:
                t_run = 0.0
        self._t_hold = t_run

    def _fuse_fix(self, fix: tuple, i1: int, p_bound: np.ndarray | None) -> None:
        if not self.use_gps:
            return
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
        if p_bound is not None:
            _, _, hp, hv = nf.gps_model(truth.q_nb[i1], truth.omega_b_rps[i1])
            if res.pos_accepted:
                _, p_bound = kf_update(
                    np.zeros(nf.layout.n), p_bound, np.zeros(3), np.diag(sig**2), hp
                )
            if res.vel_accepted:
                _, p_bound = kf_update(
                    np.zeros(nf.layout.n), p_bound, np.zeros(3), np.eye(3) * vacc**2, hv
                )
            self._p_bound = p_bound
        if nf.consecutive_position_rejects >= RESET_AFTER_REJECTS:
            nf.reset_to_fix(ned, vel, sig, vacc)
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
            nf.reopen_attitude(REOPEN_TILT_SIGMA_RAD, REOPEN_RATE_SIGMA_RPS)
        if self._slip_sigma > 0 and not self._heading_pending:
            # with the no-sideslip model the heading is the course: after a reset of
            # position and velocity, or a run of rejected sideslip updates with the
            # velocity accepted, a heading that contradicts the GPS course goes onto it
            was_reset = nf.counters.gps_resets + nf.counters.gps_gap_resets != resets_before
            slip_stuck = res.vel_accepted and nf.consecutive_sideslip_rejects >= RESET_AFTER_REJECTS
            course = _gps_course(vel, vacc)
            if (was_reset or slip_stuck) and course is not None:
                nf.check_heading_against_course(*course)
        if self._heading_pending:
            course = _gps_course(vel, vacc)
            if course is not None:
                nf.set_heading(*course)
                self._heading_pending = False

    # --------------------------------------------------------------- output
    def result(self) -> RunResult:
        """Everything recorded so far (call after :meth:`finish` for the whole run)."""
        if not self.started:
            raise ValueError("the filter has not started: no estimates")
        nf = self.nf
        estimates = Estimates.stack(self._rec)
        inn = np.array([r[0:3] for r in self._inn], dtype=float).reshape(-1, 3)
        acc = np.array([r[3:5] for r in self._inn], dtype=bool).reshape(-1, 2)
        innovations = GpsInnovations(inn[:, 0], inn[:, 1], inn[:, 2], acc[:, 0], acc[:, 1])
        counts = dict(self.counts)
        counts.update(
            {
                "blocks": nf.counters.blocks,
                "samples used": nf.counters.samples,
                "samples before the filter start": self._i_start,
                "gps fixes used": nf.counters.gps_used,
                "gps positions rejected (gate)": nf.counters.gps_rejected_pos,
                "gps velocities rejected (gate)": nf.counters.gps_rejected_vel,
                "gps resets after rejections": nf.counters.gps_resets,
                "gps resets after an outage": nf.counters.gps_gap_resets,
                "rate updates": nf.counters.rate_updates,
                "rate updates rejected (gate)": nf.counters.rate_rejected,
                "zero-rate updates at rest": nf.counters.zero_rate_used,
                "zero-rate updates rejected (gate)": nf.counters.zero_rate_rejected,
                "sideslip updates": nf.counters.sideslip_used,
                "sideslip updates rejected (gate)": nf.counters.sideslip_rejected,
                "angle-of-attack updates": nf.counters.aoa_used,
                "angle-of-attack updates rejected (gate)": nf.counters.aoa_rejected,
                "heading resets to the GPS course": nf.counters.heading_resets,
                "attitude reopened after rejected velocities": nf.counters.attitude_reopens,
                "vehicle-model updates counted as coasting": nf.counters.coast_model_updates,
                "vehicle-model updates counted as the hand-over": (
                    nf.counters.handover_model_updates
                ),
                "grey forecasts fallen back": self.n_fallbacks,
            }
        )
        return RunResult(
            estimates,
            innovations,
            np.array(self._rate_nis),
            counts,
            self.method,
            self._nq,
            nf.layout.n,
            np.array(self._rate_nis_t),
        )


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
    body_velocity_log: list[BodyVelocityRecord] | None = None,
) -> RunResult:
    """Run the GPS/array filter over a whole run (a :class:`Pipeline` fed in arrival order).

    Fixes are pushed when they arrive (time of validity plus ``latency_s``),
    between the samples, as a live link would deliver them.

    Parameters
    ----------
    samples : ArraySamples
        Channel outputs (T, N), m/s^2, uniformly sampled; non-finite rows are held.
    fixes : GpsFixes
        GPS fixes; the first one at or after the alignment sets position and velocity.
    cfg : RunConfig
        What the filter knows (see :mod:`ngnav.runconfig`).
    compensation : str, optional
        Override ``cfg.compensation.method``.
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
    body_velocity_log : list, optional
        Every sideslip and angle-of-attack update is appended to it as a
        :class:`filters.vehicle_model.BodyVelocityRecord` (what
        ``python -m studies.remainder`` measures).

    Raises
    ------
    ValueError
        Bad configuration, a rate-aided layout, no usable GPS fix, no valid sample.
    filters.ekf.CovarianceError
        If the covariance stops being symmetric positive definite, or (its
        subclass ``LostTrackError``) the tilt or rate is lost twice within
        ``REOPEN_MIN_INTERVAL_S``; its ``partial`` holds the estimates up to the
        failure.
    """
    n = cfg.layout.n_sensors
    if samples.n_channels != n:
        raise ValueError(f"config layout has {n} channels, the array data has {samples.n_channels}")
    t = samples.t_s
    if t.shape[0] < 2:
        raise ValueError(f"the run holds {t.shape[0]} array samples; at least 2 are needed")
    if truth is not None and (truth.t_s.shape != t.shape or not np.allclose(truth.t_s, t)):
        raise ValueError("truth must be sampled at the array's sample times")
    pipe = Pipeline(
        cfg,
        dt_s=float(np.median(np.diff(t))),
        compensation=compensation,
        use_gps=use_gps,
        true_layout=true_layout,
        truth=truth,
        bound=bound,
        body_velocity_log=body_velocity_log,
    )
    try:
        _feed(pipe, samples, fixes, progress)
    except CovarianceError as exc:
        if pipe.started and pipe.n_epochs:
            exc.partial = pipe.result()
        raise
    return pipe.result()


def _feed(pipe: Pipeline, samples: ArraySamples, fixes: GpsFixes, progress) -> None:
    """Push a whole run into ``pipe`` in arrival order and finish it."""
    t = samples.t_s
    arrival = fixes.t_s + fixes.latency_s
    order = np.argsort(arrival, kind="stable")
    # the sample after which each fix arrives
    after = np.searchsorted(t, arrival[order], side="right")
    i = 0
    n_t = t.shape[0]
    step = max(1, n_t // 50)
    for m, j in zip(order.tolist(), after.tolist(), strict=True):
        while i < j:
            k = min(j, i + step)
            pipe.push_samples(t[i:k], samples.accel_mps2[i:k])
            i = k
            if progress is not None:
                progress(i / n_t)
        pipe.push_fix(
            fixes.t_s[m],
            fixes.lat_deg[m],
            fixes.lon_deg[m],
            fixes.alt_m[m],
            fixes.vel_ned_mps[m],
            fixes.h_acc_m[m],
            fixes.v_acc_m[m],
            fixes.vel_acc_mps[m],
        )
    while i < n_t:
        k = min(n_t, i + step)
        pipe.push_samples(t[i:k], samples.accel_mps2[i:k])
        i = k
        if progress is not None:
            progress(i / n_t)
    pipe.finish()


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
