"""Typed scenario records read from TOML, with errors that name file and key.

Scenarios ship in ``ngnav/scenarios/*.toml``; :func:`load_scenario` takes a
shipped name (``tilt-table``) or a path. Overrides (``section.key=value``, as
the CLI's ``--set``) are applied before validation.
"""

from __future__ import annotations

import dataclasses
import difflib
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, get_type_hints

from ngnav.sensors import AccelerometerModel


@dataclass(frozen=True)
class RunConfig:
    seed: int
    rate_hz: float


@dataclass(frozen=True)
class ArrayConfig:
    layout: str
    lever_arm_m: float


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
    run: RunConfig
    array: ArrayConfig
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
    "run": RunConfig,
    "array": ArrayConfig,
    "sensor": AccelerometerModel,
    "mounting": MountingConfig,
    "calibration": CalibrationConfig,
    "test": TestConfig,
    "compensation": CompensationConfig,
}


def _coerce(value: Any, kind: Any, where: str) -> Any:
    text = str(kind)
    if kind is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true/false, got {value!r}")
        return value
    if kind is int or text == "int | None":
        if value is None and "None" in text:
            return None
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {value!r}")
        return value
    if kind is float or text == "float | None":
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: expected a string, got {value!r}")
        return value
    if text.startswith("tuple[float"):
        if not isinstance(value, list) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value
        ):
            raise ValueError(f"{where}: expected a list of numbers, got {value!r}")
        return tuple(float(v) for v in value)
    raise TypeError(f"{where}: unsupported field type {kind}")


def unknown_name(what: str, name: str, known: Iterable[str]) -> str:
    """``unknown key filter.rate_hzz (did you mean filter.rate_hz?)``: the nearest known name."""
    near = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f"unknown {what} {name}" + (f" (did you mean {near[0]}?)" if near else "")


def _build(cls: type, table: Any, section: str, source: str) -> Any:
    if not isinstance(table, dict):
        raise ValueError(f"{source}: [{section}] must be a table")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        if section == "filter":
            from ngnav.settings import retired_key_message

            msg = retired_key_message(unknown[0])
            if msg:
                raise ValueError(f"{source}: {msg}")
        known = (f"{section}.{k}" for k in fields)
        raise ValueError(f"{source}: {unknown_name('key', f'{section}.{unknown[0]}', known)}")
    kwargs = {}
    for name, f in fields.items():
        if name not in table:
            if f.default is dataclasses.MISSING:
                raise ValueError(f"{source}: missing key {section}.{name}")
            continue
        kwargs[name] = _coerce(table[name], hints[name], f"{source}: {section}.{name}")
    try:
        return cls(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{source}: [{section}] {exc}") from None


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text  # a bare word is a string


def apply_overrides(data: dict, overrides: list[str], source: str) -> dict:
    """Apply ``section.key=value`` overrides (TOML values) to parsed scenario data."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for item in overrides:
        key, sep, value = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise ValueError(f"override {item!r} must look like section.key=value")
        if section not in out or not isinstance(out[section], dict):
            tables = [k for k, v in out.items() if isinstance(v, dict)]
            raise ValueError(
                f"{source}: override {item!r} names an {unknown_name('section', section, tables)}"
            )
        out[section][name] = _parse_value(value.strip())
    return out


def shipped_scenarios() -> list[str]:
    """Names of the scenarios shipped with the package."""
    root = resources.files("ngnav") / "scenarios"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def read_scenario_data(name_or_path: str) -> tuple[dict, str]:
    """Parsed TOML of a shipped scenario name or a file path, and its source label."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise ValueError(f"scenario file {path} does not exist")
        text, source = path.read_text(encoding="utf-8"), str(path)
    else:
        res = resources.files("ngnav") / "scenarios" / f"{name_or_path}.toml"
        if not res.is_file():
            raise ValueError(
                f"unknown scenario {name_or_path!r}; shipped: {', '.join(shipped_scenarios())}"
            )
        text, source = res.read_text(encoding="utf-8"), f"scenarios/{name_or_path}.toml"
    try:
        return tomllib.loads(text), source
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{source}: not valid TOML: {exc}") from None


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
        parts[section] = _build(cls, data[section], section, source)
    return TiltTableScenario(name=source, **parts)
