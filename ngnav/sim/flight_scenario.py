"""Flight scenarios: typed records read from the shipped TOML files.

A flight scenario names the array, the sensor preset, the mounting errors and
their calibration, the GPS receiver, the reference point, how the filter is
initialised, and the flight itself as a list of legs. Each leg starts by
moving bank, pitch (of the flight path), speed, yaw rate and angle of attack
to its targets with a minimum-jerk ramp of ``ramp_s`` and holds them to the
end of the leg; a key a leg leaves out keeps its previous value.
``[flight] initial_speed_mps``, ``initial_aoa_deg`` and ``initial_pitch_deg`` give
the values at t = 0 (all 0 by default: at rest, level, body along the velocity). A
leg's ``spin_rate_dps`` spins the body about its own x axis (a projectile). Instead of
scheduling the angle of attack, ``[flight] lift = { alpha0_deg, k_m,
liftoff_speed_mps }`` makes it the one the lift law asks for
(:class:`ngnav.sim.flight.LiftLaw`): the aircraft type's law. ``[flight] lift_scatter
= { alpha0_deg, k_m }`` gives how one aircraft of the type differs from it (1-sigma);
each simulated run then flies its own, drawn from its run's generator.
``[flight] rocking_rate_dps`` makes the body rock (1-sigma rate per axis, white at the
array's rate; :mod:`ngnav.sim.rocking`): a bench's or a waiting vehicle's micro-motion,
which the zero-rate update's sigma at rest (``rest.rate_sigma_dps``) declares.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ngnav.config import (
    ArraySection,
    RunSection,
    apply_overrides,
    build_section,
    read_scenario_data,
)
from ngnav.layout import layout_by_name
from ngnav.settings import (
    CompensationSettings,
    FilterSettings,
    RestSettings,
    VehicleSettings,
    migrate_legacy,
)
from ngnav.sim.faults import ChannelFault, parse_faults
from ngnav.sim.flight import FlightPlan, LiftLaw, Profile, Transition
from ngnav.sim.sensors import PRESET_NAMES, AccelerometerSpec, sensor_preset


@dataclass(frozen=True)
class SensorChoice:
    preset: str
    noise_density_ug_rthz: float | None = None
    turn_on_bias_mg: float | None = None
    bias_rw_ug_rts: float | None = None
    scale_error: float | None = None
    range_g: float | None = None

    def spec(self) -> AccelerometerSpec:
        """The preset with any overridden fields."""
        if self.preset not in PRESET_NAMES:
            raise ValueError(f"unknown sensor preset {self.preset!r}; presets: {PRESET_NAMES}")
        base = sensor_preset(self.preset)
        changes = {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name != "preset" and getattr(self, f.name) is not None
        }
        return dataclasses.replace(base, **changes) if changes else base


@dataclass(frozen=True)
class FlightMountingConfig:
    outward_offset_m: float = 0.006
    position_scatter_m: float = 0.0005
    axis_error_deg: float = 0.5
    calibration_samples: int = 2000
    #: Declare the bench calibration's scale and axis 1-sigmas in ``config.toml`` (the
    #: filter then carries their residual as states): what a vehicle whose load reaches
    #: tens of g needs; at a few g their effect is below the bias walk.
    declare_calibration_sigmas: bool = False


@dataclass(frozen=True)
class GpsConfig:
    rate_hz: float = 5.0
    h_acc_m: float = 1.5
    v_acc_m: float = 3.0
    vel_acc_mps: float = 0.1
    latency_s: float = 0.0
    antenna_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    outage_start_s: float = -1.0
    outage_s: float = 0.0
    glitch_times_s: tuple[float, ...] = ()
    glitch_m: float = 50.0


@dataclass(frozen=True)
class ReferenceConfig:
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class InitialConfig:
    heading_deg: float = 0.0
    alignment: str = "static"
    static_s: float = 5.0
    tilt_sigma_deg: float = 2.0
    heading_source: str = "config"
    heading_sigma_deg: float = 5.0
    rate_sigma_dps: float = 1.0

    def __post_init__(self) -> None:
        if self.alignment not in ("static", "config"):
            raise ValueError(f"alignment must be 'static' or 'config', got {self.alignment!r}")
        if self.heading_source not in ("config", "gps"):
            raise ValueError(
                f"heading_source must be 'config' or 'gps', got {self.heading_source!r}"
            )


@dataclass(frozen=True)
class Leg:
    duration_s: float
    ramp_s: float = 1.0
    bank_deg: float | None = None
    pitch_deg: float | None = None
    speed_mps: float | None = None
    yaw_rate_dps: float | None = None
    aoa_deg: float | None = None
    spin_rate_dps: float | None = None


@dataclass(frozen=True)
class FlightScenario:
    """A whole flight scenario (see the module docstring)."""

    name: str
    run: RunSection
    array: ArraySection
    sensor: SensorChoice
    mounting: FlightMountingConfig
    gps: GpsConfig
    reference: ReferenceConfig
    initial: InitialConfig
    filter: FilterSettings
    legs: tuple[Leg, ...]
    initial_speed_mps: float = 0.0
    initial_aoa_deg: float = 0.0
    initial_pitch_deg: float = 0.0
    compensation: CompensationSettings = dataclasses.field(default_factory=CompensationSettings)
    vehicle: VehicleSettings = dataclasses.field(default_factory=VehicleSettings)
    rest: RestSettings = dataclasses.field(default_factory=RestSettings)
    lift: LiftLaw | None = None
    #: 1-sigma of one aircraft's (alpha0 rad, K m) about the type's law, or None.
    lift_scatter: tuple[float, float] | None = None
    #: Channel faults the simulator injects (``[faults]``; :mod:`ngnav.sim.faults`).
    faults: tuple[ChannelFault, ...] = ()
    #: Times the filter is told its track is lost (``[faults] lose_track_at_s``, s): the
    #: recovery's validation (:mod:`filters.recovery`).
    lose_track_at_s: tuple[float, ...] = ()
    #: The body's rocking, 1-sigma rate per axis and array sample, deg/s (0: none).
    rocking_rate_dps: float = 0.0

    def plan(self) -> FlightPlan:
        """The flight's bank, pitch, speed, yaw-rate and angle-of-attack profiles."""
        aoa0 = float(np.deg2rad(self.initial_aoa_deg))
        pitch0 = float(np.deg2rad(self.initial_pitch_deg))
        current = {
            "bank": 0.0,
            "pitch": pitch0,
            "speed": self.initial_speed_mps,
            "yaw": 0.0,
            "aoa": aoa0,
            "spin": 0.0,
        }
        trans: dict[str, list[Transition]] = {k: [] for k in current}
        start = 0.0
        keys = {
            "bank": "bank_deg",
            "pitch": "pitch_deg",
            "speed": "speed_mps",
            "yaw": "yaw_rate_dps",
            "aoa": "aoa_deg",
            "spin": "spin_rate_dps",
        }
        for leg in self.legs:
            for k, attr in keys.items():
                target = getattr(leg, attr)
                if target is None:
                    continue
                value = target if k == "speed" else np.deg2rad(target)
                if value != current[k]:
                    trans[k].append(Transition(start, leg.ramp_s, value - current[k]))
                    current[k] = value
            start += leg.duration_s
        return FlightPlan(
            duration_s=start,
            bank=Profile(0.0, tuple(trans["bank"])),
            pitch=Profile(pitch0, tuple(trans["pitch"])),
            speed=Profile(self.initial_speed_mps, tuple(trans["speed"])),
            yaw_rate=Profile(0.0, tuple(trans["yaw"])),
            heading0_rad=float(np.deg2rad(self.initial.heading_deg)),
            aoa=Profile(aoa0, tuple(trans["aoa"])),
            lift=self.lift,
            spin_rate=Profile(0.0, tuple(trans["spin"])),
        )


