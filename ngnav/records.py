"""Immutable records that carry data between modules, each with its time.

Arrays inside records are copied and made read-only, so a record can be shared
without defensive copies downstream.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

#: The navigation error blocks every estimate starts with, in order (``filters.state``).
NAV_BLOCKS: tuple[tuple[str, int], ...] = (("pos", 3), ("vel", 3), ("att", 3), ("rate", 3))
#: Number of navigation error states.
N_NAV = 12


def frozen_array(a: np.ndarray | None, name: str, shape_tail: tuple[int, ...] = ()) -> np.ndarray:
    """Copy ``a`` to a read-only float array and check its trailing shape."""
    if a is None:
        raise ValueError(f"{name} is required")
    out = np.array(a, dtype=float)
    if shape_tail and out.shape[out.ndim - len(shape_tail) :] != shape_tail:
        raise ValueError(f"{name} must have trailing shape {shape_tail}, got {out.shape}")
    out.setflags(write=False)
    return out


def freeze_fields(record: object, shapes: dict[str, tuple[int, ...]]) -> None:
    """Replace the named array fields of a frozen dataclass by read-only copies.

    ``shapes`` maps field name to the required trailing shape (``()`` for any).
    """
    for name, tail in shapes.items():
        object.__setattr__(record, name, frozen_array(getattr(record, name), name, tail))


def check_time_axis(t_s: np.ndarray, name: str = "t_s") -> None:
    """Raise ValueError naming the first sample where ``t_s`` is not finite or not increasing."""
    if t_s.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {t_s.shape}")
    bad = np.flatnonzero(~np.isfinite(t_s))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] is not finite ({t_s[bad[0]]})")
    step = np.diff(t_s)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        i = bad[0] + 1
        raise ValueError(
            f"time stamps must increase strictly: {name}[{i}] = {t_s[i]!r} "
            f"follows {name}[{i - 1}] = {t_s[i - 1]!r}"
        )


@dataclass(frozen=True)
class ArraySamples:
    """Raw accelerometer-array outputs.

    Parameters
    ----------
    t_s : array (T,)
        Sample times, s; finite and strictly increasing.
    accel_mps2 : array (T, N)
        Sensor outputs along each sensing axis, m/s^2 (specific force). Rows
        that are not finite mark invalid samples; see :attr:`invalid`.
    """

    t_s: np.ndarray
    accel_mps2: np.ndarray

    def __post_init__(self) -> None:
        t = frozen_array(self.t_s, "t_s")
        a = frozen_array(self.accel_mps2, "accel_mps2")
        check_time_axis(t)
        if a.ndim != 2 or a.shape[0] != t.shape[0]:
            raise ValueError(
                f"accel_mps2 must have shape (T, N) with T = {t.shape[0]} samples, got {a.shape}"
            )
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "accel_mps2", a)

    @property
    def n_channels(self) -> int:
        return self.accel_mps2.shape[1]

    @property
    def invalid(self) -> np.ndarray:
        """Boolean mask (T,) of samples with a non-finite channel."""
        return ~np.all(np.isfinite(self.accel_mps2), axis=1)


@dataclass(frozen=True)
class ArrayKinematics:
    """Body kinematics solved from an accelerometer array, at the sample times.

    Parameters
    ----------
    t_s : array (T,)
        Times, s.
    omega_dot_b_rps2 : array (T, 3)
        Angular acceleration, body frame, rad/s^2.
    f_b_mps2 : array (T, 3)
        Specific force at the body origin, body frame, m/s^2.
    rate_products_rps2 : array (T, 3)
        ``[w_y w_z, w_x w_z, w_x w_y]``, rad^2/s^2; NaN where the layout
        cannot solve them.
    rate_squares_rps2 : array (T, 3)
        ``[w_x^2, w_y^2, w_z^2]``, rad^2/s^2; NaN where the layout cannot
        solve them (the nine-cube never excites them).
    """

    t_s: np.ndarray
    omega_dot_b_rps2: np.ndarray
    f_b_mps2: np.ndarray
    rate_products_rps2: np.ndarray
    rate_squares_rps2: np.ndarray

    def __post_init__(self) -> None:
        freeze_fields(
            self,
            {
                "t_s": (),
                "omega_dot_b_rps2": (3,),
                "f_b_mps2": (3,),
                "rate_products_rps2": (3,),
                "rate_squares_rps2": (3,),
            },
        )


@dataclass(frozen=True)
class FaultEvent:
    """One failed channel found by the health tests (:mod:`filters.faults`).

    Attributes
    ----------
    channels : tuple of int
        The channel (1-based), or the channels the parity cannot tell apart.
    kind : str
        ``dead``, ``stuck``, ``saturated``, ``noisy`` (named by the channel's own
        samples) or ``drift`` (an offset only the parity sees).
    detected_at_s : float
        When a test first failed, run clock, s.
    isolated_at_s : float
        When the channel was named alone, s (NaN while it is not).
    """

    channels: tuple[int, ...]
    kind: str
    detected_at_s: float
    isolated_at_s: float = float("nan")

    @property
    def isolated(self) -> bool:
        """True once one channel is named."""
        return not np.isnan(self.isolated_at_s)

    def describe(self) -> str:
        """``channel 6 dead: detected 20.025 s, isolated 20.025 s`` (or not isolated)."""
        which = " or ".join(str(c) for c in self.channels)
        iso = f"isolated {self.isolated_at_s:.3f} s" if self.isolated else "not isolated"
        return f"channel {which} {self.kind}: detected {self.detected_at_s:.3f} s, {iso}"


@dataclass(frozen=True)
class TrackLoss:
    """The filter lost its track and started again (:mod:`filters.recovery`).

    Attributes
    ----------
    lost_at_s : float
        When the track was lost, run clock, s.
    restarted_s : float
        When the filter started again from a GPS fix, s.
    reason : str
        What lost it (the covariance failure's message, or a forced loss).
    """

    lost_at_s: float
    restarted_s: float
    reason: str

    def describe(self) -> str:
        """``lost 200.000 s (reason), started again 200.400 s``."""
        return (
            f"lost {self.lost_at_s:.3f} s ({self.reason}), started again {self.restarted_s:.3f} s"
        )


@dataclass(frozen=True)
class GpsUpdateResult:
    """Innovation statistics of one GPS fix: NIS of position and velocity, and acceptance.

    ``nis_pos_h`` and ``nis_pos_v`` split the position NIS into horizontal (2 dof) and
    vertical (1 dof), before the update.
    """

    nis_pos: float
    nis_vel: float
    pos_accepted: bool
    vel_accepted: bool
    nis_pos_h: float = float("nan")
    nis_pos_v: float = float("nan")


@dataclass(frozen=True)
class NavEstimate:
    """One epoch of a navigation filter: state, covariance, health (what outputs read).

    Attributes
    ----------
    t_s : float
        Epoch time, run clock, s.
    pos_ned_m, vel_ned_mps : array (3,)
        Position and velocity of the array's reference point, NED from the run's
        origin, m and m/s (the velocity a user reads, second-order mean included).
    q_nb : array (4,)
        Attitude, Hamilton scalar-first, body (FRD) to NED.
    omega_b_rps : array (3,)
        Body rate, FRD, rad/s.
    bias : array (k,)
        Feature-bias estimates ``[wdot(3), f(3), quad(nq)]``.
    cov : array (n, n)
        Covariance of the whole error state, its blocks in the order of
        ``state_blocks`` (:mod:`filters.state`): position (m), velocity (m/s, the
        velocity a user reads), attitude (a NED small angle, rad), rate (rad/s), then
        the biases, sensor positions and angle-of-attack states the filter carries.
        :attr:`cov_nav` is its navigation (first 12 x 12) block.
    bound_nav : array (12, 12) or None
        The same filter's covariance linearised at the truth (simulations only).
    aoa_rad, aoa_sigma_rad : float or None
        The angle-of-attack estimate and its 1-sigma when the filter carries it.
    last_gps : GpsUpdateResult or None
        The last GPS fix's innovation statistics (None before the first).
    t_last_position_fix_s : float
        Time of the last accepted GPS position, s.
    resets : int
        Times the filter was put back on a GPS fix (after rejections or an outage).
    rate_innovation : array (nq,)
        The last rate-product innovation, rad^2/s^2.
    rate_nis : float
        Its NIS (NaN when the block had no rate update).
    rate_rejected : bool
        The last rate update failed its gate.
    forecast_fallback : bool
        This block's GM(1,1) forecast fell back to the last value.
    forecast_fallbacks : int
        GM(1,1) forecasts fallen back so far.
    held_samples : int
        Array samples held so far (non-finite or saturated).
    rate_updates_rejected : int
        Rate updates rejected by their gate so far.
    faulty_channels : int
        Bit ``i`` set: channel ``i + 1`` was invalid or saturated in this block, is
        excluded as failed, or is one of a group the parity suspects
        (:mod:`filters.faults`, :mod:`filters.exclusion`).
    state_blocks : tuple of (str, int)
        The error state's ordered ``(name, dof)`` blocks that ``cov`` follows; by
        default the four navigation blocks alone (a 12 x 12 ``cov``).
    dr_m : array (3N,) or None
        Estimated sensor-position errors ``dr_i`` (FRD, m; sensor ``i`` at
        ``3 i : 3 i + 3``) when the filter carries them (block ``dr``).
    axis_error_b : array (3N,) or None
        Estimated residual errors ``dg_i`` of the calibrated sensing axes (FRD,
        dimensionless: the scale's along the axis, the angles' across it; sensor ``i``
        at ``3 i : 3 i + 3``) when the filter carries them (block ``cal``).
    valid : bool
        False after the filter started again from a lost track until its attitude's
        1-sigma is back (:mod:`filters.recovery`).
    aoa_states : array (1-2,) or None
        The angle-of-attack block's nominal when carried (block ``aoa``): the lift
        law's offset (rad) and its ``K`` (m), or the offset alone.
    """

    t_s: float
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    q_nb: np.ndarray
    omega_b_rps: np.ndarray
    bias: np.ndarray
    cov: np.ndarray
    bound_nav: np.ndarray | None = None
    aoa_rad: float | None = None
    aoa_sigma_rad: float | None = None
    last_gps: GpsUpdateResult | None = None
    t_last_position_fix_s: float = float("-inf")
    resets: int = 0
    rate_innovation: np.ndarray | None = None
    rate_nis: float = float("nan")
    rate_rejected: bool = False
    forecast_fallback: bool = False
    forecast_fallbacks: int = 0
    held_samples: int = 0
    rate_updates_rejected: int = 0
    faulty_channels: int = 0
    state_blocks: tuple[tuple[str, int], ...] = NAV_BLOCKS
    dr_m: np.ndarray | None = None
    aoa_states: np.ndarray | None = None
    valid: bool = True
    axis_error_b: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = sum(dof for _, dof in self.state_blocks)
        if n < N_NAV or self.state_blocks[: len(NAV_BLOCKS)] != NAV_BLOCKS:
            raise ValueError(f"state_blocks must start with {NAV_BLOCKS}, got {self.state_blocks}")
        shapes = {"pos_ned_m": (3,), "vel_ned_mps": (3,), "q_nb": (4,), "omega_b_rps": (3,)}
        shapes |= {"bias": (), "cov": (n, n)}
        for name, tail in (("bound_nav", (N_NAV, N_NAV)), ("rate_innovation", ())):
            if getattr(self, name) is not None:
                shapes[name] = tail
        for name in ("dr_m", "aoa_states", "axis_error_b"):
            if getattr(self, name) is not None:
                shapes[name] = ()
        freeze_fields(self, shapes)

    @property
    def cov_nav(self) -> np.ndarray:
        """The navigation block (12, 12) of :attr:`cov`: position, velocity, attitude, rate."""
        return self.cov[:N_NAV, :N_NAV]

    def block_cov(self, name: str) -> np.ndarray:
        """The covariance of one named block of :attr:`state_blocks` (dof, dof)."""
        start = 0
        for block, dof in self.state_blocks:
            if block == name:
                return self.cov[start : start + dof, start : start + dof]
            start += dof
        known = ", ".join(b for b, d in self.state_blocks if d)
        raise KeyError(f"no state block {name!r} in this estimate (it has: {known})")


@dataclass(frozen=True)
class Estimates:
    """A filter's estimates at every epoch (E epochs), stacked.

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
    aoa_rad, aoa_sigma_rad : arrays (E,) or None
        The angle-of-attack estimate and its 1-sigma, rad, when the filter carries it.
    faulty_channels : array (E,) of int or None
        Each epoch's :attr:`NavEstimate.faulty_channels` bitmask (None when not kept).
    valid : array (E,) of bool or None
        Each epoch's :attr:`NavEstimate.valid` (None: all valid).
    """

    t_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    q_nb: np.ndarray
    omega_b_rps: np.ndarray
    bias: np.ndarray
    cov_nav: np.ndarray
    bound_nav: np.ndarray | None = None
    aoa_rad: np.ndarray | None = None
    aoa_sigma_rad: np.ndarray | None = None
    faulty_channels: np.ndarray | None = None
    valid: np.ndarray | None = None

    def __post_init__(self) -> None:
        freeze_fields(
            self,
            {"t_s": (), "pos_ned_m": (3,), "vel_ned_mps": (3,), "q_nb": (4,), "omega_b_rps": (3,)},
        )

    @classmethod
    def stack(cls, epochs: list[NavEstimate]) -> Estimates:
        """The records of consecutive epochs as one :class:`Estimates`."""
        return cls.from_rows(
            [
                (
                    e.t_s,
                    e.pos_ned_m,
                    e.vel_ned_mps,
                    e.q_nb,
                    e.omega_b_rps,
                    e.bias,
                    e.cov_nav,
                    e.bound_nav,
                    e.aoa_rad,
                    e.aoa_sigma_rad,
                    e.faulty_channels,
                    e.valid,
                )
                for e in epochs
            ]
        )

    @classmethod
    def from_rows(cls, rows: list[tuple]) -> Estimates:
        """Epochs given as this class's fields in order, one tuple each (E rows)."""
        if not rows:
            raise ValueError("no estimates to stack")
        cols = list(zip(*rows, strict=True))
        out = [np.array(c) for c in cols[:7]]
        out += [None if c[0] is None else np.array(c) for c in cols[7:]]
        return cls(*out)


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

    ``rate_dim`` is the rate measurement's size, ``state_size`` the error state's;
    ``rate_nis_t_s`` holds the time of each ``rate_nis`` value (s). ``estimates``
    keep each epoch's navigation covariance (12 x 12); ``final`` is the last epoch's
    whole record, with the full covariance and the estimated biases, sensor positions
    and angle-of-attack states. ``smoothed`` holds the smoothed epochs of a run made
    with ``smooth=True`` (the same epochs; no angle of attack, no bound); ``faults``
    the failed channels the health tests found (:mod:`filters.faults`).
    """

    estimates: Estimates
    innovations: GpsInnovations
    rate_nis: np.ndarray
    counts: dict[str, int]
    compensation: str
    rate_dim: int = field(default=3)
    state_size: int = 0
    rate_nis_t_s: np.ndarray | None = None
    final: NavEstimate | None = None
    smoothed: Estimates | None = None
    #: The failed channels found (:class:`FaultEvent`), in the order found.
    faults: tuple[FaultEvent, ...] = ()
    #: Each ``rate_nis`` value's dof (fewer than ``rate_dim`` once channels are excluded).
    rate_nis_dof: np.ndarray | None = None
    #: Each loss of the track and start again (:class:`TrackLoss`), in order.
    track_losses: tuple[TrackLoss, ...] = ()


@dataclass(frozen=True)
class FlightTruth:
    """Exact truth of a moving body at the array's sample times (a flight, a turntable).

    Attributes
    ----------
    t_s : array (T,)
        Times, s.
    pos_ned_m : array (T, 3)
        Position of the body origin in the tangent plane, NED, m.
    vel_ned_mps : array (T, 3)
        Velocity of the body origin, NED, m/s.
    q_nb : array (T, 4)
        Attitude, body (FRD) to NED, Hamilton scalar first.
    omega_b_rps, omega_dot_b_rps2 : array (T, 3)
        Body rate (rad/s) and its derivative (rad/s^2), body frame.
    f_b_mps2 : array (T, 3)
        Specific force at the body origin, body frame, m/s^2.
    """

    t_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    q_nb: np.ndarray
    omega_b_rps: np.ndarray
    omega_dot_b_rps2: np.ndarray
    f_b_mps2: np.ndarray

    def __post_init__(self) -> None:
        freeze_fields(
            self,
            {
                "t_s": (),
                "pos_ned_m": (3,),
                "vel_ned_mps": (3,),
                "q_nb": (4,),
                "omega_b_rps": (3,),
                "omega_dot_b_rps2": (3,),
                "f_b_mps2": (3,),
            },
        )
        check_time_axis(self.t_s)

    def loop_state(self) -> np.ndarray:
        """True values (T, 9) of the compensation loop's channels (rate, rate dot, force)."""
        return np.hstack([self.omega_b_rps, self.omega_dot_b_rps2, self.f_b_mps2])


#: What a GPS fix may report and still be a fix of something flying: the latitude and
#: longitude's own ranges; ellipsoidal heights from below the lowest land (-430 m) and
#: geoid (-106 m) with margin to the edge of space (the Karman line), and ground speeds up
#: to Mach 9 at sea level, beyond any air-breathing or tactical vehicle. Anything outside
#: is a corrupt or garbage field: dropped at input and counted by kind
#: (:func:`fix_range_problems`).
FIX_ALT_RANGE_M = (-1000.0, 100_000.0)
FIX_MAX_SPEED_MPS = 3000.0
#: The kinds :func:`fix_range_problems` names, in the order it checks them.
FIX_RANGE_KINDS = (
    "latitude beyond +-90 deg",
    "longitude beyond +-180 deg",
    "altitude outside -1 km .. 100 km",
    "speed above 3 km/s",
)


def fix_range_problems(
    lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray, vel_ned_mps: np.ndarray
) -> np.ndarray:
    """Index into :data:`FIX_RANGE_KINDS` of each fix's first out-of-range field, -1 where
    all are in range (M,); arrays (M,) and (M, 3), or scalars and (3,) for one fix."""
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    alt = np.atleast_1d(np.asarray(alt_m, dtype=float))
    vel = np.asarray(vel_ned_mps, dtype=float).reshape(lat.shape[0], 3)
    speed = np.sqrt(np.nansum(vel * vel, axis=1))  # a component not given (NaN) left out
    bad = (
        np.abs(lat) > 90.0,
        np.abs(lon) > 180.0,
        (alt < FIX_ALT_RANGE_M[0]) | (alt > FIX_ALT_RANGE_M[1]),
        speed > FIX_MAX_SPEED_MPS,
    )
    out = np.full(lat.shape[0], -1)
    for k in range(len(bad) - 1, -1, -1):
        out[bad[k]] = k
    return out


@dataclass(frozen=True)
class GpsFixes:
    """A sequence of M GPS fixes (see the module docstring for meanings).

    Attributes
    ----------
    t_s, lat_deg, lon_deg, alt_m, h_acc_m, v_acc_m, vel_acc_mps, latency_s : arrays (M,)
    vel_ned_mps : array (M, 3)
    """

    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    vel_ned_mps: np.ndarray
    h_acc_m: np.ndarray
    v_acc_m: np.ndarray
    vel_acc_mps: np.ndarray
    latency_s: np.ndarray

    def __post_init__(self) -> None:
        shapes = {k: () for k in ("t_s", "lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m")}
        shapes.update({"vel_ned_mps": (3,), "vel_acc_mps": (), "latency_s": ()})
        freeze_fields(self, shapes)
        m = self.t_s.shape[0]
        for k in shapes:
            if getattr(self, k).shape[0] != m:
                raise ValueError(f"GpsFixes.{k} has {getattr(self, k).shape[0]} rows, t_s has {m}")
        if m:
            check_time_axis(self.t_s)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def select(self, keep: np.ndarray) -> GpsFixes:
        """The fixes where the boolean mask ``keep`` (M,) is true, in order."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != self.t_s.shape:
            raise ValueError(f"mask has shape {keep.shape}, expected {self.t_s.shape}")
        return GpsFixes(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})
