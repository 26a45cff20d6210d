"""Error-state (multiplicative) EKF: compensated nine-accelerometer array + GPS.

filterpy is the engine: every covariance step is ``filterpy.kalman.predict``
or ``filterpy.kalman.update`` (Joseph form) with the F, Q, H, R built here.
The nominal state (position, velocity, attitude quaternion, body rate,
feature biases) is propagated by the array's compensated samples:

- rate:      ``w_k = w_{k-1} + (wdot_{k-1} + wdot_k - 2 b_wdot) dt / 2``
- attitude:  ``q_k = q_{k-1} * exp((w_{k-1} + w_k) dt / 2)``
- velocity:  ``v_k = v_{k-1} + (a_{k-1} + a_k) dt / 2`` with ``a = C_nb (f - b_f) + g``;
  position by the trapezoid.

Samples are instantaneous values at their times (as a simulation makes
them); the trapezoid keeps the integration error second order in ``dt``.

Samples are processed in blocks (``filter_rate_hz``, 100 Hz by default; a
block also ends at every GPS fix time): the nominal state is propagated
sample by sample, the covariance once per block, and the block's mean
rate-quadratic terms update the rate (SPEC section 2; the information a
six-accelerometer layout lacks). The error state is injected into the nominal
state after every update and reset to zero.

Second-order terms (SPEC section 7) are kept: the expected rotated specific
force ``E[C f] = (I + (P_att - tr(P_att) I) / 2) C f``, the expected products
``E[w_i w_j] = w_i w_j + P_ij`` with their spread in R, and the mean and spread
of the sideslip model's quadratic part (:meth:`NavFilter.sideslip_second_order`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from filters.constraints import ConstraintsMixin
from filters.feature_model import FeatureModelMixin
from filters.measurements import MeasurementsMixin
from filters.noise import FilterNoise
from filters.nominal import NominalMixin
from filters.process import ProcessMixin
from filters.remainder import RemainderMixin
from filters.state import ATT, POS, RATE, VEL, StateLayout
from filters.supervision import Counters, SupervisionMixin
from filters.updates import Measurement, update_correlated
from filters.vehicle_model import (
    ATTITUDE_REMAINDER_UPDATES,
    COAST_AFTER_S,
    COAST_REMAINDER_UPDATES,
    SIDESLIP_REMAINDER_UPDATES,
    BodyVelocityRecord,
)
from ngnav.conventions import gravity_n_mps2
from ngnav.rotation import (
    quat_normalize,
)


@dataclass
class NavFilter(
    FeatureModelMixin,
    NominalMixin,
    ProcessMixin,
    MeasurementsMixin,
    ConstraintsMixin,
    RemainderMixin,
    SupervisionMixin,
):
    """The GPS/array error-state EKF.

    Parameters
    ----------
    noise : FilterNoise
        Feature noise and bias model.
    quad_pairs : array (nq, 2) of int
        Body-rate component pairs ``(i, j)`` of the solved quadratic terms
        ``w_i w_j`` (e.g. products ``(1, 2), (0, 2), (0, 1)`` for the nine-cube).
    antenna_b_m : array (3,)
        GPS antenna position from the array's reference point, FRD, m.
    gate_probability : float
        Innovation gate: a fix whose NIS exceeds the chi-square quantile of
        this probability is rejected (counted). 0.9999 by default.
    rate_measurement : bool
        Use the rate-quadratic terms as a rate measurement.
    sensor_axes_b : array (N, 3), optional
        Nominal sensing axes; with ``solve_matrix`` and a nonzero
        ``noise.position_sigma_m`` they switch on the ``DR`` states.
    solve_matrix : array (k, N), optional
        The solve operator ``S`` (solved features from channel outputs).
    sensor_positions_b_m : array (N, 3), optional
        Nominal sensor positions, FRD, m; with ``solve_matrix`` and
        ``noise.cal_prior_cov`` they switch on the ``CAL`` states (the load at each
        sensor is what their error is read through).
    aoa_prior_sigma_rad : float
        > 0 carries the angle of attack as a state (``AOA``) with this prior
        1-sigma, rad; 0 (the default) assumes zero angle of attack.
    aoa_rw_rad_rts : float
        Random walk of the angle-of-attack state, rad/sqrt(s).
    aoa_lift_k_m : float
        The airframe's lift law ``K`` (m): with it the state is the law's offset
        ``alpha_b`` and the angle of attack is ``w(V) (alpha_b + K n_w / V^2)`` (see
        :meth:`set_load`); 0 (the default) makes the state the angle of attack itself.
    liftoff_speed_mps : float
        The lift-off blend ``w(V)``: 0 below 0.8 times this speed (on the wheels,
        no angle of attack), 1 from it up, a minimum-jerk step between; 0 (the
        default) means always flying.
    aoa_lift_k_sigma_m : float
        > 0 (with ``aoa_lift_k_m``) carries the error of ``K`` as a second, constant
        ``AOA`` state with this prior 1-sigma, m.
    quad_feedback : array (nq, 6), optional
        With a forecast compensation: the sensitivity of the solved quadratic terms
        to the forecast's six rate products ``(wx^2, wy^2, wz^2, wy wz, wx wz, wx wy)``
        (their rows of ``S E``). The forecast extrapolates the filter's own rate
        history, so a rate error ``dw`` returns in the compensated terms as
        ``E_q J6 dw`` beside the products' own ``J dw``; the rate measurement's
        Jacobian carries both (see :meth:`rate_model`). None: the products alone.
    feature_quad_feedback : array (6, 6), optional
        The same for the solved angular acceleration and force (their rows of ``S E``):
        a rate error returns in them as ``A S E_q J6 dw`` (``A`` the loop's map,
        ``noise.bias_effect``), which the transition carries (:meth:`propagation_matrices`).
        Negligible at a few rad/s; at a projectile's spin (12 rad/s) it drives the rate
        error with a time constant of 10-20 s.
    remainder_updates, attitude_remainder_updates : float
        How many times the body-velocity updates count their second-order
        remainder's variance and its attitude-product part (>= 1;
        :func:`remainder_variance`). Defaults :data:`SIDESLIP_REMAINDER_UPDATES`
        and :data:`ATTITUDE_REMAINDER_UPDATES`; ``python -m studies.remainder`` measures what
        a flight's remainders need.
    coast_remainder_updates, coast_after_s, coast_hold_s : float
        The whole remainder's count in a coast (default
        :data:`COAST_REMAINDER_UPDATES`), the time without an accepted GPS position
        that makes one (s, default :data:`COAST_AFTER_S`; at least
        :data:`COAST_AFTER_FIXES` fix intervals), and how long after the
        last coasting update the count holds (s; 0 by default, the pipeline passes
        the count's own length at its 5 Hz): :meth:`current_remainder_updates`.
    handover_hold_s : float
        How long after the vehicle models' first update since :meth:`initialise` the
        body-velocity updates count the whole remainder ``coast_remainder_updates``
        times, as after a coast (s, >= 0; default 0). The pipeline passes the coast's
        hold for every alignment: a configured one (a hand-over in flight, whose first
        update comes at once) and a static one (whose first comes in the take-off
        roll): either way the attitude errors the models first meet, a hand-over's or
        the configured heading's, have not yet been renewed by any measurement
        (docs/notes/filter-notes.md, "the hand-over counted as a coast's
        end").
    count_by_prior_weight : bool
        Outside the hand-over and coasts, scale the sideslip update's two counts by the
        weight the update keeps on the prior along the constraint
        (:func:`filters.vehicle_model.prior_weighted_count`): in GPS-held flight, where
        the prior along the constraint is hundreds to thousands of times R, the count
        falls to about 1 and the constraint's direction keeps the remainder's own
        variance after the update (docs/notes/filter-notes.md, "the count by the prior's
        weight"). The angle-of-attack update keeps its counts: its prior along the
        constraint holds the lift law's states, which persist from one update to the next
        rather than being fresh process noise. False (the default): the configured counts
        everywhere; the pipeline turns it on for a fixed-wing.
    body_velocity_error : bool
        Take the velocity error in the body frame: the truth is
        ``exp(dtheta) C (C^T v + dv_b)``, and the Kalman state's ``VEL`` holds its NED
        image ``xi_v = C dv_b + dtheta x v`` (equal to the NED error to first order, so
        F, H and P keep their NED coordinates). The vehicle models (``n_b . v_b = 0``) are
        then exactly linear, with no attitude-product remainder to count; what changes
        (:meth:`_inject`, :meth:`propagate`, :meth:`body_velocity_second_order`,
        :meth:`velocity_curvature`):

        - a correction turns the nominal velocity with the attitude
          (``v <- exp(dtheta) (v + dv + v x dtheta)``) and the velocity rows take the
          reset's Jacobian (``xi_v`` moves with the attitude correction by ``V dtheta``
          per radian of the error left);
        - the propagation's mean correction is gravity's attitude curvature and the
          rate-velocity product, not the force's;
        - the models' remainder is the body velocity's own second order over the
          interval since the model's last update (rate error times body-velocity error,
          gravity's attitude curvature);
        - the NED velocity a user reads, ``v + xi_v + c`` with ``c = dtheta x xi_v -
          dtheta x (dtheta x v) / 2``, takes ``c``'s mean and covariance (estimates and
          the GPS velocity fix).

        False (the default): the NED velocity error (docs/notes/filter-notes.md, "the velocity
        error in the body frame, with the reset's Jacobian").

    Attributes
    ----------
    body_velocity_log : list of BodyVelocityRecord or None
        Set to a list to have every sideslip and angle-of-attack update recorded in it
        (None, the default, records nothing).
    """

    noise: FilterNoise
    quad_pairs: np.ndarray
    antenna_b_m: np.ndarray
    gate_probability: float = 0.9999
    rate_measurement: bool = True
    sensor_axes_b: np.ndarray | None = None
    solve_matrix: np.ndarray | None = None
    sensor_positions_b_m: np.ndarray | None = None
    aoa_prior_sigma_rad: float = 0.0
    aoa_rw_rad_rts: float = 0.0
    aoa_lift_k_m: float = 0.0
    liftoff_speed_mps: float = 0.0
    aoa_lift_k_sigma_m: float = 0.0
    quad_feedback: np.ndarray | None = None
    feature_quad_feedback: np.ndarray | None = None
    remainder_updates: float = SIDESLIP_REMAINDER_UPDATES
    attitude_remainder_updates: float = ATTITUDE_REMAINDER_UPDATES
    coast_remainder_updates: float = COAST_REMAINDER_UPDATES
    coast_after_s: float = COAST_AFTER_S
    coast_hold_s: float = 0.0
    handover_hold_s: float = 0.0
    count_by_prior_weight: bool = False
    body_velocity_error: bool = False
    counters: Counters = field(default_factory=Counters)

    def __post_init__(self) -> None:
        for name in ("remainder_updates", "attitude_remainder_updates", "coast_remainder_updates"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 1.0 <= v <= 1e4):
                raise ValueError(f"{name} must be a number in [1, 10000], got {v}")
        for name in ("coast_after_s", "coast_hold_s", "handover_hold_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
        self._coast_until = -np.inf
        self._handover_until = -np.inf
        #: Whether the hand-over's hold starts at the next body-velocity update.
        self._handover_pending = False
        #: Filter time of each vehicle model's last accepted update, s, by axis.
        self._model_last_t: dict[int, float] = {}
        #: Whether each vehicle model's last update passed its gate, by axis.
        self._model_last_ok: dict[int, bool] = {}
        self._t_prev_fix = -np.inf
        #: Spacing of the last two GPS fixes received, s (NaN before the second).
        self.fix_interval_s = float("nan")
        self.body_velocity_log: list[BodyVelocityRecord] | None = None
        #: A smoother's lag-one clone (:class:`filters.smoother.LagOne`), or None.
        self.lag = None
        self.quad_pairs = np.asarray(self.quad_pairs, dtype=int).reshape(-1, 2)
        self.antenna_b_m = np.asarray(self.antenna_b_m, dtype=float).reshape(3)
        n_dr = 0
        if self.noise.position_sigma_m > 0:
            if self.sensor_axes_b is None or self.solve_matrix is None:
                raise ValueError("position states need sensor_axes_b and solve_matrix")
            n_dr = 3 * self.sensor_axes_b.shape[0]
        n_cal = 0
        if self.noise.cal_prior_cov is not None:
            if self.sensor_positions_b_m is None or self.solve_matrix is None:
                raise ValueError("calibration states need sensor_positions_b_m and solve_matrix")
            n_cal = 3 * np.shape(self.sensor_positions_b_m)[0]
            if np.shape(self.noise.cal_prior_cov) != (n_cal, n_cal):
                raise ValueError(f"noise.cal_prior_cov must be ({n_cal}, {n_cal})")
            self.sensor_positions_b_m = np.asarray(self.sensor_positions_b_m, dtype=float)
        for name in (
            "aoa_prior_sigma_rad",
            "aoa_rw_rad_rts",
            "aoa_lift_k_m",
            "liftoff_speed_mps",
            "aoa_lift_k_sigma_m",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
        n_aoa = int(self.aoa_prior_sigma_rad > 0)
        if n_aoa and self.aoa_lift_k_m > 0 and self.aoa_lift_k_sigma_m > 0:
            n_aoa = 2
        self.layout = StateLayout(self.quad_pairs.shape[0], n_dr, n_aoa, n_cal)
        n = self.layout.n
        k = 6 + self.layout.nq
        for name in ("feature_cov", "bias_prior_cov", "bias_rw_cov", "bias_effect"):
            m = getattr(self.noise, name)
            if m is not None and np.shape(m) != (k, k):
                raise ValueError(f"noise.{name} must be ({k}, {k}), got {np.shape(m)}")
        bw = self.noise.block_wdot_cov
        if bw is not None and np.shape(bw) != (3, 3):
            raise ValueError(f"noise.block_wdot_cov must be (3, 3), got {np.shape(bw)}")
        cq = self.noise.quad_cross_cov
        if cq is not None and np.shape(cq) != (6, self.layout.nq):
            raise ValueError(
                f"noise.quad_cross_cov must be (6, {self.layout.nq}), got {np.shape(cq)}"
            )
        self._block: tuple[int, float, np.ndarray] | None = None
        if not 0.5 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0.5, 1), got {self.gate_probability}")
        self.gate3 = float(chi2.ppf(self.gate_probability, 3))
        self.gate1 = float(chi2.ppf(self.gate_probability, 1))
        self.gate2 = float(chi2.ppf(self.gate_probability, 2))
        self.gate_q = float(chi2.ppf(self.gate_probability, max(self.layout.nq, 1)))
        self.x = np.zeros(n)
        self.P = np.eye(n)
        self.t_s = 0.0
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.w = np.zeros(3)
        self.bias = np.zeros(6 + self.layout.nq)
        self.dr = np.zeros(n_dr)
        self.dg = np.zeros(n_cal)
        self.aoa_b = 0.0
        self.aoa_k = self.aoa_lift_k_m  # the lift law's K estimate, m
        self._lift_u = 0.0  # n_w / V^2 of the last block, 1/m
        # the Jacobian's u: LIFT_JACOBIAN_LAG_BLOCKS blocks older (errors in variables)
        self._lift_u_jac = 0.0
        self._lift_u_recent: list[float] = []
        self._lift_u_var = 0.0  # the load noise's variance in u, 1/m^2
        self._lift_w = 1.0  # the lift-off blend w(V)
        self._lift_axis = np.array([0.0, 0.0, -1.0])  # n_w = _lift_axis . f (FRD)
        self._lift_dw = 0.0  # dw/dV of the lift-off blend, s/m
        # the load's sensitivity to the sensor positions (3, 3N), with DR states
        self._lift_sg_f: np.ndarray | None = None
        self._eye3 = np.eye(3)
        lay = self.layout
        #: kernels.inject_error's state offsets, and its Jacobian rows' output
        self._inject_offsets = (lay.bias.start, lay.dr.start, lay.cal.start, lay.aoa.start, n_aoa)
        self._g_rows = np.zeros((3, 3, 3))
        #: kernels.propagate_block's F and Q (n, n), C_nb at the block start (3, 3) and the
        #: mean NED force (3,), written every block
        self._fq_out = (np.zeros((n, n)), np.zeros((n, n)), np.zeros((3, 3)), np.zeros(3))
        self._g = gravity_n_mps2()
        self._consec_rejects = 0
        self._consec_slip_rejects = 0
        self._consec_vel_rejects = 0
        self.last_rate_innovation = np.zeros(self.layout.nq)
        #: Its covariance before the update (nq, nq): the parity test's metric.
        self.last_rate_innovation_cov = np.eye(self.layout.nq)
        self._last_wdot = np.zeros(3)
        self._last_f = np.zeros(3)
        #: True while a zero-rate update resets the rate at every block (the pipeline
        #: sets it): the propagation then gives the rate one block's own noise
        #: (FilterNoise.block_wdot_cov), not the loop's
        self.rate_reset_each_block = False
        #: Which rate products measure the rate (nq,): all of them until channels are
        #: excluded (:meth:`set_solve`).
        self.rate_rows = np.ones(self.layout.nq, dtype=bool)
        #: What aided quadratic terms leave in the solved [wdot, f] (6, 6) and rate
        #: products (nq, 6), or None (:meth:`set_solve`).
        self._aided_quadratics: np.ndarray | None = None
        self._aided_in_quad: np.ndarray | None = None
        #: A walk added to the biases' (k, k), per s: a suspect channel's offset
        #: (:meth:`set_extra_bias_walk`).
        self.extra_bias_walk = np.zeros((6 + self.layout.nq, 6 + self.layout.nq))
        self._derive_feature_model()

    # ------------------------------------------------------------------ set-up
    def initialise(
        self,
        t_s: float,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        q_nb: np.ndarray,
        omega_b_rps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: np.ndarray,
        att_sigma_rad: np.ndarray,
        rate_sigma_rps: float,
        aoa_rad: float = 0.0,
        bias: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Set the nominal state and a diagonal prior (biases from ``noise.bias_prior_cov``).

        ``aoa_rad`` is the ``AOA`` state's prior mean (the angle of attack, or with
        a lift law its offset ``alpha_b``); its 1-sigma is ``aoa_prior_sigma_rad``.
        ``bias``, if given, is the bias states' estimate (6 + nq,) and covariance to start
        from instead of zero and the prior (a start again keeps the array's).
        """
        self.t_s = float(t_s)
        self.pos = np.array(pos_ned_m, dtype=float)
        self.vel = np.array(vel_ned_mps, dtype=float)
        self.q = quat_normalize(np.asarray(q_nb, dtype=float))
        self.w = np.array(omega_b_rps, dtype=float)
        self.bias = np.zeros(6 + self.layout.nq) if bias is None else np.array(bias[0], dtype=float)
        p = np.zeros((self.layout.n, self.layout.n))
        p[POS, POS] = np.diag(np.broadcast_to(pos_sigma_m, 3) ** 2)
        p[VEL, VEL] = np.diag(np.broadcast_to(vel_sigma_mps, 3) ** 2)
        p[ATT, ATT] = np.diag(np.broadcast_to(att_sigma_rad, 3) ** 2)
        p[RATE, RATE] = np.eye(3) * rate_sigma_rps**2
        bs = self.layout.bias
        p[bs, bs] = self.noise.bias_prior_cov if bias is None else bias[1]
        dr = self.layout.dr
        p[dr, dr] = np.eye(self.layout.n_dr) * self.noise.position_sigma_m**2
        self.dr = np.zeros(self.layout.n_dr)
        cal = self.layout.cal
        if self.layout.n_cal:
            p[cal, cal] = self.noise.cal_prior_cov
        self.dg = np.zeros(self.layout.n_cal)
        self.aoa_b = float(aoa_rad) if self.layout.n_aoa else 0.0
        self.aoa_k = self.aoa_lift_k_m
        self._lift_u, self._lift_w = 0.0, 1.0
        self._lift_u_jac = 0.0
        self._lift_u_recent = []
        self._lift_u_var = 0.0
        self._lift_sg_f = None
        ia = self.layout.aoa
        p[ia, ia] = np.diag(
            [self.aoa_prior_sigma_rad**2, self.aoa_lift_k_sigma_m**2][: ia.stop - ia.start]
        )
        self.P = p
        self.x = np.zeros(self.layout.n)
        self.t_last_position_fix = self.t_s
        # 1-sigma NED velocity and position errors of the force's second-order part since
        # the last position or velocity measurement (ProcessMixin._add_curvature_noise)
        self._curvature_sd_mps = np.zeros(3)
        self._curvature_sd_m = np.zeros(3)
        # the hold starts at the vehicle models' first update (current_remainder_updates)
        self._handover_until = -np.inf
        self._handover_pending = self.handover_hold_s > 0.0
        self.check_covariance("initialisation")

    def _apply(self, meas: Measurement) -> None:
        """Fuse one measurement (ungated) and fold the error into the nominal state.

        filterpy's update (:func:`filters.updates.update_correlated`, with the noise
        correlated with the prior as ``meas.cross`` where there is such a correlation).
        """
        if self.lag is not None:
            self.lag.update(meas, self.P)
        self.x, self.P = update_correlated(self.x, self.P, meas.z, meas.R, meas.H, meas.cross)
        self._inject()
