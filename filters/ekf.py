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

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import predict as kf_predict
from scipy.stats import chi2

from filters.state import ATT, N_NAV, POS, RATE, VEL, StateLayout
from filters.updates import quadratic_form, update_correlated
from filters.vehicle_model import (
    ATTITUDE_REMAINDER_UPDATES,
    BODY_REMAINDER_INTERVAL_S,
    BODY_REMAINDER_MAX_INTERVAL_S,
    COAST_AFTER_FIXES,
    COAST_AFTER_S,
    COAST_REMAINDER_UPDATES,
    LATERAL,
    LIFT_JACOBIAN_LAG_BLOCKS,
    SIDESLIP_REMAINDER_UPDATES,
    VERTICAL,
    BodyVelocityRecord,
    Remainder,
    attitude_product_matrix,
    blend_spread_var,
    constraint_axes,
    prior_weighted_count,
    remainder_moments,
    remainder_variance,
)
from ngnav.compensation import QUAD_PAIRS
from ngnav.conventions import gravity_n_mps2
from ngnav.errors import CovarianceError
from ngnav.flight import quat_from_euler
from ngnav.motion import min_jerk_step
from ngnav.records import GpsUpdateResult
from ngnav.rotation import (
    cross_rows,
    dcm_from_quat,
    euler_from_quat,
    quat_from_rotvec,
    quat_normalize,
    quat_rotate_by_rotvec,
    skew,
)

#: Consecutive fixes after an outage that fail the position gate before the filter is put
#: on the fix anyway. The first fix after an outage resets position and velocity when it
#: passes the gate (a glitch then is one fix off, rejected); but a coast that ended more
#: sure of itself than its errors fails the gate on every fix, and waiting for the general
#: run of rejections (the pipeline's ``RESET_AFTER_REJECTS``, 5 s at 5 Hz) left
#: ``uav-survey`` run 11 off for 5 s after its outage. Three fixes in a row that disagree
#: with the coast are the receiver, not a glitch.
GAP_RESET_AFTER_REJECTS = 3


def _product_derivatives(pairs: Sequence[Sequence[int]]) -> np.ndarray:
    """``D`` (len(pairs), 3, 3) with ``d(w_i w_j)/dw = D[r] @ w`` for each pair ``(i, j)``.

    ``D[r, c, m] = [c = i][m = j] + [c = j][m = i]``.
    """
    d = np.zeros((len(pairs), 3, 3))
    for r, (i, j) in enumerate(pairs):
        d[r, i, j] += 1.0
        d[r, j, i] += 1.0
    return d


#: The (attitude, velocity) error rows of the body-velocity models' second-order term.
_DTHETA_DV = np.r_[ATT, VEL]
_DTHETA_DV_IX = np.ix_(_DTHETA_DV, _DTHETA_DV)
#: (attitude, velocity, rate) error indices: the body-velocity remainder's variables.
_DTHETA_DV_DW = np.r_[ATT, VEL, RATE]
#: Levi-Civita symbol: ``(a x b)_i = EPS[i] a . b``, EPS[i, j, k] = eps_ijk.
_EPS = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_i, _j, _k] = 1.0
    _EPS[_i, _k, _j] = -1.0


_E3 = np.eye(3)
#: The NED velocity curvature's bilinear part, ``(dtheta x xi_v)_i``, as ``x^T M_i x / 2``
#: over ``x = (dtheta, xi_v)`` (:meth:`NavFilter.velocity_curvature`).
_CURVATURE_CROSS = np.zeros((3, 6, 6))
_CURVATURE_CROSS[:, 0:3, 3:6] = _EPS
_CURVATURE_CROSS[:, 3:6, 0:3] = _EPS.transpose(0, 2, 1)


def _axial(x: np.ndarray) -> np.ndarray:
    """``sum_jk eps_ijk x_jk`` (3,): ``E[a x b]`` for ``x = E[a b^T]``."""
    return np.array([x[1, 2] - x[2, 1], x[2, 0] - x[0, 2], x[0, 1] - x[1, 0]])