_SECTIONS = {
    "run": RunSection,
    "array": ArraySection,
    "sensor": SensorChoice,
    "mounting": FlightMountingConfig,
    "gps": GpsConfig,
    "reference": ReferenceConfig,
    "initial": InitialConfig,
    "filter": FilterSettings,
}
#: Sections a scenario may leave out (their defaults apply).
_OPTIONAL_SECTIONS = {
    "compensation": CompensationSettings,
    "vehicle": VehicleSettings,
    "rest": RestSettings,
}


def _legs(value: Any, source: str) -> tuple[Leg, ...]:
    if not isinstance(value, list) or not value:
        raise ValueError(f"{source}: flight.legs must be a non-empty list of tables")
    legs = []
    for i, item in enumerate(value):
        leg = build_section(Leg, item, f"flight.legs[{i}]", source)
        if leg.duration_s <= 0 or not 0 < leg.ramp_s <= leg.duration_s:
            raise ValueError(
                f"{source}: flight.legs[{i}] needs duration_s > 0 and 0 < ramp_s <= duration_s"
            )
        legs.append(leg)
    return tuple(legs)


def load_flight(name_or_path: str, overrides: list[str] | None = None) -> FlightScenario:
    """Load a flight scenario (shipped name or path), applying ``section.key=value`` overrides."""
    data, source = read_scenario_data(name_or_path)
    data = migrate_legacy(data, source)
    for section in (*_OPTIONAL_SECTIONS, "faults"):
        data.setdefault(section, {})
    data = apply_overrides(data, overrides or [], source)
    known = set(_SECTIONS) | set(_OPTIONAL_SECTIONS) | {"flight", "faults"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{source}: unknown section [{unknown[0]}]")
    parts = {}
    for section, cls in _SECTIONS.items():
        if section not in data:
            raise ValueError(f"{source}: missing section [{section}]")
        parts[section] = build_section(cls, data[section], section, source)
    for section, cls in _OPTIONAL_SECTIONS.items():
        parts[section] = build_section(cls, data[section], section, source)
    flight = data.get("flight")
    if not isinstance(flight, dict) or "legs" not in flight:
        raise ValueError(f"{source}: missing [flight] with legs")
    starts = ("initial_speed_mps", "initial_aoa_deg", "initial_pitch_deg")
    extra = sorted(set(flight) - {"legs", "lift", "lift_scatter", "rocking_rate_dps", *starts})
    if extra:
        raise ValueError(f"{source}: unknown key flight.{extra[0]}")
    start_values = {}
    for key in starts:
        value = flight.get(key, 0.0)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{source}: flight.{key}: expected a number")
        start_values[key] = float(value)
    rocking = flight.get("rocking_rate_dps", 0.0)
    if isinstance(rocking, bool) or not isinstance(rocking, int | float) or not rocking >= 0:
        raise ValueError(f"{source}: flight.rocking_rate_dps: expected a number >= 0")
    legs = _legs(flight["legs"], source)
    for i, leg in enumerate(legs):
        if leg.aoa_deg is not None and not -30.0 < leg.aoa_deg < 30.0:
            raise ValueError(f"{source}: flight.legs[{i}].aoa_deg must be in (-30, 30) deg")
    lift = None
    if "lift" in flight:
        lift_keys = ("alpha0_deg", "k_m", "liftoff_speed_mps")
        table = flight["lift"]
        if not isinstance(table, dict) or set(table) != set(lift_keys):
            raise ValueError(f"{source}: flight.lift must be a table of exactly {lift_keys}")
        for key in lift_keys:
            if isinstance(table[key], bool) or not isinstance(table[key], int | float):
                raise ValueError(f"{source}: flight.lift.{key}: expected a number")
        try:
            lift = LiftLaw(
                float(np.deg2rad(table["alpha0_deg"])),
                float(table["k_m"]),
                float(table["liftoff_speed_mps"]),
            )
        except ValueError as exc:
            raise ValueError(f"{source}: flight.lift: {exc}") from None
        if start_values["initial_aoa_deg"] or any(leg.aoa_deg is not None for leg in legs):
            raise ValueError(f"{source}: flight.lift replaces aoa_deg and initial_aoa_deg")
    scatter = None
    if "lift_scatter" in flight:
        table = flight["lift_scatter"]
        if lift is None:
            raise ValueError(f"{source}: flight.lift_scatter needs flight.lift")
        if not isinstance(table, dict) or set(table) != {"alpha0_deg", "k_m"}:
            raise ValueError(f"{source}: flight.lift_scatter must be a table of alpha0_deg, k_m")
        vals = [table["alpha0_deg"], table["k_m"]]
        if any(isinstance(v, bool) or not isinstance(v, int | float) or v < 0 for v in vals):
            raise ValueError(f"{source}: flight.lift_scatter: expected numbers >= 0")
        scatter = (float(np.deg2rad(vals[0])), float(vals[1]))
    parts["sensor"].spec()  # validate the preset now, naming the file
    fault_table = dict(data["faults"]) if isinstance(data["faults"], dict) else data["faults"]
    losses = fault_table.pop("lose_track_at_s", []) if isinstance(fault_table, dict) else []
    if not isinstance(losses, list) or any(
        isinstance(v, bool) or not isinstance(v, int | float) or not v > 0 for v in losses
    ):
        raise ValueError(f"{source}: faults.lose_track_at_s must be a list of times > 0 s")
    faults = parse_faults(fault_table, source)
    n_channels = layout_by_name(parts["array"].layout, parts["array"].lever_arm_m).n_sensors
    for f in faults:
        if f.channel > n_channels:
            raise ValueError(
                f"{source}: a fault on channel {f.channel}: the {parts['array'].layout} has "
                f"{n_channels} channels"
            )
    return FlightScenario(
        name=source,
        legs=legs,
        **start_values,
        lift=lift,
        lift_scatter=scatter,
        faults=faults,
        lose_track_at_s=tuple(float(v) for v in sorted(losses)),
        rocking_rate_dps=float(rocking),
        **parts,
    )


def is_flight_scenario(name_or_path: str) -> bool:
    """True if the scenario file has a [flight] section (the tilt table has none)."""
    data, _ = read_scenario_data(name_or_path)
    return "flight" in data
