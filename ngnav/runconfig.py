"""The configuration of one run (``config.toml``): what the filter knows of the hardware.

A recorded run and a simulated one are described the same way: the nominal
layout, the calibrated mounting errors, scale and offset of each channel, the
sensor noise, the reference point, the antenna lever arm, how to initialise,
and the filter's settings. Nothing here is truth: a simulation writes its
truth to separate files.

``config.toml`` layout (all keys required unless a default is given)::

    [array]        positions_b_m = [[x, y, z], ...]   # N rows, FRD, m (nominal)
                   axes_b = [[x, y, z], ...]          # N unit vectors (nominal)
                   lever_arm_m = 0.1                  # optional, informational
    [calibration]  position_error_b_m = [[..]]        # N x 3, known offsets, m
                   axis_error_rad = [[a1, a2], ...]   # N x 2, calibrated, rad
                   scale = [...]                      # N, real/nominal sensitivity
                   offset_mps2 = [...]                # N, zero offset, m/s^2
                   position_sigma_m = x               # 1-sigma of the unknown position
                                                      # error per axis (default 0)
    [sensor]       noise_sigma_mps2 = [...] or x      # per sample, m/s^2
                   turn_on_bias_mps2 = [...] or x     # 1-sigma, m/s^2
                   bias_rw_mps2_rts = [...] or x      # m/s^2 per root s
                   range_mps2 = x                     # saturation level
    [reference]    lat_deg, lon_deg, alt_m            # NED origin, WGS-84
    [gps]          antenna_b_m = [x, y, z]            # FRD, m
    [initial]      alignment = "static"|"config", static_s, roll_deg, pitch_deg,
                   yaw_deg, tilt_sigma_deg, heading_source = "config"|"gps",
                   heading_sigma_deg, rate_dps = [x, y, z], rate_sigma_dps
    [filter]       rate_hz, compensation, window, gate_probability, rate_range_dps,
                   sideslip_sigma_deg, aoa_sigma_deg, aoa_prior_deg,
                   aoa_prior_sigma_deg, aoa_rw_deg_rts, aoa_lift_k_m, aoa_lift_k_sigma_m,
                   liftoff_speed_mps,
                   gps_gap_reset_s, fusion_lag_s,
                   hold_wdot_sigma_rps2, hold_force_sigma_mps2, position_states,
                   remainder_updates, attitude_remainder_updates,
                   coast_remainder_updates, coast_after_s,
                   forecast_error_persistence, forecast_correction,
                   vehicle_model_rate_hz, count_by_prior_weight,
                   body_velocity_error, rest_rate_sigma_dps
                   (each explained in FilterSettings' docstring)
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ngnav.layout import ArrayLayout
from ngnav.mounting import MountingErrors


@dataclass(frozen=True)
class InitialSettings:
    """How the filter starts (see the module docstring).

    With ``alignment = "config"`` (a hand-over: the vehicle is already moving) the
    filter starts at ``roll_deg``/``pitch_deg``/``yaw_deg`` and at the body rate
    ``rate_dps`` (FRD, deg/s; the launcher's reading), each with its 1-sigma; a
    static alignment starts at rest (``rate_dps`` unused): at zero rate, with
    ``rate_sigma_dps`` the rest's residual rate (a still vehicle turns in the NED
    frame only with the Earth, 0.0042 deg/s, which the filter leaves out; a running
    engine's rocking is more).
    """

    alignment: str = "static"
    static_s: float = 5.0
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    tilt_sigma_deg: float = 2.0
    heading_source: str = "config"
    heading_sigma_deg: float = 5.0
    rate_dps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rate_sigma_dps: float = 1.0

    def __post_init__(self) -> None:
        if len(self.rate_dps) != 3 or not all(np.isfinite(self.rate_dps)):
            raise ValueError(f"initial.rate_dps must be 3 finite numbers, got {self.rate_dps}")


#: Compensation choices of the filter's front end.
COMPENSATIONS: tuple[str, ...] = ("gm11", "none", "line", "last", "oracle")


@dataclass(frozen=True)
class FilterSettings:
    """Filter rate (Hz), compensation method, GM window, gate and rate range (deg/s).

    ``sideslip_sigma_deg`` > 0 adds the fixed-wing vehicle model: at 5 Hz
    (through GPS outages too) and above 5 m/s ground speed, the body-lateral
    velocity is measured as zero with a 1-sigma of
    ``speed * tan(sideslip_sigma_deg)``. It assumes the
    ground velocity lies in the body's x-z plane (calm air, or a crab angle
    within that sigma); 0 (the default) leaves it out. With the model on, a
    heading that contradicts the GPS course (beyond the 1-dof gate) is put on
    the course after a GPS reset, or after 25 sideslip updates in a row fail
    their gate while GPS velocity is accepted (``NavFilter.check_heading_against_course``,
    counted as "heading resets to the GPS course"): a heading 180 deg off also
    has zero lateral velocity, and one tens of degrees off never passes the gate.

    ``aoa_sigma_deg`` > 0 adds the same model in the body's x-z plane: with the
    sideslip updates (and above the same speed), the velocity along the
    wind-normal axis ``[-sin alpha, 0, cos alpha]`` (FRD) is measured as zero
    with a 1-sigma of ``|v| tan(aoa_sigma_deg)``: the ground velocity leaves the
    body x axis by the angle of attack ``alpha`` and by nothing else (calm air).
    0 (the default) leaves it out.

    ``aoa_prior_sigma_deg`` > 0 carries ``alpha`` as a filter state (``AOA``),
    starting at ``aoa_prior_deg`` with that 1-sigma and wandering as a random
    walk of ``aoa_rw_deg_rts`` (deg/sqrt(s)), which must cover how fast the
    vehicle's angle of attack changes (it follows load factor and speed). The
    state is learnt while GPS holds the velocity and carries the pitch-to-path
    tie through an outage. With ``aoa_prior_sigma_deg`` = 0 the model assumes
    ``alpha`` = 0 (the land-vehicle non-holonomic constraint), which no
    aircraft keeps: lift needs angle of attack.

    ``aoa_lift_k_m`` > 0 gives the state the airframe's lift law:
    ``alpha = w(V) (alpha_b + K n_w / V^2)``, ``K = 2 (m/S) / (rho C_La)`` in m,
    with the wind-frame normal load ``n_w`` from the array's specific force and
    ``V`` the speed, so the angle of attack follows every change of load factor
    and speed as the lift asks; the state is then the law's offset ``alpha_b``
    (the zero-lift angle, prior ``aoa_prior_deg``) and its random walk covers
    only what the law leaves out. ``aoa_lift_k_sigma_m`` > 0 carries the error of
    ``K`` (mass, density and lift slope are never known exactly) as a second,
    constant state with that prior 1-sigma: its effect grows with the load factor,
    which a random walk on the offset cannot describe. With
    ``liftoff_speed_mps`` > 0, ``w(V)`` is 0 below 0.8 times that speed (on the
    wheels: no angle of attack), 1 from it up, a minimum-jerk step between.

    ``gps_gap_reset_s``: the first fix after this long without an accepted
    GPS position (an outage) is not fused but, if it passes the gate, puts
    position and velocity on the fix (``NavFilter.reset_to_fix``; PX4 EKF2
    resets to GPS after a fusion timeout in the same way). A long coast
    builds its cross-covariances on a drifted trajectory; fusing a large
    innovation through them left the vertical velocity several sigma off for
    30 s on ``uav-survey``. 0 switches the reset off.

    ``fusion_lag_s``: how far the filter's fusion horizon runs behind the
    newest array sample when inputs arrive as a stream (PX4 EKF2's delayed
    horizon). A GPS fix that arrives within this lag of its time of validity
    is fused exactly there, as in an offline run; a later one is fused at the
    next block with a ``v dt`` time shift and counted. Estimates are output
    at the fusion horizon, so they trail the newest sample by this lag.

    ``position_states``: carry the residual sensor positions as filter states
    (``DR``, see :mod:`filters.state`) when the calibration gives a position
    1-sigma; False leaves them out (the scatter is then unmodelled).

    ``remainder_updates`` and ``attitude_remainder_updates`` (each >= 1): how many
    times the sideslip and angle-of-attack updates count their second-order
    remainder's variance, and its attitude-product part, in R: the number of
    consecutive updates (at ``vehicle_model_rate_hz``) that share one value of it
    (``filters.vehicle_model.remainder_variance``; the attitude part never fewer times than
    the whole). The defaults, 4 and 40, are what ``uav-survey`` was tuned and
    measured with (docs/notes/filter-notes.md, "the sideslip remainder"); ``tactical`` counts the
    attitude part 7 times, its measured persistence after the hand-over, which
    counts the whole remainder ``coast_remainder_updates`` times for the coast's
    hold from the vehicle models' first update (after a configured alignment at once,
    after a static one in the take-off roll; docs/notes/filter-notes.md, "the hand-over counted
    as a coast's end"). ``python -m studies.remainder`` measures what a flight's remainders
    actually need, against its truth.

    ``forecast_error_persistence`` (>= 0, default 2): with a forecast compensation
    (GM(1,1), line, last) the filter measures the forecast's error after each block,
    from the block's own mean less the forecast, and adds what the compensation
    left of it to the rate and velocity covariance (``filters.pipeline``, "the
    forecast's error"). The error of a forecast through a manoeuvre's onset is
    not white: it persists over a few blocks, and this is how many blocks' worth
    of its variance one block counts (``1 + 2 sum_k rho_k`` of its autocorrelation;
    over ``tactical``'s roll-ins the angular acceleration's reads 0.72, 0.3 and 0.1
    at lags of 1, 2 and 5 blocks). 1, 2 and 3 were tried on 100 ``tactical`` runs
    and 1 and 2 over ten draws of 50 (docs/notes/filter-notes.md, "the forecast's error"): without
    ``forecast_correction`` 2 meets the target on one draw, 1 on none; with it (as
    ``tactical.toml`` ships) 1 meets it on two. 0 switches it off.

    ``forecast_correction`` (default false): with a forecast compensation, after
    each block remove from the nominal rate, attitude, velocity and position what
    the forecast's measured error left in the block's features (``E_6 d``, ``d``
    the block's mean less its forecast, :attr:`filters.pipeline.Pipeline.last_forecast_error`;
    ``filters.ekf.NavFilter.remove_feature_residual``), and from the history the next
    forecasts read. The forecast's error in a given manoeuvre has the same sign in every
    run, which no noise term removes; on ``tactical`` it biased the lift law's ``K``
    by 1.5 sigma after the roll-out (docs/notes/filter-notes.md, "`tactical`'s angle of attack
    after the
    roll-out"). Off by default; ``tactical.toml`` turns it on with persistence 1, which
    over ten draws of 50 runs cut the misses below 90 % from 19 to 13 and centred the
    attitude and the angle of attack (persistence 0 with a halved angle-of-attack walk
    turned the rate, attitude and angle of attack optimistic; docs/notes/filter-notes.md, "the
    forecast's
    error taken out of the state"). On ``uav-survey``'s five draws it left the same
    misses, each a little smaller, so the survey ships without it (docs/notes/filter-notes.md).

    ``coast_remainder_updates`` (>= 1, default 40) replaces ``remainder_updates``
    while the filter coasts: from ``coast_after_s`` (default 1 s) or five intervals
    of the GPS fixes received, whichever is longer, without an accepted GPS position until
    ``coast_remainder_updates / 5 Hz`` seconds after the last such update (the
    coast's remainder lasts its count of updates after it). 40 is the persistence
    ``python -m studies.remainder`` measures through ``uav-survey``'s outage. Setting it equal to
    ``remainder_updates`` turns the switch off.

    ``vehicle_model_rate_hz`` (in (0, 5], default 5): the rate of the sideslip and
    angle-of-attack updates outside the hand-over and coasts; through those (and their
    holds) they run at 5 Hz, where ``coast_remainder_updates`` counts 5 Hz updates
    (``filters.ekf.NavFilter.counts_as_coast``). ``remainder_updates`` and
    ``attitude_remainder_updates`` count updates at this rate. Updating about once per
    decorrelation interval of the remainder, consecutive updates share little of it and
    the count can be 1, which removes the dip the count makes after each update
    (docs/notes/filter-notes.md, "the vehicle model at the remainder's own interval"). Both
    scenarios
    keep 5 Hz: at 1 Hz ``tactical``'s rate read optimistic over ten draws (3.06) and
    ``uav-survey``'s dip stayed (its attitude part still counted 8 times).

    ``count_by_prior_weight`` (default false): outside the hand-over and coasts, the
    sideslip update counts the remainder ``1 + (n - 1) w`` times in place of ``n`` (each
    of its two counts), ``w = R / (h P h^T + R)`` the weight the update keeps on the prior
    along the constraint (``filters.vehicle_model.prior_weighted_count``). A remainder
    shared by consecutive updates adds information it does not have only through what an
    update keeps of the earlier ones. In GPS-held flight the prior along the constraint
    is hundreds to thousands of times R (fresh process noise), the update replaces the constraint's
    combination by the measurement, and the gain is the same to ``(n - 1) R / (h P h^T)``
    either way, so the count only left the constraint's direction several times too
    uncertain after each update: the joint NEES's dip (docs/notes/filter-notes.md, "the count by
    the prior's weight"). The angle-of-attack update keeps its counts: its prior along
    the constraint holds the lift law's states, which persist from update to update, and
    weighted like the sideslip's it turned ``uav-survey``'s attitude and rate optimistic.
    Both scenarios turn it on.

    ``body_velocity_error`` (default false): the filter takes its velocity error in the
    body frame (``filters.ekf.NavFilter.body_velocity_error``): the vehicle models become
    exactly linear, their attitude-product remainder, which persists as long as the tilt
    errors do and needed the counts above, is gone, and the velocity rows take the
    correction's reset Jacobian instead. The velocity a user reads stays NED, with the
    parametrization's curvature in its mean and covariance. The filter uses it only while
    its attitude is known to about 2 deg and the last GPS velocity and vehicle-model
    updates passed their gates (``filters.ekf.NavFilter.in_body_frame``: without that
    guard a hand-over told 1 deg while 15 deg off relearned its tilt twice as badly), and
    the NED error otherwise. On in ``tactical`` (with ``coast_remainder_updates = 10``),
    where it lifts the joint NEES from 84.0 to 89.7 % inside on runs 0-49 (at f2cb205);
    off in ``uav-survey``, whose coast's end it left optimistic and whose joint it lowered
    while GPS holds (docs/notes/filter-notes.md, "the velocity error in the body frame, with the
    reset's Jacobian" and "Not met yet").

    ``rest_rate_sigma_dps`` > 0 (default 0: off) adds the zero-rate update at detected
    rest (``filters.ekf.NavFilter.update_zero_rate``): at the start of every block while
    :class:`filters.rest.RestDetector` says the vehicle stands still, the body rate is
    measured as zero with this 1-sigma per axis (deg/s): the vehicle's rocking on its
    mounts, or a numerical floor where the rest is exact (the simulated flights: 1e-4).
    At rest nothing else holds a gyro-free array's yaw rate (the rate products vanish
    with the rates, and GPS sees no heading without a horizontal acceleration): without
    the update two minutes at rest (``static``) lost the heading with a yaw-rate sigma
    that stopped at 1.6 deg/s (0.028 rad/s) while the error grew to 11 deg/s by 120 s
    (docs/notes/filter-notes.md, "two minutes at rest"). Rest is the static alignment's,
    going on, or one the GPS velocity and the array's steadiness confirm for 1 s; any
    change of the array's output, a fix that reads motion, or a rejected update ends it.
    A spin at constant rate with no angular acceleration (a multirotor yawing in hover)
    reads as rest to the array: the update's gate rejects it once the filter's rate
    contradicts zero, but not if the spin began before the filter did. Leave it off for
    such vehicles.
    """

    #: Settings that no longer exist, with the behaviour that is now fixed: a file that
    #: gives that value still reads (docs/design.md, "Settings retired").
    RETIRED: ClassVar[dict[str, Any]] = {
        "remainder_off_constraint": False,
        "position_consider": False,
        "remainder_consider": False,
    }

    rate_hz: float = 100.0
    compensation: str = "gm11"
    window: int = 5
    gate_probability: float = 0.9999
    rate_range_dps: float = 200.0
    sideslip_sigma_deg: float = 0.0
    aoa_sigma_deg: float = 0.0
    aoa_prior_deg: float = 0.0
    aoa_prior_sigma_deg: float = 0.0
    aoa_rw_deg_rts: float = 0.0
    aoa_lift_k_m: float = 0.0
    aoa_lift_k_sigma_m: float = 0.0
    liftoff_speed_mps: float = 0.0
    gps_gap_reset_s: float = 5.0
    fusion_lag_s: float = 0.1
    hold_wdot_sigma_rps2: float = 2.0
    hold_force_sigma_mps2: float = 3.0
    position_states: bool = True
    remainder_updates: float = 4.0
    attitude_remainder_updates: float = 40.0
    coast_remainder_updates: float = 40.0
    coast_after_s: float = 1.0
    forecast_error_persistence: float = 2.0
    forecast_correction: bool = False
    vehicle_model_rate_hz: float = 5.0
    count_by_prior_weight: bool = False
    body_velocity_error: bool = False
    rest_rate_sigma_dps: float = 0.0

    def __post_init__(self) -> None:
        if self.compensation not in COMPENSATIONS:
            raise ValueError(
                f"filter.compensation must be one of {COMPENSATIONS}, got {self.compensation!r}"
            )
        for name in ("sideslip_sigma_deg", "aoa_sigma_deg"):
            v = getattr(self, name)
            if not 0.0 <= v < 45.0:
                raise ValueError(f"filter.{name} must be in [0, 45), got {v}")
        if not (np.isfinite(self.aoa_prior_deg) and abs(self.aoa_prior_deg) < 30.0):
            raise ValueError(f"filter.aoa_prior_deg must be in (-30, 30), got {self.aoa_prior_deg}")
        for name in ("aoa_prior_sigma_deg", "aoa_rw_deg_rts"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 <= v <= 30.0):
                raise ValueError(f"filter.{name} must be a number in [0, 30], got {v}")
        if self.aoa_prior_sigma_deg > 0 and self.aoa_sigma_deg == 0:
            raise ValueError(
                "filter.aoa_prior_sigma_deg > 0 needs filter.aoa_sigma_deg > 0: the "
                "angle-of-attack state is observed only through that model"
            )
        for name in ("aoa_lift_k_m", "aoa_lift_k_sigma_m", "liftoff_speed_mps"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 <= v <= 1000.0):
                raise ValueError(f"filter.{name} must be a number in [0, 1000], got {v}")
            if v > 0 and self.aoa_prior_sigma_deg == 0:
                raise ValueError(
                    f"filter.{name} > 0 needs filter.aoa_prior_sigma_deg > 0 "
                    "(the angle-of-attack state)"
                )
        if self.aoa_rw_deg_rts > 0 and self.aoa_prior_sigma_deg == 0:
            raise ValueError(
                "filter.aoa_rw_deg_rts > 0 needs filter.aoa_prior_sigma_deg > 0 "
                "(the angle-of-attack state)"
            )
        if not (np.isfinite(self.gps_gap_reset_s) and self.gps_gap_reset_s >= 0.0):
            raise ValueError(
                f"filter.gps_gap_reset_s must be a finite number >= 0, got {self.gps_gap_reset_s}"
            )
        if not (np.isfinite(self.rest_rate_sigma_dps) and 0.0 <= self.rest_rate_sigma_dps <= 10.0):
            raise ValueError(
                "filter.rest_rate_sigma_dps must be a number in [0, 10], got "
                f"{self.rest_rate_sigma_dps}"
            )
        for name in ("hold_wdot_sigma_rps2", "hold_force_sigma_mps2"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise ValueError(f"filter.{name} must be a finite number >= 0, got {v}")
        for name in ("remainder_updates", "attitude_remainder_updates", "coast_remainder_updates"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 1.0 <= v <= 1e4):
                raise ValueError(f"filter.{name} must be a number in [1, 10000], got {v}")
        if not (
            np.isfinite(self.forecast_error_persistence)
            and 0.0 <= self.forecast_error_persistence <= 100.0
        ):
            raise ValueError(
                "filter.forecast_error_persistence must be a number in [0, 100], got "
                f"{self.forecast_error_persistence}"
            )
        if not (
            np.isfinite(self.vehicle_model_rate_hz) and 0.0 < self.vehicle_model_rate_hz <= 5.0
        ):
            raise ValueError(
                "filter.vehicle_model_rate_hz must be a number in (0, 5] Hz, got "
                f"{self.vehicle_model_rate_hz}"
            )
        if not (np.isfinite(self.coast_after_s) and 0.0 < self.coast_after_s <= 1e3):
            raise ValueError(
                f"filter.coast_after_s must be a number in (0, 1000] s, got {self.coast_after_s}"
            )
        if not (np.isfinite(self.fusion_lag_s) and 0.0 <= self.fusion_lag_s <= 10.0):
            raise ValueError(
                f"filter.fusion_lag_s must be a number in [0, 10] s, got {self.fusion_lag_s}"
            )


@dataclass(frozen=True)
class RunConfig:
    """Everything the filter is told about a run (arrays are read-only)."""

    layout: ArrayLayout
    known_errors: MountingErrors
    scale: np.ndarray
    offset_mps2: np.ndarray
    noise_sigma_mps2: np.ndarray
    turn_on_bias_mps2: np.ndarray
    bias_rw_mps2_rts: np.ndarray
    range_mps2: float
    lat0_deg: float
    lon0_deg: float
    alt0_m: float
    antenna_b_m: np.ndarray
    position_sigma_m: float = 0.0
    initial: InitialSettings = field(default_factory=InitialSettings)
    filter: FilterSettings = field(default_factory=FilterSettings)

    def __post_init__(self) -> None:
        n = self.layout.n_sensors
        for name in (
            "scale",
            "offset_mps2",
            "noise_sigma_mps2",
            "turn_on_bias_mps2",
            "bias_rw_mps2_rts",
        ):
            a = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (n,)).copy()
            if not np.all(np.isfinite(a)):
                raise ValueError(f"config: {name} must be finite")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if np.any(self.noise_sigma_mps2 <= 0):
            raise ValueError("config: sensor.noise_sigma_mps2 must be positive")
        if np.any(self.scale <= 0):
            raise ValueError("config: calibration.scale must be positive")
        arm = np.asarray(self.antenna_b_m, dtype=float).reshape(3).copy()
        arm.setflags(write=False)
        object.__setattr__(self, "antenna_b_m", arm)
        if self.known_errors.n_sensors != n:
            raise ValueError(
                f"config: calibration has {self.known_errors.n_sensors} sensors, layout has {n}"
            )
        if self.initial.alignment not in ("static", "config"):
            raise ValueError(
                f"config: initial.alignment must be static or config, "
                f"got {self.initial.alignment!r}"
            )
        if self.initial.heading_source not in ("config", "gps"):
            raise ValueError("config: initial.heading_source must be config or gps")


def _matrix(table: dict, key: str, shape: tuple[int | None, int], where: str) -> np.ndarray:
    if key not in table:
        raise ValueError(f"{where}: missing key {key}")
    try:
        a = np.asarray(table[key], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {key} must be numbers") from None
    if a.ndim != 2 or a.shape[1] != shape[1] or (shape[0] is not None and a.shape[0] != shape[0]):
        raise ValueError(
            f"{where}: {key} must have shape ({shape[0] or 'N'}, {shape[1]}), got {a.shape}"
        )
    return a


def _vector(table: dict, key: str, n: int, where: str, default: Any = None) -> np.ndarray:
    if key not in table:
        if default is None:
            raise ValueError(f"{where}: missing key {key}")
        return np.full(n, float(default))
    try:
        a = np.asarray(table[key], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {key} must be a number or {n} numbers") from None
    if a.ndim == 0:
        return np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(f"{where}: {key} must have {n} values, got {a.shape[0]}")
    return a


def _settings(cls: type, table: Any, where: str) -> Any:
    from ngnav.scenario import _build

    return _build(cls, table if table is not None else {}, where, "config.toml")


def read_run_config(path: str | Path) -> RunConfig:
    """Read and validate a run's ``config.toml``; errors name the file and key."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: no such file") from None
    return read_run_config_text(text, str(p))


def read_run_config_text(text: str, where: str) -> RunConfig:
    """Parse and validate the text of a ``config.toml``; errors start with ``where``."""
    p = where
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{p}: not valid TOML: {exc}") from None
    for section in ("array", "calibration", "sensor", "reference"):
        if not isinstance(data.get(section), dict):
            raise ValueError(f"{p}: missing section [{section}]")
    arr, cal, sen, ref = data["array"], data["calibration"], data["sensor"], data["reference"]
    pos = _matrix(arr, "positions_b_m", (None, 3), f"{p} [array]")
    n = pos.shape[0]
    axes = _matrix(arr, "axes_b", (n, 3), f"{p} [array]")
    try:
        layout = ArrayLayout(
            pos, axes, name=str(arr.get("name", "config")), lever_arm_m=arr.get("lever_arm_m")
        )
        known = MountingErrors(
            _matrix(cal, "position_error_b_m", (n, 3), f"{p} [calibration]"),
            _matrix(cal, "axis_error_rad", (n, 2), f"{p} [calibration]"),
        )
        gps = data.get("gps", {})
        ref_vals = []
        for k in ("lat_deg", "lon_deg", "alt_m"):
            if k not in ref:
                raise ValueError(f"{p} [reference]: missing key {k}")
            ref_vals.append(float(ref[k]))
        if "range_mps2" not in sen:
            raise ValueError(f"{p} [sensor]: missing key range_mps2")
        return RunConfig(
            layout=layout,
            known_errors=known,
            scale=_vector(cal, "scale", n, f"{p} [calibration]", 1.0),
            offset_mps2=_vector(cal, "offset_mps2", n, f"{p} [calibration]", 0.0),
            noise_sigma_mps2=_vector(sen, "noise_sigma_mps2", n, f"{p} [sensor]"),
            turn_on_bias_mps2=_vector(sen, "turn_on_bias_mps2", n, f"{p} [sensor]", 0.0),
            bias_rw_mps2_rts=_vector(sen, "bias_rw_mps2_rts", n, f"{p} [sensor]", 0.0),
            range_mps2=float(sen["range_mps2"]),
            lat0_deg=ref_vals[0],
            lon0_deg=ref_vals[1],
            alt0_m=ref_vals[2],
            antenna_b_m=np.asarray(gps.get("antenna_b_m", [0.0, 0.0, 0.0]), dtype=float),
            position_sigma_m=float(cal.get("position_sigma_m", 0.0)),
            initial=_settings(InitialSettings, data.get("initial"), "initial"),
            filter=_settings(FilterSettings, data.get("filter"), "filter"),
        )
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return repr(float(v))
    return str(v)


def write_run_config(cfg: RunConfig, path: str | Path) -> None:
    """Write ``cfg`` as ``config.toml`` (round-trips exactly through :func:`read_run_config`)."""
    Path(path).write_text(run_config_text(cfg), encoding="utf-8")


def run_config_text(cfg: RunConfig) -> str:
    """The ``config.toml`` text of ``cfg`` (deterministic; floats by ``repr``)."""
    from dataclasses import asdict

    lines = ["# ngnav run configuration: what the filter knows of the hardware (no truth).", ""]
    sections: dict[str, dict[str, Any]] = {
        "array": {
            "name": cfg.layout.name,
            "positions_b_m": cfg.layout.positions_b_m,
            "axes_b": cfg.layout.axes_b,
        },
        "calibration": {
            "position_error_b_m": cfg.known_errors.position_error_b_m,
            "axis_error_rad": cfg.known_errors.axis_error_rad,
            "scale": cfg.scale,
            "offset_mps2": cfg.offset_mps2,
            "position_sigma_m": cfg.position_sigma_m,
        },
        "sensor": {
            "noise_sigma_mps2": cfg.noise_sigma_mps2,
            "turn_on_bias_mps2": cfg.turn_on_bias_mps2,
            "bias_rw_mps2_rts": cfg.bias_rw_mps2_rts,
            "range_mps2": cfg.range_mps2,
        },
        "reference": {"lat_deg": cfg.lat0_deg, "lon_deg": cfg.lon0_deg, "alt_m": cfg.alt0_m},
        "gps": {"antenna_b_m": cfg.antenna_b_m},
        "initial": asdict(cfg.initial),
        "filter": asdict(cfg.filter),
    }
    if cfg.layout.lever_arm_m is not None:
        sections["array"]["lever_arm_m"] = float(cfg.layout.lever_arm_m)
    for name, table in sections.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {_fmt(v)}" for k, v in table.items()]
        lines.append("")
    return "\n".join(lines)
