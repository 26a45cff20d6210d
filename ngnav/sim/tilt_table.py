"""The paper's indexing-head scenario (``scenarios/tilt-table.toml``) as typed records."""

from __future__ import annotations

from dataclasses import dataclass

from ngnav.config import (
    ArraySection,
    RunSection,
    apply_overrides,
    build_section,
    read_scenario_data,
)
from ngnav.sim.sensors import AccelerometerModel


@dataclass(frozen=True)
class MountingConfig:
    outward_offset_m: float
    position_scatter_m: float
    axis_error_deg: float


@dataclass(frozen=True)
class CalibrationConfig:
    samples_per_position: int
    method: str


@dataclass(frozen=True)
class TestConfig:
    plane: str
    rest_before_s: float
    turn_duration_s: float
    rest_after_s: float
    pivot_b_m: tuple[float, float, float]


@dataclass(frozen=True)
class CompensationConfig:
    window: int
    grey_shift: str
    rate_range_dps: float


@dataclass(frozen=True)
class TiltTableScenario:
    """The paper's indexing-head experiment (see ``scenarios/tilt-table.toml``)."""

    name: str
    run: RunSection
    array: ArraySection
    sensor: AccelerometerModel
    mounting: MountingConfig
    calibration: CalibrationConfig
    test: TestConfig
    compensation: CompensationConfig

    def __post_init__(self) -> None:
        where = f"scenario {self.name!r}"
        if self.test.plane not in ("horizontal", "vertical"):
            raise ValueError(f"{where}: test.plane must be 'horizontal' or 'vertical'")
        if self.calibration.method not in ("multiposition", "eq27"):
            raise ValueError(f"{where}: calibration.method must be 'multiposition' or 'eq27'")
        if self.compensation.grey_shift not in ("range", "auto"):
            raise ValueError(f"{where}: compensation.grey_shift must be 'range' or 'auto'")
        if self.compensation.rate_range_dps <= 0:
            raise ValueError(f"{where}: compensation.rate_range_dps must be positive")
        if self.compensation.window < 4:
            raise ValueError(f"{where}: compensation.window must be >= 4 (GM(1,1))")
        if self.calibration.samples_per_position < 1:
            raise ValueError(f"{where}: calibration.samples_per_position must be >= 1")
        for key in ("rest_before_s", "turn_duration_s", "rest_after_s"):
            if getattr(self.test, key) < 0 or (
                key == "turn_duration_s" and self.test.turn_duration_s == 0
            ):
                raise ValueError(f"{where}: test.{key} must be positive")
        if self.test.rest_before_s * self.run.rate_hz < 1:
            raise ValueError(f"{where}: test.rest_before_s must hold at least one sample")


_SECTIONS = {
    "run": RunSection,
    "array": ArraySection,
    "sensor": AccelerometerModel,
    "mounting": MountingConfig,
    "calibration": CalibrationConfig,
    "test": TestConfig,
    "compensation": CompensationConfig,
}


def load_tilt_table(
    name_or_path: str = "tilt-table", overrides: list[str] | None = None
) -> TiltTableScenario:
    """Load the indexing-head scenario, applying ``section.key=value`` overrides."""
    data, source = read_scenario_data(name_or_path)
    data = apply_overrides(data, overrides or [], source)
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise ValueError(f"{source}: unknown section [{unknown[0]}]")
    parts = {}
    for section, cls in _SECTIONS.items():
        if section not in data:
            raise ValueError(f"{source}: missing section [{section}]")
        parts[section] = build_section(cls, data[section], section, source)
    return TiltTableScenario(name=source, **parts)
