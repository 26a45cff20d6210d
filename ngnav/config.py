"""The one TOML loader: typed records from scenario and run files, errors that name file and key.

Scenarios ship in ``ngnav/sim/scenarios/*.toml``; :func:`read_scenario_data` takes a
shipped name (``tilt-table``) or a path. Overrides (``section.key=value``, as the
CLI's ``--set``) are applied before validation; :func:`build_section` turns a table
into its record, naming an unknown key's nearest known one.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, get_type_hints


@dataclass(frozen=True)
class RunSection:
    """``[run]`` of a scenario: the Monte Carlo seed and the array's sample rate, Hz."""

    seed: int
    rate_hz: float

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise ValueError(f"run.seed must be 0 or more, got {self.seed}")
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"run.rate_hz must be positive, got {self.rate_hz}")


@dataclass(frozen=True)
class ArraySection:
    """``[array]`` of a scenario: the nominal layout's name and its lever arm, m."""

    layout: str = "nine-cube"
    lever_arm_m: float = 0.1


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


def build_section(cls: type, table: Any, section: str, source: str) -> Any:
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
        msg = str(exc)  # a record's own message may name the key as section.key already
        where = "" if msg.startswith(f"{section}.") else f"[{section}] "
        raise ValueError(f"{source}: {where}{msg}") from None


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
    root = resources.files("ngnav.sim") / "scenarios"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def read_toml_file(path: str | Path, missing: str) -> dict:
    """Parsed TOML of a file; ValueError ``missing`` if it does not exist, or one line
    naming the file if it is not valid TOML."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(missing) from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{p}: not valid TOML: {exc}") from None


def read_scenario_data(name_or_path: str) -> tuple[dict, str]:
    """Parsed TOML of a shipped scenario name or a file path, and its source label."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise ValueError(f"scenario file {path} does not exist")
        text, source = path.read_text(encoding="utf-8"), str(path)
    else:
        res = resources.files("ngnav.sim") / "scenarios" / f"{name_or_path}.toml"
        if not res.is_file():
            raise ValueError(
                f"unknown scenario {name_or_path!r}; shipped: {', '.join(shipped_scenarios())}"
            )
        text, source = res.read_text(encoding="utf-8"), f"scenarios/{name_or_path}.toml"
    try:
        return tomllib.loads(text), source
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{source}: not valid TOML: {exc}") from None