def body_velocity_reset_jacobian(
    dtheta: np.ndarray, dxi_v: np.ndarray, vel_ned_mps: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The velocity rows of the body-velocity error's reset Jacobian, ``(G_vv, G_vtheta)``.

    A correction ``(dtheta, dxi_v)`` (NED rad, NED m/s) injected body-style
    (:meth:`NavFilter._inject` with ``body_velocity_error``) at the nominal velocity
    ``vel_ned_mps`` leaves errors ``e`` about the old nominal; about the new one the
    velocity error is, to first order in ``e``,

    ``xi_v' = (I + [dtheta]x) e_v + ([dtheta]x [v]x - [dxi_v]x - [v]x [dtheta]x / 2) e_theta``

    (``C' dv_b' = exp(dtheta) C (dv_b - dv_b_hat)`` and the new attitude error
    ``(I + [dtheta]x / 2) e_theta``: ``exp(dtheta') = exp(dtheta + e) exp(-dtheta)``, whose
    first-order term is ``[dtheta, e] / 2``). Both (3, 3).
    """
    st = skew(np.asarray(dtheta, dtype=float))
    sv = skew(np.asarray(vel_ned_mps, dtype=float))
    gvv = np.eye(3) + st
    gvt = st @ sv - skew(np.asarray(dxi_v, dtype=float)) - 0.5 * sv @ st
    return gvv, gvt


#: Largest curvature ``|v| |dtheta|^2 / 2`` (m/s) of a correction the body-frame velocity
#: error (``NavFilter.body_velocity_error``) injects body-style. A larger attitude
#: correction (a tilt relearned after :meth:`NavFilter.reopen_attitude`, tens of degrees)
#: would turn the NED velocity by metres per second beyond the update's linear step and
#: the next GPS velocities would fail their gate: such a correction is injected as the
#: NED error's (velocity added, attitude reset only). 0.05 m/s is half a GPS velocity
#: sigma; at 60 m/s it lets through corrections up to 2.3 deg, the hand-over's 1 deg with
#: room.
BODY_INJECTION_MAX_CURVATURE_MPS = 0.05
#: Largest curvature ``|v| tr(P_att) / 2`` (m/s) the attitude's uncertainty may give the
#: NED velocity while the body-frame velocity error is in use
#: (:meth:`NavFilter.in_body_frame`): above it (a heading several degrees uncertain, a
#: tilt reopened) the NED error's linearisation is the better one, since the NED velocity
#: does not depend on the attitude at all. A GPS velocity sigma (0.1 m/s).
BODY_FRAME_MAX_CURVATURE_MPS = 0.1


def static_mean_walk_s(dt_s: float, n_samples: int) -> float:
    """The weight (s) of a random walk's spread between its last sample and its mean.

    For ``n_samples`` samples ``dt_s`` apart of a walk with spectral density ``q``
    (per second), ``b_last - mean(b)`` has variance ``q * walk_s`` with
    ``walk_s = dt_s (n - 1)(2 n - 1) / (6 n)``: a third of the span for many samples,
    zero for one. :meth:`NavFilter.update_static_biases` reads its mean with it.
    """
    n = int(n_samples)
    if n < 1 or not dt_s >= 0.0:
        raise ValueError(f"need n_samples >= 1 and dt_s >= 0, got {n_samples}, {dt_s}")
    return float(dt_s) * (n - 1) * (2 * n - 1) / (6.0 * n)


@dataclass(frozen=True)
class FilterNoise:
    """Noise model of the filter, in the solved-feature space.

    Attributes
    ----------
    feature_cov : array (k, k)
        Per-sample covariance of the solved features ``[wdot(3), f(3), quad(nq)]``.
    bias_prior_cov : array (k, k)
        Prior covariance of the feature biases (turn-on bias mapped through S).
    bias_rw_cov : array (k, k)
        Random-walk spectral density of the feature biases, per second.
    position_sigma_m : float
        Prior 1-sigma of each residual sensor-position error (per axis, m);
        0 leaves the ``DR`` block out (see :mod:`filters.state`).
    quad_cross_cov : array (6, nq), optional
        Per-sample covariance of the ``[wdot, f]`` noise with the quadratic terms'
        noise, as solved from the same channel samples (the solve mixes every
        channel into every feature: on the nine-cube the correlations are 0.25 and
        0.5). A block's rate measurement then shares noise with the propagation
        that led to it; :meth:`NavFilter.update_rate` carries that cross-covariance.
        None treats them as independent.
    bias_effect : array (k, k), optional
        What an error of the bias states (true less estimated, the raw feature biases
        ``S b``) leaves in the compensated features the filter propagates and
        measures with. A forecast compensation feeds its own history back, and that
        history holds the block means less the bias *estimates*: the estimates'
        error comes back through the loop like the noise does, and over many blocks
        the features carry ``T (S b - b_hat)`` with ``T = [[A, 0], [-E_q A, I]]``,
        ``A = (I + E_6)^-1`` (:func:`filters.pipeline.filter_noise`). The transition's
        bias columns, the rate measurement's and the lift law's force-bias term use
        it. None: the identity (no forecast feedback).
    block_wdot_cov : array (3, 3), optional
        Per-sample covariance of the angular acceleration as one block's own samples
        carry it: the raw solve's. ``feature_cov`` maps the noise through a forecast
        compensation's loop, which holds for errors integrated over many blocks; an
        error that lives one block (the rate while a zero-rate update resets it at
        every block, :attr:`NavFilter.rate_reset_each_block`) sees this one. None:
        ``feature_cov``'s.
    """

    feature_cov: np.ndarray
    bias_prior_cov: np.ndarray
    bias_rw_cov: np.ndarray
    position_sigma_m: float = 0.0
    quad_cross_cov: np.ndarray | None = None
    bias_effect: np.ndarray | None = None
    block_wdot_cov: np.ndarray | None = None


@dataclass
class Counters:
    """What the filter did, for the run summary."""

    blocks: int = 0
    samples: int = 0
    gps_used: int = 0
    gps_rejected_pos: int = 0
    gps_rejected_vel: int = 0
    gps_resets: int = 0
    gps_gap_resets: int = 0
    rate_updates: int = 0
    rate_rejected: int = 0
    held_samples: int = 0
    sideslip_used: int = 0
    sideslip_rejected: int = 0
    aoa_used: int = 0
    aoa_rejected: int = 0
    heading_resets: int = 0
    attitude_reopens: int = 0
    coast_model_updates: int = 0
    handover_model_updates: int = 0
    zero_rate_used: int = 0
    zero_rate_rejected: int = 0


@dataclass
class NavFilter:
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
        variance after the update (docs/notes/filter-notes.md, "the count by the prior's weight").
        The
        angle-of-attack update keeps its counts: its prior along the constraint holds
        the lift law's states, which persist from one update to the next rather than
        being fresh process noise. False (the default): the configured counts everywhere.
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
    aoa_prior_sigma_rad: float = 0.0
    aoa_rw_rad_rts: float = 0.0
    aoa_lift_k_m: float = 0.0
    liftoff_speed_mps: float = 0.0
    aoa_lift_k_sigma_m: float = 0.0
    quad_feedback: np.ndarray | None = None
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
        self.quad_pairs = np.asarray(self.quad_pairs, dtype=int).reshape(-1, 2)
        self.antenna_b_m = np.asarray(self.antenna_b_m, dtype=float).reshape(3)
        n_dr = 0
        if self.noise.position_sigma_m > 0:
            if self.sensor_axes_b is None or self.solve_matrix is None:
                raise ValueError("position states need sensor_axes_b and solve_matrix")
            n_dr = 3 * self.sensor_axes_b.shape[0]
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
        self.layout = StateLayout(self.quad_pairs.shape[0], n_dr, n_aoa)
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
        self._eye = np.eye(n)
        self._eye3 = np.eye(3)
        self._g = gravity_n_mps2()
        self._sww = self.noise.feature_cov[0:3, 0:3]
        # the rate's noise over one block (FilterNoise.block_wdot_cov): the loop's mapped
        # noise plus the positive part of what the mapping took off
        self._sww_block = self._sww
        if self.noise.block_wdot_cov is not None:
            ev, vec = np.linalg.eigh(np.asarray(self.noise.block_wdot_cov) - self._sww)
            self._sww_block = self._sww + (vec * np.maximum(ev, 0.0)) @ vec.T
        #: True while a zero-rate update resets the rate at every block (the pipeline
        #: sets it): the propagation then gives the rate one block's own noise
        #: (FilterNoise.block_wdot_cov), not the loop's
        self.rate_reset_each_block = False
        self._sff = self.noise.feature_cov[3:6, 3:6]
        self._sfw = self.noise.feature_cov[3:6, 0:3]
        self._sqq = self.noise.feature_cov[6:, 6:]
        self._consec_rejects = 0
        self._consec_slip_rejects = 0
        self._consec_vel_rejects = 0
        self.last_rate_innovation = np.zeros(self.layout.nq)
        self._last_wdot = np.zeros(3)
        self._last_f = np.zeros(3)
        # what a bias error leaves in the compensated [wdot, f, quad] (FilterNoise.bias_effect)
        te = self.noise.bias_effect
        te = np.eye(k) if te is None else np.array(te, dtype=float)
        self._bias_effect_f = te[3:6].copy()  # into the force (FRD), per block rotated to NED
        # the constant part of the error dynamics, copied and filled per block: only
        # the navigation rows (position, velocity, attitude, rate) of F are non-zero
        # (biases and the angle-of-attack offset walk, DR and K are constants)
        fc = np.zeros((N_NAV, n))
        fc[POS, VEL] = np.eye(3)
        fc[RATE, self.layout.bias] = -te[0:3]
        self._fc_base = fc
        # the rate measurement's Jacobian without its rate columns (filled per block)
        h_rate = np.zeros((self.layout.nq, n))
        h_rate[:, self.layout.bias] = te[6:]
        self._h_rate_base = h_rate
        self._t12 = np.eye(12)
        self._eye12 = np.eye(N_NAV)
        self._q12_cache: dict[tuple[int, float], np.ndarray] = {}
        self._q_walk_cache: dict[float, np.ndarray] = {}
        self._weights_cache: dict[tuple[int, float], tuple[np.ndarray, ...]] = {}
        if self.solve_matrix is not None:
            # T S with each column repeated 3 times: the compensated features carry the
            # sensor positions' effect through the forecast's loop as they carry a bias's
            # (geometry_jacobian)
            ts = te @ np.asarray(self.solve_matrix, dtype=float)
            self._solve_rep = np.repeat(ts, 3, axis=1)
        d = _product_derivatives(self.quad_pairs.tolist())
        if self.quad_feedback is not None:
            fb = np.asarray(self.quad_feedback, dtype=float)
            if fb.shape != (self.layout.nq, 6):
                raise ValueError(
                    f"quad_feedback must have shape ({self.layout.nq}, 6), got {fb.shape}"
                )
            d = d + np.einsum("rs,scm->rcm", fb, _product_derivatives(QUAD_PAIRS))
        self._quad_d = d

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
    ) -> None:
        """Set the nominal state and a diagonal prior (biases from ``noise.bias_prior_cov``).

        ``aoa_rad`` is the ``AOA`` state's prior mean (the angle of attack, or with
        a lift law its offset ``alpha_b``); its 1-sigma is ``aoa_prior_sigma_rad``.
        """
        self.t_s = float(t_s)
        self.pos = np.array(pos_ned_m, dtype=float)
        self.vel = np.array(vel_ned_mps, dtype=float)
        self.q = quat_normalize(np.asarray(q_nb, dtype=float))
        self.w = np.array(omega_b_rps, dtype=float)
        self.bias = np.zeros(6 + self.layout.nq)
        p = np.zeros((self.layout.n, self.layout.n))
        p[POS, POS] = np.diag(np.broadcast_to(pos_sigma_m, 3) ** 2)
        p[VEL, VEL] = np.diag(np.broadcast_to(vel_sigma_mps, 3) ** 2)
        p[ATT, ATT] = np.diag(np.broadcast_to(att_sigma_rad, 3) ** 2)
        p[RATE, RATE] = np.eye(3) * rate_sigma_rps**2
        bs = self.layout.bias
        p[bs, bs] = self.noise.bias_prior_cov
        dr = self.layout.dr
        p[dr, dr] = np.eye(self.layout.n_dr) * self.noise.position_sigma_m**2
        self.dr = np.zeros(self.layout.n_dr)
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
        # the hold starts at the vehicle models' first update (current_remainder_updates)
        self._handover_until = -np.inf
        self._handover_pending = self.handover_hold_s > 0.0
        self.check_covariance("initialisation")

    # ------------------------------------------------------------- propagation
    def propagate(
        self, wdot: np.ndarray, f: np.ndarray, dt: float, sg: np.ndarray | None = None
    ) -> np.ndarray:
        """Propagate through a block of K compensated samples.

        Samples are instantaneous values at the sample times; the block runs
        from the previous sample (the last one propagated, kept by the filter;
        set by :meth:`set_last_sample` at the start) to the last sample of
        ``wdot``/``f``. Rate, velocity and position are integrated by the
        trapezoid rule, the attitude by the product of the sample rotations.

        Parameters
        ----------
        wdot, f : arrays (K, 3)
            Angular acceleration (rad/s^2) and specific force (m/s^2), FRD.
        dt : float
            Sample interval, s.
        sg : array (k, 3N), optional
            The block's sensitivity of the solved features to the sensor
            positions (:meth:`geometry_jacobian`); required with ``DR`` states.

        Returns
        -------
        omega_b_rps : array (K, 3)
            The nominal rate at each sample (for the rate measurement).
        """
        k = wdot.shape[0]
        bw, bf = self._feature_offset(sg)
        mw, mw0, wts, wts1 = self._block_weights(k, dt)
        # rate, sample rotation vectors and their running sum (attitude relative to
        # the block start, second order) at once: all linear in the K + 1 samples
        wd = np.concatenate([self._last_wdot[None], wdot])
        wd -= bw
        lin = mw @ wd
        lin += mw0 * self.w
        w = lin[:k]
        alpha = lin[k : 2 * k]
        cum = lin[2 * k :]
        f_c = np.concatenate([self._last_f[None], f])
        f_c -= bf
        # rotate f_k by exp(cum_k) to the block-start body frame, to second order
        cf = cross_rows(cum, f_c)
        f_b0 = f_c + cf + 0.5 * cross_rows(cum, cf)
        c0 = dcm_from_quat(self.q)
        pa = self.P[ATT, ATT]
        g_n = self._g
        if self.in_body_frame():
            # the truth's body velocity moves by f - w x v_b + C_true^T g: its mean holds
            # gravity's attitude curvature, C^T (P_att - tr(P_att) I) g / 2, and the
            # rate-velocity product's -E[dw x dv_b]
            m = c0
            g_n = g_n + 0.5 * (pa @ g_n - (pa[0, 0] + pa[1, 1] + pa[2, 2]) * g_n)
            g_n = g_n - c0 @ _axial(self._rate_body_velocity_cov(c0))
        else:
            # E[C f] = (I + (P_att - tr(P_att) I) / 2) C f  (second order in the attitude error)
            m = pa @ c0
            m *= 0.5
            m += (1.0 - 0.5 * (pa[0, 0] + pa[1, 1] + pa[2, 2])) * c0
        # the trapezoid's velocity increment, position increment and mean force
        # are weighted sums of a_n = m f_b0 + g over the samples
        y = (wts @ f_b0) @ m.T
        y += wts1 * g_n
        self.pos = self.pos + (k * dt) * self.vel + y[1]
        self.vel = self.vel + y[0]
        # attitude: exact product of the sample rotations, with the coning term
        # sum_s cum_s x alpha_s / 2, the axial vector of sum_s cum_s alpha_s^T
        m01, m02, m10, m12, m20, m21 = (cum[:-1].T @ alpha).ravel()[[1, 2, 3, 5, 6, 7]].tolist()
        cx, cy, cz = cum[-1].tolist()
        rot = [cx + 0.5 * (m12 - m21), cy + 0.5 * (m20 - m02), cz + 0.5 * (m01 - m10)]
        self.q = quat_rotate_by_rotvec(self.q, rot, left=False)
        self.w = w[-1].copy()
        self._last_wdot = wdot[-1].copy()
        self._last_f = f[-1].copy()
        self.t_s += k * dt
        f_n = y[2] - g_n
        self._predict_covariance(k, dt, c0, f_n, sg)
        self._block = (k, dt, c0)  # for the rate measurement of this block
        self.counters.blocks += 1
        self.counters.samples += k
        return w

    def _block_weights(
        self, k: int, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The block integration as matrices over its K + 1 samples (cached per K, dt).

        With ``d`` (K + 1, 3) the angular accelerations at the block's sample
        times (the previous block's last one first) and ``w0`` the rate at the
        block start, the trapezoid rule gives the rates at the K sample times
        ``W d + w0``, the sample rotation vectors ``alpha_s = dt (w_s + w_s+1) / 2``
        and their running sums ``cum_s`` (s = 0..K) as rows of ``mw @ d + mw0 w0``
        (3K + 1 rows: rates, rotation vectors, running sums). ``wts`` (3, K + 1)
        turns accelerations ``a`` at the sample times into the block's velocity
        increment (trapezoid), its position increment beyond ``K dt v0``
        (trapezoid of the trapezoid) and its mean over the K new samples;
        ``wts1`` (3, 1) are their row sums (the weights of a constant).
        """
        key = (k, dt)
        got = self._weights_cache.get(key)
        if got is not None:
            return got
        h = 0.5 * dt
        tw = np.zeros((k + 1, k + 1))  # running trapezoid: value at s minus value at 0
        for s in range(1, k + 1):
            tw[s] = tw[s - 1]
            tw[s, s - 1] += h
            tw[s, s] += h
        avg = h * (np.eye(k, k + 1) + np.eye(k, k + 1, 1))  # interval mean times dt
        run = np.tril(np.ones((k + 1, k)), -1)  # running sum from 0
        mw = np.vstack([tw[1:], avg @ tw, run @ avg @ tw])
        ones = np.ones(k + 1)
        mw0 = np.concatenate([ones[1:], avg @ ones, run @ avg @ ones])[:, None]
        trap = np.full(k + 1, dt)
        trap[[0, -1]] = h
        mean = np.r_[0.0, np.full(k, 1.0 / k)]
        wts = np.vstack([tw[k], trap @ tw, mean])
        got = (mw, mw0, wts, wts.sum(axis=1)[:, None])
        self._weights_cache[key] = got
        return got

    def add_forecast_noise(self, cov_b: np.ndarray, t_s: float) -> None:
        """Covariance of the compensation's forecast error over one block.

        ``cov_b`` (6, 6) is the covariance of the error the forecast left in the
        block's solved ``[wdot, f]`` (FRD; rad/s^2 and m/s^2), a constant over
        the block's ``t_s`` seconds: it adds ``cov t^2`` to the rate (body) and
        ``C cov C^T t^2`` to the velocity (NED), with their cross term, as
        :meth:`add_hold_noise` does for a held run; the next transition carries
        it into attitude and position.
        """
        ct = dcm_from_quat(self.q) * t_s
        t2 = t_s * t_s
        ww = cov_b[0:3, 0:3] * t2
        wf = cov_b[0:3, 3:6] @ ct.T * t_s
        ff = ct @ cov_b[3:6, 3:6] @ ct.T
        p = self.P
        p[RATE, RATE] += 0.5 * (ww + ww.T)  # exactly symmetric
        p[RATE, VEL] += wf
        p[VEL, RATE] += wf.T
        p[VEL, VEL] += 0.5 * (ff + ff.T)
        self.P = p

    def remove_feature_residual(self, r_b: np.ndarray, t_s: float) -> None:
        """Take a constant error in the last block's solved ``[wdot, f]`` out of the state.

        ``r_b`` (6,) is the error (FRD; rad/s^2 and m/s^2) the block's ``t_s``
        seconds were propagated with. It put ``r t`` into the rate,
        ``r t^2 / 2`` (body) into the attitude, ``C r t`` into the velocity and
        ``C r t^2 / 2`` into the position (``C`` the block-end attitude), for a
        residual the previous block's last sample carried too (the trapezoid's first
        interval starts there); this removes them from the nominal state. Left: the
        block's turn, the propagation's second-order attitude-covariance factor on
        ``C f`` and what an attitude residual does through gravity. The covariance is
        left as it is.
        """
        r = np.asarray(r_b, dtype=float)
        t2 = 0.5 * t_s * t_s
        c = dcm_from_quat(self.q)
        self.w = self.w - t_s * r[0:3]
        self.q = quat_rotate_by_rotvec(self.q, -t2 * r[0:3], left=False)
        dv = c @ r[3:6]
        self.vel = self.vel - t_s * dv
        self.pos = self.pos - t2 * dv

    def add_hold_noise(
        self, t_before_s: float, t_after_s: float, wdot_sigma_rps2: float, f_sigma_mps2: float
    ) -> None:
        """Covariance of the forecast that stood in for held (missing) samples.

        Over a run of held samples the filter propagates on the compensation's
        forecast, whose error is modelled as a random constant (1-sigma
        ``wdot_sigma_rps2``, ``f_sigma_mps2``) over the run: the rate error grows
        as ``sigma T`` and the velocity error as ``sigma_f T``. The run grew from
        ``t_before_s`` to ``t_after_s`` held seconds in this block; the increment
        of those variances is added (the transition carries them into attitude and
        position at the next block).
        """
        d = t_after_s * t_after_s - t_before_s * t_before_s
        if d <= 0.0:
            return
        p = self.P
        p[RATE, RATE] += np.eye(3) * (wdot_sigma_rps2 * wdot_sigma_rps2 * d)
        p[VEL, VEL] += np.eye(3) * (f_sigma_mps2 * f_sigma_mps2 * d)
        self.P = p

    def _feature_offset(self, sg: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """What the nominal removes from ``wdot`` and ``f``: biases plus ``S G dr_hat``."""
        bw, bf = self.bias[0:3], self.bias[3:6]
        if self.layout.n_dr:
            if sg is None:
                raise ValueError("a filter with position states needs the block's sg")
            off = sg[0:6] @ self.dr
            bw, bf = bw + off[0:3], bf + off[3:6]
        return bw, bf

    def geometry_jacobian(self, wdot_b_rps2: np.ndarray, omega_b_rps: np.ndarray) -> np.ndarray:
        """Sensitivity (k, 3N) of the compensated features to the sensor positions.

        A sensor at ``r_i + dr_i`` reads ``theta_i . (wdot x dr_i + w x (w x dr_i))``
        more than at ``r_i``: row ``i`` of ``G`` is ``theta_i^T M`` with
        ``M = [wdot]x + [w]x^2``, and the solved features see ``S G``. With a forecast
        compensation (``noise.bias_effect`` ``T``) the forecast's history holds them
        (it takes out the bias estimates, not ``S G dr_hat``), so the loop returns them
        as it returns a bias and the compensated features see ``T S G``: this is what
        the nominal takes out (``T S G dr_hat``) and what the Jacobians carry. The raw
        ``S G`` left tactical's 27 position states' NEES at 37.6 by the end (24 runs,
        against 30.0 for their prior; 30.6 with ``T``).

        Parameters
        ----------
        wdot_b_rps2, omega_b_rps : arrays (3,)
            The block's angular acceleration and rate, FRD.
        """
        ax, ay, az = np.asarray(wdot_b_rps2, dtype=float).tolist()
        x, y, z = np.asarray(omega_b_rps, dtype=float).tolist()
        n2 = x * x + y * y + z * z
        # [wdot]x + [w]x^2 = [wdot]x + w w^T - |w|^2 I
        m = np.array(
            [
                [x * x - n2, x * y - az, x * z + ay],
                [y * x + az, y * y - n2, y * z - ax],
                [z * x - ay, z * y + ax, z * z - n2],
            ]
        )
        tm = self.sensor_axes_b @ m  # (N, 3)
        # entry (r, 3 i + c) is S[r, i] tm[i, c]: S with each column repeated 3 times
        return self._solve_rep * tm.ravel()

    def set_last_sample(self, wdot: np.ndarray, f: np.ndarray) -> None:
        """The compensated sample at the filter's current time (FRD; rad/s^2, m/s^2)."""
        self._last_wdot = np.array(wdot, dtype=float)
        self._last_f = np.array(f, dtype=float)

    def _predict_covariance(
        self, k: int, dt: float, c: np.ndarray, f_n: np.ndarray, sg: np.ndarray | None
    ) -> None:
        phi, q = self.propagation_matrices(k, dt, c, f_n, sg)
        self.x, self.P = kf_predict(self.x, self.P, phi, q)
        self._symmetrise()

    def propagation_matrices(
        self,
        k: int,
        dt: float,
        c: np.ndarray,
        f_n: np.ndarray,
        sg: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Transition F and process noise Q over a block of ``k`` samples.

        Parameters
        ----------
        k : int
            Samples in the block; ``dt`` their interval, s.
        c : array (3, 3)
            ``C_nb`` at the block start.
        f_n : array (3,)
            Mean specific force over the block, NED, m/s^2.
        sg : array (k, 3N), optional
            Feature sensitivity to the sensor positions (with ``DR`` states).
        """
        t = k * dt
        fc = self._fc_base.copy()
        fc[VEL, ATT] = -skew(f_n)
        fc[VEL, self.layout.bias] = -(c @ self._bias_effect_f)
        fc[ATT, RATE] = c
        if self.layout.n_dr:
            dr = self.layout.dr
            fc[RATE, dr] = -sg[0:3]
            fc[VEL, dr] = -c @ sg[3:6]
        # F t = [[A, B], [0, 0]] (navigation rows first), so (F t)^m = A^(m-1) [A, B]:
        # the series I + F t + (F t)^2 / 2 + (F t)^3 / 6 needs only the 12 rows
        # in Horner form, (I + A (I + A / 3) / 2) [A, B]
        ft = fc * t
        a = ft[:, :N_NAV]
        b = a * (1.0 / 3.0)
        b += self._eye12
        b = a @ b
        b *= 0.5
        b += self._eye12
        phi = self._eye.copy()
        phi[:N_NAV] += b @ ft
        # noise of the k samples, summed exactly for constant C: body-frame blocks rotated
        t12 = self._t12
        t12[0:3, 0:3] = c
        t12[3:6, 3:6] = c
        t12[6:9, 6:9] = c
        q12 = t12 @ self._q12_body(k, dt) @ t12.T
        q = self._q_walks(t).copy()
        q[:12, :12] = q12
        return phi, q

    def _q_walks(self, t: float) -> np.ndarray:
        """Process noise (n, n) of the random walks over ``t`` s: the biases' and the
        angle-of-attack offset's (the K error, if carried, is constant); cached per t."""
        q = self._q_walk_cache.get(t)
        if q is None:
            n = self.layout.n
            q = np.zeros((n, n))
            bs = self.layout.bias
            q[bs, bs] = self.noise.bias_rw_cov * t
            if self.layout.n_aoa:
                ia = self.layout.aoa.start
                q[ia, ia] = self.aoa_rw_rad_rts**2 * t
            self._q_walk_cache[t] = q
        return q

    def _q12_body(self, k: int, dt: float) -> np.ndarray:
        """Navigation-block noise (12, 12) of ``k`` samples with ``C = I`` (cached per k).

        A feature-noise sample ``n = [n_w, n_f]`` at step ``j`` of ``k`` enters
        the rate as ``dt n_w``, the attitude as ``(k - j) dt^2 n_w``, the
        velocity as ``dt n_f`` and the position as ``(k - j) dt^2 n_f``; the
        sums over ``j`` of 1, ``(k - j)`` and ``(k - j)^2`` give the weights. With
        :attr:`rate_reset_each_block` the angular acceleration's noise is one block's
        own (``FilterNoise.block_wdot_cov``).
        """
        block = self.rate_reset_each_block
        key = (k, dt, block)
        qb = self._q12_cache.get(key)
        if qb is None:
            s0 = k * dt**2
            s1 = k * (k - 1) / 2.0 * dt**3
            s2 = (k - 1) * k * (2 * k - 1) / 6.0 * dt**4
            sff, sfw = self._sff, self._sfw
            sww = self._sww_block if block else self._sww
            qb = np.block(
                [
                    [s2 * sff, s1 * sff, s2 * sfw, s1 * sfw],
                    [s1 * sff, s0 * sff, s1 * sfw, s0 * sfw],
                    [s2 * sfw.T, s1 * sfw.T, s2 * sww, s1 * sww],
                    [s1 * sfw.T, s0 * sfw.T, s1 * sww, s0 * sww],
                ]
            )
            self._q12_cache[key] = qb
        return qb

    # ------------------------------------------------------------- measurements
    def rate_noise_cross(
        self, k: int, dt: float, c: np.ndarray, held: np.ndarray | None = None
    ) -> np.ndarray | None:
        """``E[dx v^T]`` (n, nq): a block's propagation noise with its rate measurement's.

        The block's ``k`` samples (interval ``dt``, ``C_nb`` ``c`` at its start) drive
        the error state as :meth:`_q12_body` says (sample ``j`` enters the rate as
        ``-dt n_w``, the attitude as ``-(k - j) dt^2 C n_w``, the velocity and position
        likewise with ``n_f``; minus: errors are true - estimate), and their mean
        quadratic terms, noise ``v = mean n_q``, are the rate measurement. With
        ``X = noise.quad_cross_cov`` the cross-covariance is ``-dt X_w`` for the rate,
        ``-dt C X_f`` for the velocity, ``-dt^2 lag C X_w`` and ``-dt^2 lag C X_f`` for
        the attitude and position (``lag`` the mean of ``k - j`` over the samples
        measured; ``held`` (k,) marks held ones, which carry no sample noise). None
        without the cross-covariance or with no sample measured.
        """
        cq = self.noise.quad_cross_cov
        if cq is None or self.layout.nq == 0:
            return None
        if held is None:
            lag = 0.5 * (k - 1)
        else:
            j = np.arange(1, k + 1)[~np.asarray(held, dtype=bool)]
            if j.size == 0:
                return None
            lag = float(np.mean(k - j))
        cw, cf = c @ cq[0:3], c @ cq[3:6]
        a = dt * dt * lag
        m = np.zeros((self.layout.n, self.layout.nq))
        m[POS] = -a * cf
        m[VEL] = -dt * cf
        m[ATT] = -a * cw
        m[RATE] = -dt * cq[0:3]
        return m

    def update_rate(
        self,
        quad_mean: np.ndarray,
        w_block: np.ndarray,
        k: int,
        sg: np.ndarray | None = None,
        held: np.ndarray | None = None,
    ) -> float | None:
        """Update with a block's mean solved rate-quadratic terms (nq,); returns the NIS.

        ``sg`` is the block's :meth:`geometry_jacobian` (with ``DR`` states). Right
        after :meth:`propagate` over the same block, the measurement's noise is
        correlated with that block's propagation noise (:meth:`rate_noise_cross`;
        ``held`` (K,) marks its held samples) and the update carries it.
        """
        nq = self.layout.nq
        block, self._block = self._block, None
        if nq == 0 or not self.rate_measurement:
            return None
        prr = self.P[RATE, RATE]
        pred, h = self.rate_model(w_block, sg, np.diagonal(prr))
        i, j = self.quad_pairs[:, 0], self.quad_pairs[:, 1]
        pij = prr[i, j]
        pred = pred + pij + self.bias[6:]
        # second order: the spread of d_i d_j about its mean P_ij
        r = self._sqq * (1.0 / k)
        r.flat[:: nq + 1] += prr[i, i] * prr[j, j] + pij * pij
        if self.layout.n_dr:
            pred = pred + sg[6:] @ self.dr
        y = quad_mean - pred
        self.last_rate_innovation = y
        m = None if block is None else self.rate_noise_cross(*block, held)
        s = h @ self.P @ h.T + r
        if m is not None:
            hm = h @ m
            s += hm + hm.T
        nis = quadratic_form(y, s)
        if nis > self.gate_q:
            self.counters.rate_rejected += 1
            return nis
        self.x, self.P = self._update(y, r, h, m)
        self._inject()
        self.counters.rate_updates += 1
        return nis

    def rate_at_rest_model(self) -> np.ndarray:
        """The zero-rate update's Jacobian (3, n): it reads the body rate states."""
        h = np.zeros((3, self.layout.n))
        h[:, RATE] = np.eye(3)
        return h

    def update_zero_rate(self, sigma_rps: float) -> tuple[float, bool]:
        """Zero-rate update at detected rest: the body rate (FRD, rad/s) is measured as zero.

        A vehicle standing still does not turn in the filter's NED frame (which leaves the
        Earth's rotation out), so ``omega_b = 0`` with 1-sigma ``sigma_rps`` per axis:
        its rocking on its mounts, or a numerical floor where the rest is exact. It is
        what holds the yaw rate at rest, where a gyro-free array has nothing else: the
        rate products vanish with the rates, and without a horizontal acceleration GPS
        does not see the heading. It also makes the angular-acceleration biases
        observable (the rate stays zero while their error would integrate into it).
        Gated on the 3-dof chi-square threshold (a rejection says the vehicle turns:
        :class:`filters.rest.RestDetector` ends the rest).

        Returns ``(nis, accepted)``.
        """
        if not (np.isfinite(sigma_rps) and sigma_rps > 0.0):
            raise ValueError(f"sigma_rps must be finite and > 0, got {sigma_rps}")
        nis, ok = self._gated_update(
            -self.w, np.eye(3) * (sigma_rps * sigma_rps), self.rate_at_rest_model()
        )
        self.counters.zero_rate_used += int(ok)
        self.counters.zero_rate_rejected += int(not ok)
        return nis, ok

    def update_static_biases(
        self,
        mean_features: np.ndarray,
        n_samples: int,
        effect: np.ndarray | None = None,
        sample_cov: np.ndarray | None = None,
        walk_s: float = 0.0,
    ) -> None:
        """Static alignment: at rest ``wdot = 0`` and ``w = 0``, so the mean solved
        angular acceleration and rate products over ``n_samples`` samples measure
        their biases directly (noise ``feature_cov / n``). Through the channel-bias
        correlation this also informs the force bias. Without it a gyro-free
        array leaves the static alignment with its yaw-acceleration bias at the
        turn-on prior, and a single-axis yaw rate is invisible to the products.

        ``effect`` (k, k), optional, is what the bias states leave in
        ``mean_features`` (the identity by default; the pipeline's static mean has the
        mounting term at rest taken out with the biased force, which leaves
        ``M = I - E_f (I + E_ff)^-1`` of the force bias in the other features).

        ``sample_cov`` (k, k), optional, is the per-sample covariance of the raw solved
        features the mean was taken of (default: ``noise.feature_cov``). The static
        mean has no forecast loop, so its noise is the raw solve's, through ``effect``
        as the biases are: ``M cov M^T / n``. ``noise.feature_cov`` is the
        propagation's, mapped through the loop (``T``), about 13 % smaller in variance
        on the angular acceleration with ``uav-survey``'s 6 mm outward offset.

        ``walk_s`` (s, >= 0, default 0) weights the biases' random walk: the states
        are the biases at the mean's last sample, which differ from their mean over
        the span by a walk of covariance ``noise.bias_rw_cov * walk_s``, read through
        ``effect`` as the noise is (:func:`static_mean_walk_s`: about a third of the
        span; 13 % of the white noise's variance over ``uav-survey``'s 5 s).
        """
        if not (np.isfinite(walk_s) and walk_s >= 0.0):
            raise ValueError(f"walk_s must be finite and >= 0, got {walk_s}")
        nq = self.layout.nq
        k = 6 + nq
        idx = np.r_[0:3, 6 : 6 + nq]
        m = np.eye(k) if effect is None else np.asarray(effect, dtype=float)
        if m.shape != (k, k):
            raise ValueError(f"effect must be ({k}, {k}), got {m.shape}")
        h = np.zeros((idx.size, self.layout.n))
        h[:, self.layout.bias] = m[idx]
        if sample_cov is None:
            r = self.noise.feature_cov[np.ix_(idx, idx)] / max(int(n_samples), 1)
        else:
            mi = m[idx]
            r = mi @ np.asarray(sample_cov, dtype=float) @ mi.T / max(int(n_samples), 1)
        if walk_s > 0.0:
            r = r + m[idx] @ self.noise.bias_rw_cov @ m[idx].T * walk_s
        y = mean_features[idx] - m[idx] @ self.bias
        self.x, self.P = self._update(y, r, h)
        self._inject()

    def _update(
        self, y: np.ndarray, r: np.ndarray, h: np.ndarray, m: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The Kalman update of every measurement (error state ``x``, zero before it).

        filterpy's update (:func:`filters.updates.update_correlated`, with the noise
        correlated with the prior as ``m`` where there is such a correlation).
        """
        return update_correlated(self.x, self.P, y, r, h, m)

    def rate_model(
        self,
        w_block: np.ndarray,
        sg: np.ndarray | None = None,
        rate_var: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Block-mean quadratic terms (nq,) of the rates (K, 3) and their Jacobian (nq, n).

        The rate error is the same at every sample of a block, so the Jacobian
        is the block mean of ``d(w_i w_j)/dw``; the bias block is the identity,
        the ``DR`` block the quadratic rows of ``sg``.

        ``rate_var`` (3,), the variances of the rate estimate, shrinks each
        rate in the Jacobian to ``sign(w) sqrt(max(0, w^2 - var))``, the
        unbiased estimate of its size. A product ``w_i w_j`` tells about
        ``w_j`` only as much as the *true* ``w_i`` is large; near zero rate an
        estimate ``w_i`` made of its own error would claim information that
        the measurement does not hold (a straight flight's yaw rate would
        look measured and the heading would turn overconfident).

        With ``quad_feedback`` the rate columns also carry the forecast
        compensation's return of the rate error, ``E_q J6(w)``.
        """
        i, j = self.quad_pairs[:, 0], self.quad_pairs[:, 1]
        inv_k = 1.0 / w_block.shape[0]
        pred = (w_block.T @ w_block)[i, j] * inv_k
        w_mean = w_block.sum(axis=0) * inv_k
        if rate_var is not None:
            w_mean = np.array(
                [
                    math.copysign(math.sqrt(max(wm * wm - v, 0.0)), wm) if wm else 0.0
                    for wm, v in zip(w_mean.tolist(), np.asarray(rate_var).tolist(), strict=True)
                ]
            )
        h = self._h_rate_base.copy()
        h[:, RATE] = self._quad_d @ w_mean
        if self.layout.n_dr:
            h[:, self.layout.dr] = sg[6:]
        return pred, h

    def gps_model(
        self, q_nb: np.ndarray, omega_b_rps: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Antenna offset (NED) and velocity (NED, from rotation) and their Jacobians.

        Returns ``C r``, ``C (w x r)``, ``H_pos`` (3, n), ``H_vel`` (3, n).
        """
        c = dcm_from_quat(q_nb)
        r = self.antenna_b_m
        cr = c @ r
        wx, wy, wz = np.asarray(omega_b_rps, dtype=float).tolist()
        rx, ry, rz = r.tolist()
        cwr = c @ np.array([wy * rz - wz * ry, wz * rx - wx * rz, wx * ry - wy * rx])
        n = self.layout.n
        hp = np.zeros((3, n))
        hp[:, POS] = self._eye3
        hp[:, ATT] = -skew(cr)
        hv = np.zeros((3, n))
        hv[:, VEL] = self._eye3
        hv[:, ATT] = -skew(cwr)
        hv[:, RATE] = -c @ skew(r)
        return cr, cwr, hp, hv

    def update_gps(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
        dt_fix_s: float = 0.0,
        reset: bool = False,
    ) -> GpsUpdateResult:
        """Gate and apply one GPS fix (antenna position and velocity, NED).

        ``dt_fix_s`` is the fix time minus the filter time (|dt| below one
        array sample); the prediction is moved by ``v dt``. With ``reset``
        (the first fix after an outage) a fix that passes the position gate
        is not fused: :meth:`reset_to_fix` puts position and velocity on it; so
        does the :data:`GAP_RESET_AFTER_REJECTS`-th fix in a row that fails it.
        """
        t_fix = self.t_s + dt_fix_s
        if np.isfinite(self._t_prev_fix) and t_fix > self._t_prev_fix:
            self.fix_interval_s = t_fix - self._t_prev_fix
        self._t_prev_fix = t_fix
        cr, _, hp, _ = self.gps_model(self.q, self.w)
        rp = np.diag(np.broadcast_to(np.asarray(pos_sigma_m, dtype=float), 3) ** 2)
        yp = pos_ned_m - (self.pos + cr + self.vel * dt_fix_s)
        sp = hp @ self.P @ hp.T + rp
        nis_h = quadratic_form(yp[0:2], sp[0:2, 0:2])
        nis_vt = float(yp[2] ** 2 / sp[2, 2]) if sp[2, 2] > 0 else float("inf")
        if reset:
            nis_p = quadratic_form(yp, sp)
            passed = np.isfinite(nis_p) and nis_p <= self.gate3
            if passed or self._consec_rejects + 1 >= GAP_RESET_AFTER_REJECTS:
                _, cwr, _, hv = self.gps_model(self.q, self.w)
                yv = vel_ned_mps - (self.vel + cwr)
                nis_v = quadratic_form(yv, hv @ self.P @ hv.T + np.eye(3) * vel_sigma_mps**2)
                self._put_on_fix(
                    pos_ned_m - self.vel * dt_fix_s, vel_ned_mps, pos_sigma_m, vel_sigma_mps
                )
                self.counters.gps_gap_resets += 1
                self.counters.gps_used += 1
                return GpsUpdateResult(nis_p, nis_v, True, True, nis_h, nis_vt)
            self.counters.gps_rejected_pos += 1
            self.counters.gps_rejected_vel += 1
            self._consec_rejects += 1
            return GpsUpdateResult(nis_p, float("nan"), False, False, nis_h, nis_vt)
        nis_p, ok_p = self._gated_update(yp, rp, hp)
        _, cwr, _, hv = self.gps_model(self.q, self.w)  # after the position update
        rv = self._eye3 * float(vel_sigma_mps) ** 2
        yv = vel_ned_mps - (self.vel + cwr)
        if self.in_body_frame():
            mc, cc = self.velocity_curvature()
            yv = yv - mc
            rv = rv + cc
        nis_v, ok_v = self._gated_update(yv, rv, hv)
        self.counters.gps_used += int(ok_p or ok_v)
        self.counters.gps_rejected_pos += int(not ok_p)
        self.counters.gps_rejected_vel += int(not ok_v)
        self._consec_rejects = 0 if ok_p else self._consec_rejects + 1
        self._consec_vel_rejects = 0 if ok_v else self._consec_vel_rejects + 1
        if ok_p:
            self.t_last_position_fix = self.t_s
        return GpsUpdateResult(nis_p, nis_v, ok_p, ok_v, nis_h, nis_vt)

    @property
    def aoa(self) -> float:
        """The nominal angle of attack, rad: ``w (alpha_b + K u)`` (``alpha_b`` without a law)."""
        return self._lift_w * self._unblended_aoa()

    def _unblended_aoa(self) -> float:
        """The lift law before the lift-off blend, ``alpha_b + K u``, rad."""
        return self.aoa_b + self.aoa_k * self._lift_u

    def _aoa_gradient(self) -> np.ndarray:
        """d alpha / d(AOA states): ``w [1, u]`` (or ``[w]`` with the offset alone)."""
        return self._lift_w * np.array([1.0, self._lift_u_jac])[: self.layout.n_aoa]

    def aoa_jacobian(self, vel_ned_mps: np.ndarray) -> np.ndarray:
        """``d alpha / d(error state)`` (n,) at the velocity ``vel_ned_mps`` (NED, m/s).

        ``w [1, u]`` for the law's offset and ``K``; through ``u = n_w / V^2``
        (:meth:`set_load`), ``-2 w K u v^T / V^2`` for the velocity and
        ``-w K [sin a, 0, -cos a] T_f / V^2`` for the biases (``T_f`` the force rows of
        ``noise.bias_effect``) and likewise, with the load's ``S G`` force rows for
        ``T_f`` (:meth:`set_load`'s ``sg_f``), for the sensor positions; through the
        lift-off blend ``w(V)``, ``w'(V) (alpha_b + K u) v^T / V``. Zero without the
        ``AOA`` state. The ``u`` here is the load :data:`LIFT_JACOBIAN_LAG_BLOCKS`
        blocks back, whose noise is independent of the predicted angle's (equal to the
        current one under a steady load).
        """
        j = np.zeros(self.layout.n)
        if not self.layout.n_aoa:
            return j
        ia = self.layout.aoa.start
        j[ia] = self._lift_w
        if self.layout.n_aoa == 2:
            j[ia + 1] = self._lift_w * self._lift_u_jac
        speed2 = float(vel_ned_mps @ vel_ned_mps)
        if speed2 <= 1.0:
            return j
        if self._lift_dw:
            lift = self._unblended_aoa()
            j[VEL] += self._lift_dw * lift * vel_ned_mps / np.sqrt(speed2)
        if self.aoa_k > 0.0:
            wk = self._lift_w * self.aoa_k / speed2
            j[VEL] += -2.0 * wk * self._lift_u_jac * vel_ned_mps
            j[self.layout.bias] += -wk * (self._lift_axis @ self._bias_effect_f)
            if self.layout.n_dr and self._lift_sg_f is not None:
                j[self.layout.dr] += -wk * (self._lift_axis @ self._lift_sg_f)
        return j

    @property
    def aoa_sigma(self) -> float:
        """1-sigma of :attr:`aoa`, rad: :meth:`aoa_jacobian`'s linear part, the lift-off
        blend's beyond it (:meth:`blend_remainder_var`) and the load's noise
        (:meth:`set_load`); 0 without the state."""
        j = self.aoa_jacobian(self.vel)
        lift = self._unblended_aoa()
        var = j @ self.P @ j + lift * lift * self.blend_remainder_var() + self._load_angle_var()
        return float(np.sqrt(var))

    def _load_angle_var(self) -> float:
        """Variance of the angle of attack from the load's noise, ``(w K)^2 Var(u)``, rad^2."""
        wk = self._lift_w * self.aoa_k
        return wk * wk * self._lift_u_var

    def load_noise_var(self, q_nb: np.ndarray, vel_ned_mps: np.ndarray, aoa_rad: float) -> float:
        """The angle-of-attack model's variance from the load's noise at a given state,
        ``(dv/dalpha)^2 (w K)^2 Var(u)`` (m^2/s^2), ``dv/dalpha = -(C t_b) . v``: what its R
        adds (:meth:`set_load`); 0 without a load covariance."""
        _, t_b = constraint_axes(VERTICAL, aoa_rad)
        dv_da = -float((dcm_from_quat(q_nb) @ t_b) @ vel_ned_mps)
        return dv_da * dv_da * self._load_angle_var()

    def _speed(self) -> float:
        """``|v|`` of the nominal velocity, m/s (on floats: it runs every block)."""
        vx, vy, vz = self.vel.tolist()
        return math.sqrt(vx * vx + vy * vy + vz * vz)

    def blend_remainder_var(self) -> float:
        """Variance of the lift-off blend ``w(V)`` beyond its linear term (dimensionless).

        The blend is the minimum-jerk step over ``[0.8, 1] liftoff_speed_mps``, whose
        first and second derivatives vanish where it starts and ends: there a speed
        error ``dV`` moves ``w`` by ``10 (dV / width)^3`` and more, which the
        Jacobian's ``w'(V) dV`` cannot carry (the filter's angle-of-attack sigma
        went to 1e-8 deg at the blend's start while the truth, blended on its own
        speed, was 1e-4 deg off). This is ``Var[w(V + dV) - w(V) - w'(V) dV]`` for
        ``dV ~ N(0, u^T P_vel u)`` (``u`` the velocity's direction), on a 41-point
        grid over +-6 sigma; 0 where the blend is flat over +-6 sigma of speed,
        without the ``AOA`` state, or without a blend.
        """
        v_lof = self.liftoff_speed_mps
        if not self.layout.n_aoa or v_lof <= 0.0:
            return 0.0
        speed = self._speed()
        if speed <= 1.0:
            return 0.0
        width = 0.2 * v_lof
        x0 = (speed - 0.8 * v_lof) / width
        # the per-block path: the trace bounds the speed's variance from above
        p, iv = self.P, VEL.start
        s_max = 6.0 * math.sqrt(max(float(p[iv, iv] + p[iv + 1, iv + 1] + p[iv + 2, iv + 2]), 0.0))
        s_max /= width
        if x0 + s_max <= 0.0 or x0 - s_max >= 1.0:
            return 0.0
        u = self.vel / speed
        sx = float(np.sqrt(max(u @ self.P[VEL, VEL] @ u, 0.0))) / width
        if x0 + 6.0 * sx <= 0.0 or x0 - 6.0 * sx >= 1.0:
            return 0.0
        return blend_spread_var(x0, sx)

    def set_load(
        self,
        f_b_mps2: np.ndarray,
        load_cov: np.ndarray | None = None,
        sg_f: np.ndarray | None = None,
    ) -> None:
        """Feed the lift law the block's specific force (FRD, m/s^2, biases removed).

        ``u = n_w / V^2`` with the wind-frame normal load ``n_w = sin(a) f_x - cos(a) f_z``
        at the current angle of attack and ``V = |v|`` (calm air), and the lift-off blend
        ``w(V)``. The angle of attack so depends on the velocity and force-bias states
        too; :meth:`body_velocity_model` carries both in its Jacobian, which takes ``u``
        from :data:`LIFT_JACOBIAN_LAG_BLOCKS` calls back (errors in variables).

        ``load_cov`` (3, 3), (m/s^2)^2, FRD, is the covariance of the noise in
        ``f_b_mps2`` (the pipeline's: the block means' ``feature_cov / k``, weighted as its
        extrapolation weights them). The angle carries it, ``Var(u) = a^T load_cov a / V^4``
        along the lift axis ``a``: the angle-of-attack model's R and :attr:`aoa_sigma`
        add it. None: a noise-free load.

        ``sg_f`` (3, 3N), with ``DR`` states: the force rows of the load's sensitivity
        to the sensor positions (:meth:`geometry_jacobian`'s, weighted as the load's
        blocks are), whose ``S G dr_hat`` the caller has taken out of ``f_b_mps2`` as the
        propagation does; the angle of attack's Jacobian carries their errors as it
        carries the biases'. None: the load does not depend on them.
        """
        self._lift_sg_f = None if sg_f is None else np.asarray(sg_f, dtype=float)
        speed = self._speed()
        a = self.aoa  # the angle n_w is taken at: the last block's
        v_lof = self.liftoff_speed_mps
        if v_lof > 0.0:
            s, ds, _ = min_jerk_step((speed - 0.8 * v_lof) / (0.2 * v_lof))
            self._lift_w, self._lift_dw = float(s), float(ds) / (0.2 * v_lof)
        if self.aoa_k > 0.0 and speed > 1.0:
            self._lift_axis = np.array([math.sin(a), 0.0, -math.cos(a)])  # n_w = this . f
            n_w = self._lift_axis @ f_b_mps2
            # products, not powers: a diverged speed gives 0 here, not an OverflowError
            speed2 = speed * speed
            self._lift_u = float(n_w) / speed2
            ax = self._lift_axis
            self._lift_u_var = (
                0.0 if load_cov is None else float(ax @ load_cov @ ax) / speed2 / speed2
            )
            recent = self._lift_u_recent
            recent.append(self._lift_u)
            if len(recent) > LIFT_JACOBIAN_LAG_BLOCKS + 1:
                del recent[0]
            self._lift_u_jac = recent[0]

    def body_velocity_model(
        self, q_nb: np.ndarray, vel_ned_mps: np.ndarray, axis: int = LATERAL, aoa_rad: float = 0.0
    ) -> tuple[float, np.ndarray]:
        """Velocity along a body constraint axis, ``n_b . C^T v`` (m/s), and its Jacobian (1, n).

        ``axis`` is :data:`LATERAL` (``n_b = e_y``: the sideslip model) or
        :data:`VERTICAL` (``n_b = [-sin alpha, 0, cos alpha]``, the wind-normal axis at
        angle of attack ``aoa_rad``: the angle-of-attack model; ``e_z`` at zero). With
        the ``AOA`` state the vertical model's Jacobian includes
        ``d/dalpha = -t_b . C^T v``, ``t_b = [cos alpha, 0, sin alpha]`` (the wind x axis),
        times :meth:`aoa_jacobian`.
        """
        c = dcm_from_quat(q_nb)
        n_b, t_b = constraint_axes(axis, aoa_rad)
        row = c @ n_b  # n_b^T C^T as a NED row
        h = np.zeros((1, self.layout.n))
        h[0, VEL] = row
        h[0, ATT] = row @ skew(vel_ned_mps)
        if axis == VERTICAL and self.layout.n_aoa:
            h[0] += -float((c @ t_b) @ vel_ned_mps) * self.aoa_jacobian(vel_ned_mps)
        return float(row @ vel_ned_mps), h

    def sideslip_model(self, q_nb: np.ndarray, vel_ned_mps: np.ndarray) -> tuple[float, np.ndarray]:
        """Body-lateral velocity ``e_y . C^T v`` (m/s) and its Jacobian (1, n)."""
        return self.body_velocity_model(q_nb, vel_ned_mps, LATERAL)

    def update_sideslip(self, sigma_rad: float, min_speed_mps: float) -> float | None:
        """Zero-sideslip pseudo-measurement (a fixed-wing's, ``vehicle.kind``).

        R is the sigma's lateral velocity squared (at the horizontal speed) plus the
        second-order remainder's variance as :func:`remainder_variance` counts it (it
        is correlated from one update to the next); the remainder's mean is added to
        the prediction.

        Returns the NIS, or None below ``min_speed_mps`` horizontal speed (no update).
        """
        speed = float(np.hypot(self.vel[0], self.vel[1]))
        if speed < min_speed_mps:
            return None
        nis, ok = self._body_velocity_update(LATERAL, speed * np.tan(sigma_rad))
        self.counters.sideslip_used += int(ok)
        self.counters.sideslip_rejected += int(not ok)
        self._consec_slip_rejects = 0 if ok else self._consec_slip_rejects + 1
        return nis

    def update_angle_of_attack(self, sigma_rad: float, min_speed_mps: float) -> float | None:
        """Angle-of-attack pseudo-measurement (a fixed-wing's).

        The velocity along the wind-normal axis ``[-sin alpha, 0, cos alpha]`` (FRD;
        ``alpha`` the ``AOA`` state, or zero without it: the body z axis) is measured
        as zero with a 1-sigma of ``|v| tan(sigma_rad)``, and the same second-order
        terms as :meth:`update_sideslip`. Returns the NIS, or None below
        ``min_speed_mps`` horizontal speed (no update).
        """
        if float(np.hypot(self.vel[0], self.vel[1])) < min_speed_mps:
            return None
        sigma_v = float(np.linalg.norm(self.vel)) * np.tan(sigma_rad)
        nis, ok = self._body_velocity_update(VERTICAL, sigma_v)
        self.counters.aoa_used += int(ok)
        self.counters.aoa_rejected += int(not ok)
        return nis

    def _body_velocity_update(self, axis: int, sigma_v_mps: float) -> tuple[float, bool]:
        v_axis, h = self.body_velocity_model(self.q, self.vel, axis, self.aoa)
        mq, sel, mean_shift = self.body_velocity_second_order_form(axis)
        rem = self._form_moments(mq, sel, mean_shift)
        load_var = blend_var = 0.0  # R's angle-of-attack terms, m^2/s^2
        dv_da = 0.0  # the model's change per radian of angle of attack: -(C t_b . v)
        if axis == VERTICAL:
            _, t_b = constraint_axes(VERTICAL, self.aoa)
            dv_da = -float((dcm_from_quat(self.q) @ t_b) @ self.vel)
            # the predicted angle carries the load's noise: w K du
            load_var = dv_da * dv_da * self._load_angle_var()
            # the blend beyond its linear term moves the angle, and the velocity with it
            lift = self._unblended_aoa()
            blend_var = dv_da * dv_da * lift * lift * self.blend_remainder_var()
        n_upd = self.current_remainder_updates()
        counted = remainder_variance(rem, n_upd, self.attitude_remainder_updates)
        if self.count_by_prior_weight and axis == LATERAL and not self.counts_as_coast():
            # outside the hand-over and coasts (whose count stands for more than the
            # remainder's persistence): the count as far as the update keeps the prior;
            # the sideslip model only, whose prior along the constraint is fresh noise
            r_c = sigma_v_mps**2 + counted  # the sideslip's R: no load or blend terms
            s_prior = float(h[0] @ self.P @ h[0])
            counted = remainder_variance(
                rem,
                prior_weighted_count(n_upd, r_c, s_prior),
                prior_weighted_count(self.attitude_remainder_updates, r_c, s_prior),
            )
        var = sigma_v_mps**2 + counted
        if axis == VERTICAL:
            var += load_var
            if blend_var > 0.0:
                var += blend_var
        r = np.array([[var]])
        log = self.body_velocity_log
        if log is not None:
            aoa = self.aoa if axis == VERTICAL else 0.0
            rec = (self.t_s, axis, self.q.copy(), self.vel.copy(), aoa, v_axis)
            rec += (h[0, ATT].copy(), h[0, VEL].copy(), dv_da, rem, float(var))
        nis, ok = self._gated_update(np.array([-(v_axis + rem.mean)]), r, h, self.gate1)
        if ok:
            self._model_last_t[axis] = self.t_s
        self._model_last_ok[axis] = ok
        if log is not None:
            log.append(BodyVelocityRecord(*rec, ok))
        return nis, ok

    def current_remainder_updates(self) -> float:
        """The count of the whole remainder a body-velocity update uses now.

        ``coast_remainder_updates`` while coasting (more than ``coast_after_s``, or
        five intervals of the GPS fixes received, whichever is longer, since the last
        accepted GPS position: a slow receiver's normal spacing is not a coast) and for
        ``coast_hold_s`` after it: the remainder built up in a coast lasts as long
        after it as in it. The same count, if not coasting, until ``handover_hold_s``
        after the first such call since :meth:`initialise`
        (``counters.handover_model_updates``). Otherwise ``remainder_updates``. Called
        once per update: a coasting call is counted (``counters.coast_model_updates``)
        and extends the hold; the first call after :meth:`initialise` starts the
        hand-over's.
        """
        if self._handover_pending:
            self._handover_pending = False
            # less a nanosecond: the update times are sums of sample intervals, and the
            # update a whole hold later ends it
            self._handover_until = self.t_s + self.handover_hold_s - 1e-9
        coasting = self._coasting()
        if coasting:
            self._coast_until = self.t_s + self.coast_hold_s
        if coasting or self.t_s < self._coast_until:
            self.counters.coast_model_updates += 1
            return self.coast_remainder_updates
        if self.t_s < self._handover_until:
            self.counters.handover_model_updates += 1
            return self.coast_remainder_updates
        return self.remainder_updates

    def _coasting(self) -> bool:
        """More than ``coast_after_s`` (or five fix intervals) since the last accepted position."""
        after = self.coast_after_s
        if not math.isnan(self.fix_interval_s):
            after = max(after, COAST_AFTER_FIXES * self.fix_interval_s)
        return self.t_s - self.t_last_position_fix > after

    def counts_as_coast(self) -> bool:
        """Whether a body-velocity update now would use ``coast_remainder_updates``.

        True while coasting, within ``coast_hold_s`` of the last coasting update, and
        from :meth:`initialise` until ``handover_hold_s`` after the models' first
        update since: what
        :meth:`current_remainder_updates` decides, without its counting (a query).
        The pipeline runs the vehicle model at 5 Hz then, and at its own rate
        otherwise (5 Hz, ``filters.pipeline.SIDESLIP_RATE_HZ``).
        """
        return (
            self._coasting()
            or self._handover_pending
            or self.t_s < max(self._coast_until, self._handover_until)
        )

    def sideslip_second_order(self) -> Remainder:
        """:meth:`body_velocity_second_order` of the lateral axis (the sideslip model)."""
        return self.body_velocity_second_order(LATERAL)

    def body_velocity_second_order(self, axis: int = LATERAL) -> Remainder:
        """Mean and variance of a body-velocity model's second-order term (m/s, m^2/s^2).

        With ``a = C n_b`` (the constraint axis in NED; :meth:`body_velocity_model`),
        the velocity of the true state along it is ``a^T exp(-[dtheta]x) (v + dv)``;
        beyond the linear terms it holds
        ``q = dtheta^T [a]x dv + dtheta^T A dtheta / 2``
        with ``A = (a v^T + v a^T) / 2 - (a . v) I``. With the ``AOA`` state the
        vertical axis also turns, ``n_b(alpha + da) = n_b - da t_b - da^2 n_b / 2``
        (``b = C t_b``), which adds ``-da b^T ([v]x dtheta + dv) - da^2 (a . v) / 2``.
        The angle itself, ``w(V) (alpha_b + K n_w / V^2)`` with a lift law, is bilinear in
        the speed's error ``dV = v^T dv / V`` and the law's states beyond its Jacobian:
        ``da`` holds ``dV (w' d alpha_b + (w' u - 2 w u / V) dK)`` too, which moves the
        model by ``-b . v`` per radian. In the lift-off blend (``w'`` up to 0.5 per m/s,
        the law 1 deg uncertain) this term is far above the model's sigma.
        Written ``q = x^T M x / 2`` over ``x = (dtheta, dv[, da, AOA states])``, a
        Gaussian error gives ``E q = tr(M P) / 2`` and ``Var q = tr(M P M P) / 2``, the second-order
        filter's terms (as for the rate products). They are negligible while GPS
        holds velocity and attitude; at the end of a long coast (metres per second
        of velocity error, tenths of a degree of tilt) they exceed a tight sideslip
        sigma, and without them the filter trusted the linearised constraint too
        far (joint velocity-attitude NEES far above its 6 dof on ``uav-survey``).
        ``var_att`` is ``Var`` of the ``dtheta^T A dtheta / 2`` part alone.
        """
        return self._form_moments(*self.body_velocity_second_order_form(axis))

    def _form_moments(self, mq: np.ndarray, sel: np.ndarray, mean_shift: float) -> Remainder:
        """:func:`remainder_moments` of a form from :meth:`body_velocity_second_order_form`."""
        rem = remainder_moments(mq, self.P[np.ix_(sel, sel)])
        return rem._replace(mean=rem.mean - mean_shift)

    def body_velocity_second_order_form(
        self, axis: int = LATERAL
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """The remainder of :meth:`body_velocity_second_order` as a quadratic form.

        Returns
        -------
        mq : array (d, d)
            ``q = x^T mq x / 2`` over the error states ``x = dx[sel]`` (m/s per unit of
            each pair); the first three of ``sel`` are the attitude error.
        sel : array (d,) of int
            Their indices in the error state.
        mean_shift : float
            What the propagation already carries of ``E q`` (the body-frame velocity
            error's terms; 0 otherwise), m/s: the update's mean is ``E q - mean_shift``.
        """
        c = dcm_from_quat(self.q)
        n_b, t_b = constraint_axes(axis, self.aoa)
        a = c @ n_b
        v = self.vel
        with_aoa = axis == VERTICAL and self.layout.n_aoa > 0
        d = 7 if with_aoa else 6
        m = np.zeros((d, d))
        mb = None
        if self.in_body_frame():
            # n_b . v_b is linear in (dtheta, xi_v): the remainder is the body velocity's
            # own second order since the model's last update, over (dtheta, xi_v, dw)
            mb = self.body_velocity_remainder_matrix(n_b, self._model_interval(axis))
        else:
            m[0:3, 0:3] = attitude_product_matrix(a, v)
            sa = skew(a)
            m[0:3, 3:6] = sa
            m[3:6, 0:3] = sa.T
        idx = _DTHETA_DV
        if with_aoa:
            b = c @ t_b
            m[6, 0:3] = m[0:3, 6] = -(b @ skew(v))
            m[6, 3:6] = m[3:6, 6] = -b
            m[6, 6] = -float(a @ v)
        if mb is not None:
            # the propagation carries the means of its terms (propagate), so only their
            # variance is the update's
            p9 = self.P[np.ix_(_DTHETA_DV_DW, _DTHETA_DV_DW)]
            mb_mean = remainder_moments(mb, p9).mean
            if not with_aoa:
                return mb, _DTHETA_DV_DW, mb_mean
        elif not with_aoa:
            return m, idx, 0.0
        # x = (dtheta, dv, da, AOA states): the angle's linear error da (through the
        # law's states and, with a law, the speed) beside the states it is made of, for
        # the angle's own second-order terms
        ia = self.layout.aoa
        na = self.layout.n_aoa
        t = np.zeros((7 + na, 6 + na))
        t[:6, :6] = np.eye(6)
        j = self.aoa_jacobian(v)
        t[6, 3:6] = j[VEL]
        t[6, 6:] = j[ia]
        t[7:, 6:] = np.eye(na)
        mx = np.zeros((7 + na, 7 + na))
        mx[:7, :7] = m
        speed = self._speed()
        if speed > 1.0:
            # alpha = w(V) (alpha_b + K n_w / V^2) mixes the speed with the law's states:
            # d2 alpha / dV d alpha_b = w', d2 alpha / dV dK = w' u - 2 w u / V, with
            # dV = v^T dv / V. In the lift-off blend the first dwarfs the model's sigma
            # (w' up to 0.5 per m/s against a law 1 deg uncertain); without it the
            # blend's slope made the speed look measured.
            u = self._lift_u_jac
            w, dw = self._lift_w, self._lift_dw
            mix = np.array([dw, dw * u - 2.0 * w * u / speed])
            dv_da = -float(b @ v)
            v_hat = v / speed
            cross = dv_da * np.outer(v_hat, mix[:na])  # (3, na): m/s per unit^2
            mx[3:6, 7:] = cross
            mx[7:, 3:6] = cross.T
            # and the speed's own curvature: V(v + dv) bends across the velocity, and the
            # law's 1 / V^2 (with w' times it) along it; the blend's w'' is
            # blend_remainder_var's
            k_u = self.aoa_k * u
            lift = self._unblended_aoa()
            slope = dw * lift - 2.0 * w * k_u / speed  # d alpha / dV, rad s/m
            along = -4.0 * dw * k_u / speed + 6.0 * w * k_u / speed**2
            vv = np.outer(v_hat, v_hat)
            mx[3:6, 3:6] += dv_da * (slope * (np.eye(3) - vv) / speed + along * vv)
        sel = np.r_[idx, np.arange(ia.start, ia.stop)]
        if mb is None:
            return t.T @ mx @ t, sel, 0.0
        # x = (dtheta, xi_v, da, AOA states, dw): the angle's terms beside the body
        # velocity's
        nx = 7 + na
        sel = np.r_[sel, np.arange(RATE.start, RATE.stop)]
        t2 = np.zeros((nx + 3, 6 + na + 3))
        t2[:nx, : 6 + na] = t
        t2[nx:, 6 + na :] = np.eye(3)
        m3 = np.zeros((nx + 3, nx + 3))
        m3[:nx, :nx] = mx
        m3[0:6, 0:6] += mb[0:6, 0:6]
        m3[nx:, 0:6] = mb[6:9, 0:6]
        m3[0:6, nx:] = mb[0:6, 6:9]
        m3[nx:, nx:] = mb[6:9, 6:9]
        return t2.T @ m3 @ t2, sel, mb_mean

    def _model_interval(self, axis: int) -> float:
        """Time since the vehicle model's last accepted update on ``axis``, s.

        :data:`BODY_REMAINDER_INTERVAL_S` before the first, and never more than
        :data:`BODY_REMAINDER_MAX_INTERVAL_S` (a long pause below the model's speed).
        """
        last = self._model_last_t.get(axis)
        if last is None:
            return BODY_REMAINDER_INTERVAL_S
        return min(max(self.t_s - last, 0.0), BODY_REMAINDER_MAX_INTERVAL_S)

    def body_velocity_remainder_matrix(self, n_b: np.ndarray, t_s: float) -> np.ndarray:
        """The body velocity's second order along ``n_b`` over ``t_s`` s (9, 9).

        With :attr:`body_velocity_error` the models' constraint ``n_b . v_b`` is linear in
        the error state at the update; what the filter's linear propagation left out
        since the last update is the body velocity's own second order,
        ``d dv_b / dt = - dw x dv_b + C^T dtheta x (dtheta x g) / 2 + (linear)``, taken
        over the interval with the errors at the update (``dv_b`` drifting back by its
        linear rate ``L = - dw x v_b - w x dv_b + C^T (g x dtheta)``, ``dtheta`` by
        ``C dw``):

        ``q = T dw^T [n]x dv_b - T^2/2 dw^T A(n, v_b) dw + T^2/2 dw^T [n]x [w]x dv_b
        - T^2/2 dw^T [n]x C^T [g]x dtheta + T/2 dtheta^T A_g dtheta
        - T^2/2 dtheta^T A_g C dw + T^3/6 dw^T C^T A_g C dw``,

        ``A(a, v) = (a v^T + v a^T)/2 - (a . v) I``
        (:func:`filters.vehicle_model.attitude_product_matrix`), ``A_g = A(C n, g)``, and
        ``dv_b = C^T (xi_v + v x dtheta)``. Returned as ``M`` with ``q = x^T M x / 2``
        over ``x = (dtheta, xi_v, dw)`` (NED rad, NED m/s, FRD rad/s).
        """
        tt = float(t_s)
        c = dcm_from_quat(self.q)
        v = self.vel
        g = self._g
        a = c @ n_b
        d_xi = c.T  # dv_b per xi_v
        d_th = c.T @ skew(v)  # dv_b per dtheta
        sn = skew(n_b)
        ag = attitude_product_matrix(a, g)
        b_wv = tt * sn + 0.5 * tt * tt * sn @ skew(self.w)  # dw^T b_wv dv_b
        m_wx = b_wv @ d_xi
        m_wt = b_wv @ d_th - 0.5 * tt * tt * sn @ c.T @ skew(g) - 0.5 * tt * tt * (ag @ c).T
        m = np.zeros((9, 9))
        m[0:3, 0:3] = tt * ag
        m[6:9, 6:9] = -tt * tt * attitude_product_matrix(n_b, c.T @ v) + (tt**3 / 3.0) * (
            c.T @ ag @ c
        )
        m[6:9, 0:3] = m_wt
        m[0:3, 6:9] = m_wt.T
        m[6:9, 3:6] = m_wx
        m[3:6, 6:9] = m_wx.T
        return m

    def in_body_frame(self) -> bool:
        """Whether the velocity error is taken in the body frame now.

        With :attr:`body_velocity_error`, while the attitude's uncertainty curves the NED
        velocity by at most :data:`BODY_FRAME_MAX_CURVATURE_MPS`
        (``|v| tr(P_att) / 2``, the size of ``dtheta x (dtheta x v) / 2``); otherwise the
        NED error's updates, remainder and injection. The two errors agree to first order,
        so P means the same either way and the filter may change from one to the other
        between steps; what differs is second order, which is what this bounds. Also the
        NED error while the last GPS velocity or either vehicle model's last update failed
        its gate: the body-frame error trusts P's attitude, and a hand-over told 1 deg while
        15 deg off otherwise fused GPS velocities through it for a second longer and
        relearned its tilt twice as badly (docs/notes/filter-notes.md).
        """
        if not self.body_velocity_error:
            return False
        if self._consec_vel_rejects > 0 or not all(self._model_last_ok.values()):
            # a GPS velocity or a vehicle model just failed its gate: P's attitude is in
            # doubt, and the body-frame error would fuse through it
            return False
        pa = self.P[ATT, ATT]
        curv = 0.5 * float(np.linalg.norm(self.vel)) * float(pa[0, 0] + pa[1, 1] + pa[2, 2])
        return curv <= BODY_FRAME_MAX_CURVATURE_MPS

    def _rate_body_velocity_cov(self, c: np.ndarray) -> np.ndarray:
        """``E[dw dv_b^T]`` (3, 3) with ``dv_b = C^T (xi_v + v x dtheta)`` (``c`` = C)."""
        return self.P[RATE, VEL] @ c - self.P[RATE, ATT] @ skew(self.vel) @ c

    def velocity_curvature(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (3,) and covariance (3, 3) of the NED velocity's second-order part, m/s.

        With :attr:`body_velocity_error` the true NED velocity is ``v + xi_v + c``,
        ``c = dtheta x xi_v - dtheta x (dtheta x v) / 2``: each component a quadratic
        form ``x^T M_i x / 2`` over ``x = (dtheta, xi_v)``, so ``E c_i = tr(M_i P) / 2``
        and ``Cov(c_i, c_j) = tr(M_i P M_j P) / 2``. Zeros with the NED error (the
        velocity error is then exactly additive).
        """
        if not self.in_body_frame():
            return np.zeros(3), np.zeros((3, 3))
        v = self.vel
        m = _CURVATURE_CROSS.copy()  # (3, 6, 6): M_i over (dtheta, xi_v)
        # the attitude block -A(e_i, v) = -(e_i v^T + v e_i^T) / 2 + v_i I
        m[:, 0:3, 0:3] = -0.5 * (_E3[:, :, None] * v[None, None, :])
        m[:, 0:3, 0:3] -= 0.5 * (v[None, :, None] * _E3[:, None, :])
        m[:, 0:3, 0:3] += v[:, None, None] * _E3[None, :, :]
        mp = m @ self.P[_DTHETA_DV_IX]
        mean = 0.5 * np.trace(mp, axis1=1, axis2=2)
        cov = 0.5 * np.einsum("iab,jba->ij", mp, mp)
        return mean, cov

    def _gated_update(
        self, y: np.ndarray, r: np.ndarray, h: np.ndarray, gate: float | None = None
    ) -> tuple[float, bool]:
        s = h @ self.P @ h.T + r
        nis = quadratic_form(y, s)
        if not np.isfinite(nis) or nis > (self.gate3 if gate is None else gate):
            return nis, False
        self.x, self.P = self._update(y, r, h)
        self._inject()
        return nis, True

    @property
    def consecutive_position_rejects(self) -> int:
        """Fixes in a row whose position was rejected (a divergence sign)."""
        return self._consec_rejects

    @property
    def consecutive_velocity_rejects(self) -> int:
        """GPS velocities in a row that failed the gate (the tilt or rate is lost)."""
        return self._consec_vel_rejects

    def reopen_attitude(self, tilt_sigma_rad: float, rate_sigma_rps: float) -> None:
        """Documented fallback: add tilt and rate variance the filter has lost track of.

        A gyro-free array's tilt comes from integrating the rate, which comes
        from integrating the angular acceleration; when that goes wrong beyond
        its covariance (a long coast), the velocity it predicts soon fails every
        GPS gate and nothing can correct it. Adding ``tilt_sigma_rad^2`` to the
        two NED tilt variances and ``rate_sigma_rps^2`` to the three rate
        variances (heading and everything else keep theirs; adding to the
        diagonal keeps P positive definite) lets the next velocity fixes
        through to relearn them. Counted as ``attitude_reopens``.
        """
        p = self.P.copy()
        tilt = np.arange(ATT.start, ATT.start + 2)  # NED north and east tilt
        p[tilt, tilt] += tilt_sigma_rad**2
        rate = np.arange(RATE.start, RATE.stop)
        p[rate, rate] += rate_sigma_rps**2
        self.P = p
        self._consec_vel_rejects = 0
        self.counters.attitude_reopens += 1
        self.check_covariance("attitude reopened")

    @property
    def consecutive_sideslip_rejects(self) -> int:
        """Sideslip updates in a row that failed the gate (a heading far off the course)."""
        return self._consec_slip_rejects

    def check_heading_against_course(self, course_rad: float, sigma_rad: float) -> bool:
        """Documented fallback: put the heading on a GPS course it contradicts.

        For a vehicle flying with no sideslip the heading is the course of its
        ground velocity. If the heading differs from ``course_rad`` by more than
        the 1-dof gate allows (``d^2 / (P_yaw + sigma^2)``, ``d`` wrapped to
        (-pi, pi]), :meth:`set_heading` puts it on the course with ``sigma_rad``
        and the reset is counted. The zero-sideslip model cannot catch this
        itself: a heading 180 deg off the course also has zero lateral velocity,
        and a heading tens of degrees off fails every sideslip gate. Returns
        True if the heading was reset.
        """
        # the course the attitude implies: the horizontal direction of the wind x
        # axis (the body x axis without the AOA state, whose heading is the yaw)
        _, t_b = constraint_axes(VERTICAL, self.aoa)
        x_n = dcm_from_quat(self.q) @ t_b
        d = float(np.angle(np.exp(1j * (np.arctan2(x_n[1], x_n[0]) - course_rad))))
        yaw_i = ATT.start + 2  # the heading error is about NED down
        if d * d <= self.gate1 * (self.P[yaw_i, yaw_i] + sigma_rad**2):
            return False
        _, _, yaw = euler_from_quat(self.q)
        self.set_heading(yaw - d, sigma_rad)  # a turn about NED down by -d
        self.counters.heading_resets += 1
        return True

    def reset_to_fix(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
    ) -> None:
        """Documented fallback: put position and velocity on a fix (antenna, NED).

        Used after a run of rejected fixes and for the first fix after an
        outage. The antenna lever arm is removed with the current attitude and
        rate; position and velocity get the fix's variances and lose their
        correlations with the other states, which keep theirs.
        """
        self._put_on_fix(pos_ned_m, vel_ned_mps, pos_sigma_m, vel_sigma_mps)
        self.counters.gps_resets += 1

    def _put_on_fix(
        self,
        pos_ned_m: np.ndarray,
        vel_ned_mps: np.ndarray,
        pos_sigma_m: np.ndarray,
        vel_sigma_mps: float,
    ) -> None:
        c = dcm_from_quat(self.q)
        self.pos = np.asarray(pos_ned_m, dtype=float) - c @ self.antenna_b_m
        self.vel = np.asarray(vel_ned_mps, dtype=float) - c @ np.cross(self.w, self.antenna_b_m)
        n = self.layout.n
        keep = np.ones(n, dtype=bool)
        keep[0:6] = False
        p = self.P.copy()
        p[~keep, :] = 0.0
        p[:, ~keep] = 0.0
        p[POS, POS] = np.diag(np.broadcast_to(np.asarray(pos_sigma_m, dtype=float), 3) ** 2)
        p[VEL, VEL] = np.eye(3) * float(vel_sigma_mps) ** 2
        self.P = p
        self._consec_rejects = 0
        self._consec_vel_rejects = 0
        self.t_last_position_fix = self.t_s
        self.check_covariance("GPS reset")

    def set_heading(self, yaw_rad: float, sigma_rad: float) -> None:
        """Replace the heading (keeping roll and pitch); its variance becomes ``sigma^2``."""
        roll, pitch, _ = euler_from_quat(self.q)
        self.q = quat_from_euler(roll, pitch, yaw_rad)
        # the heading error is about NED down: decorrelate it and set its variance
        p = self.P.copy()
        p[8, :] = 0.0
        p[:, 8] = 0.0
        p[8, 8] = sigma_rad**2
        self.P = p
        self._consec_slip_rejects = 0
        self.check_covariance("heading alignment")

    # -------------------------------------------------------------- internals
    def _inject(self) -> None:
        dx = self.x
        self.pos = self.pos + dx[POS]
        dth = dx[ATT]
        v_old = self.vel
        body = self.in_body_frame() and (
            0.5 * float(np.linalg.norm(v_old)) * float(dth @ dth)
            <= BODY_INJECTION_MAX_CURVATURE_MPS
        )
        if body:
            # the body velocity takes the correction and the corrected attitude carries it
            self.vel = dcm_from_quat(quat_from_rotvec(dth)) @ (
                v_old + dx[VEL] + np.cross(v_old, dth)
            )
        else:
            self.vel = v_old + dx[VEL]
        self.q = quat_rotate_by_rotvec(self.q, dth, left=True)
        self.w = self.w + dx[RATE]
        self.bias = self.bias + dx[self.layout.bias]
        self.dr = self.dr + dx[self.layout.dr]
        if self.layout.n_aoa:
            da = dx[self.layout.aoa]
            self.aoa_b += float(da[0])
            if self.layout.n_aoa == 2:
                self.aoa_k += float(da[1])
        # reset Jacobian of the attitude error (first order): G = I except
        # G[ATT, ATT] = I + [dtheta]x / 2, the left (NED) error's reset (checked
        # against exact rotations in tests/test_body_velocity_error.py), with its
        # heading column held at e_z (observability-constrained, as OC-EKFs hold their
        # unobservable directions): a turn of the whole solution about the vertical is
        # the left error's e_z at every epoch, and exactly unobservable at rest. The
        # exact reset's column, e_z + dtheta x e_z / 2, put a part of a large heading
        # variance into the tilt's rows at every tilt correction, which the fixes then
        # read as heading information: at rest (`static`, 16 runs) the heading's sigma
        # fell from 5.0 to 3.6 deg while its error stayed at 5.8 deg rms (z^2 2.83);
        # held, 4.9-5.0 deg and 0.92-1.00 (docs/notes/filter-notes.md, "the zero-rate update
        # at rest")
        hx, hy, hz = dth.tolist()
        hx, hy, hz = 0.5 * hx, 0.5 * hy, 0.5 * hz
        ga = np.array([[1.0, -hz, 0.0], [hz, 1.0, 0.0], [-hy, hx, 1.0]])
        p = self.P
        if body:
            gvv, gvt = body_velocity_reset_jacobian(dth, dx[VEL], v_old)
            rows_v = p[VEL, :].copy()
            rows_t = p[ATT, :].copy()
            p[VEL, :] = gvv @ rows_v + gvt @ rows_t
            p[ATT, :] = ga @ rows_t
            cols_v = p[:, VEL].copy()
            cols_t = p[:, ATT].copy()
            p[:, VEL] = cols_v @ gvv.T + cols_t @ gvt.T
            p[:, ATT] = cols_t @ ga.T
        else:
            p[ATT, :] = ga @ p[ATT, :]
            p[:, ATT] = p[:, ATT] @ ga.T
        self.P = 0.5 * (p + p.T)
        self.x = np.zeros(self.x.shape[0])

    def _symmetrise(self) -> None:
        self.P = 0.5 * (self.P + self.P.T)

    def check_covariance(self, where: str, full: bool = True) -> None:
        """Raise :class:`CovarianceError` unless P is finite, symmetric and positive definite.

        ``full=False`` is the per-block check: finite with a positive diagonal
        (P is symmetrised after every step). The full check adds symmetry and
        a Cholesky factorisation (positive definite); the pipeline runs it at
        every GPS fix and once a second.
        """
        p = self.P
        if not np.isfinite(p).all():
            raise CovarianceError(f"covariance not finite after {where} at t = {self.t_s:.3f} s")
        if not full:
            if np.diagonal(p).min() <= 0.0:
                raise CovarianceError(
                    f"covariance has a non-positive variance after {where} at t = {self.t_s:.3f} s"
                )
            return
        if np.abs(p - p.T).max() > 1e-9 * np.abs(p).max():
            raise CovarianceError(f"covariance not symmetric after {where} at t = {self.t_s:.3f} s")
        try:
            np.linalg.cholesky(p)
        except np.linalg.LinAlgError:
            ev = np.linalg.eigvalsh(p)
            raise CovarianceError(
                f"covariance not positive definite after {where} at t = {self.t_s:.3f} s "
                f"(smallest eigenvalue {ev[0]:.3e})"
            ) from None
