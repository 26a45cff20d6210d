"""What a user may set about the filter, in four groups, each setting with its unit and default.

``config.toml`` (and a flight scenario) holds them as the sections ``[filter]``,
``[compensation]``, ``[vehicle]`` and ``[rest]``. Why each has its default, and
every behaviour that is fixed rather than set, is in ``docs/design.md``.

Files written before the settings were grouped keep reading: :func:`migrate_legacy`
moves a key of the old flat ``[filter]`` table to its group, and drops one whose
behaviour is now fixed when the file gives that fixed value (any other value is
refused with the key named).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: Compensation choices of the filter's front end (``oracle``: simulations only).
COMPENSATIONS: tuple[str, ...] = ("gm11", "none", "line", "last", "oracle")
#: Vehicle kinds: ``free`` has no motion constraint; ``fixed-wing`` adds the calm-air
#: sideslip and angle-of-attack models with the airframe's lift law.
VEHICLES: tuple[str, ...] = ("free", "fixed-wing")


def _number(where: str, v: float, lo: float, hi: float) -> None:
    if not (np.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"{where} must be a number in [{lo:g}, {hi:g}], got {v}")


@dataclass(frozen=True)
class FilterSettings:
    """``[filter]``: the estimator's own rates.

    Attributes
    ----------
    rate_hz : float
        Filter steps per second, Hz (default 100): the array's samples are
        propagated one by one and the covariance once per step.
    fusion_lag_s : float
        How far the fusion horizon trails the newest array sample on a stream, s
        (default 0.1): a GPS fix that arrives within it is fused at its time of
        validity, as offline; estimates trail the newest sample by it.
    """

    rate_hz: float = 100.0
    fusion_lag_s: float = 0.1

    def __post_init__(self) -> None:
        _number("filter.rate_hz", self.rate_hz, 1e-3, 1e5)
        _number("filter.fusion_lag_s", self.fusion_lag_s, 0.0, 10.0)


@dataclass(frozen=True)
class CompensationSettings:
    """``[compensation]``: how the array's mounting errors are taken out (paper eq. 22).

    Attributes
    ----------
    method : str
        ``gm11`` (default; the paper's grey forecast), ``line``, ``last``, ``none``,
        or ``oracle`` (the true geometry; simulations only).
    forecast_correction : bool
        Take the forecast's measured error out of the nominal state after each block
        (default false). Without it the error is counted in the rate and velocity noise
        instead, as two blocks' worth (``filters.forecast.FORECAST_ERROR_PERSISTENCE``).
    """

    method: str = "gm11"
    forecast_correction: bool = False

    def __post_init__(self) -> None:
        if self.method not in COMPENSATIONS:
            raise ValueError(
                f"compensation.method must be one of {COMPENSATIONS}, got {self.method!r}"
            )


@dataclass(frozen=True)
class VehicleSettings:
    """``[vehicle]``: what the vehicle is, and for a fixed-wing its airframe.

    Attributes
    ----------
    kind : str
        ``free`` (default: no motion constraint, any body: a tumbling munition, a
        multirotor, a test rig) or ``fixed-wing`` (the calm-air sideslip and
        angle-of-attack models, at 5 Hz above 5 m/s, and the angle of attack as a state).
    lift_k_m : float
        Fixed-wing: the lift law's ``K = 2 (m/S) / (rho C_La)``, m, in
        ``alpha = w(V) (alpha_0 + K n_w / V^2)`` (default 0: no law, the angle of
        attack is a state of its own).
    lift_k_sigma_m : float
        Fixed-wing: 1-sigma of ``K``, m, carried as a constant state (default 0: exact).
    liftoff_speed_mps : float
        Fixed-wing: below 0.8 times this speed the vehicle is on its wheels (no angle
        of attack), m/s (default 0: always flying).
    aoa_walk_deg_rts : float
        Fixed-wing: random walk of the law's offset ``alpha_0``, deg/sqrt(s)
        (default 0: a constant of the airframe).
    body_velocity_error : bool
        Fixed-wing: take the velocity error in the body frame, which makes the
        vehicle models exactly linear (default false).
    remainder_updates, attitude_remainder_updates, coast_remainder_updates : float
        Fixed-wing: how many consecutive 5 Hz updates share one value of the vehicle
        models' second-order remainder (whole, its attitude part, and the whole in a
        coast and after a hand-over), >= 1 (defaults 4, 40, 40).
    """

    kind: str = "free"
    lift_k_m: float = 0.0
    lift_k_sigma_m: float = 0.0
    liftoff_speed_mps: float = 0.0
    aoa_walk_deg_rts: float = 0.0
    body_velocity_error: bool = False
    remainder_updates: float = 4.0
    attitude_remainder_updates: float = 40.0
    coast_remainder_updates: float = 40.0

    def __post_init__(self) -> None:
        if self.kind not in VEHICLES:
            raise ValueError(f"vehicle.kind must be one of {VEHICLES}, got {self.kind!r}")
        for name in ("lift_k_m", "lift_k_sigma_m", "liftoff_speed_mps"):
            _number(f"vehicle.{name}", getattr(self, name), 0.0, 1000.0)
        _number("vehicle.aoa_walk_deg_rts", self.aoa_walk_deg_rts, 0.0, 30.0)
        for name in ("remainder_updates", "attitude_remainder_updates", "coast_remainder_updates"):
            _number(f"vehicle.{name}", getattr(self, name), 1.0, 1e4)
        if self.kind != "fixed-wing":
            airframe = ("lift_k_m", "lift_k_sigma_m", "liftoff_speed_mps", "aoa_walk_deg_rts")
            for name in airframe:
                if getattr(self, name) != 0.0:
                    raise ValueError(
                        f"vehicle.{name} describes a fixed-wing airframe; "
                        f"vehicle.kind is {self.kind!r}"
                    )
            if self.body_velocity_error:
                raise ValueError(
                    "vehicle.body_velocity_error linearises the fixed-wing models; "
                    f"vehicle.kind is {self.kind!r}"
                )

    @property
    def fixed_wing(self) -> bool:
        """True when the fixed-wing models apply."""
        return self.kind == "fixed-wing"


@dataclass(frozen=True)
class RestSettings:
    """``[rest]``: the zero-rate update while the vehicle is detected at rest.

    Attributes
    ----------
    rate_sigma_dps : float
        1-sigma of the body rate at rest per axis, deg/s (the vehicle's rocking on its
        mounts); 0 (default) switches the update off. Leave it off for a vehicle that
        spins at constant rate without angular acceleration (a multirotor yawing in
        hover reads as rest to the array).
    """

    rate_sigma_dps: float = 0.0

    def __post_init__(self) -> None:
        _number("rest.rate_sigma_dps", self.rate_sigma_dps, 0.0, 10.0)


#: The old flat ``[filter]`` keys that moved: old key -> (section, key).
MOVED: dict[str, tuple[str, str]] = {
    "compensation": ("compensation", "method"),
    "forecast_correction": ("compensation", "forecast_correction"),
    "aoa_lift_k_m": ("vehicle", "lift_k_m"),
    "aoa_lift_k_sigma_m": ("vehicle", "lift_k_sigma_m"),
    "liftoff_speed_mps": ("vehicle", "liftoff_speed_mps"),
    "aoa_rw_deg_rts": ("vehicle", "aoa_walk_deg_rts"),
    "body_velocity_error": ("vehicle", "body_velocity_error"),
    "remainder_updates": ("vehicle", "remainder_updates"),
    "attitude_remainder_updates": ("vehicle", "attitude_remainder_updates"),
    "coast_remainder_updates": ("vehicle", "coast_remainder_updates"),
    "rest_rate_sigma_dps": ("rest", "rate_sigma_dps"),
}
#: The old ``[filter]`` keys whose behaviour is now fixed, with that fixed value; a
#: fixed-wing's are checked only where the old file had the vehicle models on.
FIXED: dict[str, Any] = {
    "window": 5,
    "gate_probability": 0.9999,
    "rate_range_dps": 200.0,
    "gps_gap_reset_s": 5.0,
    "hold_wdot_sigma_rps2": 2.0,
    "hold_force_sigma_mps2": 3.0,
    "coast_after_s": 1.0,
    "vehicle_model_rate_hz": 5.0,
    "remainder_off_constraint": False,
    "position_consider": False,
    "remainder_consider": False,
    # the sensor positions are states whenever [calibration] position_sigma_m > 0
    "position_states": True,
}
FIXED_WING: dict[str, Any] = {
    "sideslip_sigma_deg": 3e-6,
    "aoa_sigma_deg": 3e-6,
    "aoa_prior_deg": -1.5,
    "aoa_prior_sigma_deg": 1.0,
    "count_by_prior_weight": True,
}
#: Their values when the vehicle models were off (a free vehicle).
FREE: dict[str, Any] = {
    "sideslip_sigma_deg": 0.0,
    "aoa_sigma_deg": 0.0,
    "aoa_prior_deg": 0.0,
    "aoa_prior_sigma_deg": 0.0,
    "count_by_prior_weight": False,
}


def retired_key_message(key: str) -> str | None:
    """What became of an old ``[filter]`` key (moved or fixed), or None for any other."""
    if key in MOVED:
        section, new = MOVED[key]
        return f"filter.{key} is now {section}.{new}"
    if key == "position_states":
        return (
            "filter.position_states is no longer a setting: a declared "
            "[calibration] position_sigma_m is always carried as states"
        )
    if key in FIXED:
        return f"filter.{key} is no longer a setting; it is {FIXED[key]!r}"
    if key == "forecast_error_persistence":
        return (
            "filter.forecast_error_persistence is no longer a setting: 1 with "
            "compensation.forecast_correction, 2 without"
        )
    if key in FIXED_WING:
        return (
            f'filter.{key} is no longer a setting: vehicle.kind = "fixed-wing" has '
            f"{FIXED_WING[key]!r}, a free vehicle none"
        )
    return None


def migrate_legacy(data: dict, source: str) -> dict:
    """A parsed config whose flat ``[filter]`` predates the groups, in today's sections.

    Returns ``data`` itself when there is nothing to move. A moved key is refused
    when its new place is also given; the forecast's error persistence must be the one
    its correction now implies (1 with it, 2 without); a key whose behaviour is now fixed must give
    that value (an old default or a shipped scenario's), or the file is refused
    naming the key and the value that holds now.
    """
    old = data.get("filter")
    if not isinstance(old, dict) or not (set(old) & (set(MOVED) | set(FIXED) | set(FREE))):
        return data
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    flt = out["filter"]
    for key, (section, new) in MOVED.items():
        if key in flt:
            table = out.setdefault(section, {})
            if new in table:
                raise ValueError(f"{source}: filter.{key} and {section}.{new} both given")
            table[new] = flt.pop(key)
    if "forecast_error_persistence" in flt:
        persistence = flt.pop("forecast_error_persistence")
        corrected = out.get("compensation", {}).get("forecast_correction", False)
        if persistence != (1.0 if corrected else 2.0):
            raise ValueError(
                f"{source}: filter.forecast_error_persistence is no longer a setting; it is "
                f"{1.0 if corrected else 2.0} with forecast_correction = {str(corrected).lower()}"
            )
    for key, fixed in FIXED.items():
        if key in flt and flt.pop(key) != fixed:
            raise ValueError(f"{source}: {retired_key_message(key)}")
    models = [k for k in FREE if k in flt]
    if models:
        given = {k: flt.pop(k) for k in models}
        wing = given.get("sideslip_sigma_deg", 0.0) > 0 or given.get("aoa_sigma_deg", 0.0) > 0
        want = FIXED_WING if wing else FREE
        for key, value in given.items():
            if value != want[key]:
                raise ValueError(
                    f"{source}: filter.{key} is no longer a setting; "
                    f"a {'fixed-wing' if wing else 'free'} vehicle has {want[key]!r}"
                )
        vehicle = out.setdefault("vehicle", {})
        vehicle.setdefault("kind", "fixed-wing" if wing else "free")
    return out
