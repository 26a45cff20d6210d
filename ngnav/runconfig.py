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
                   scale_sigma = [...] or x           # N, 1-sigma of scale (default 0)
                   axis_error_sigma_rad = [[..]] or x # N x 2, 1-sigma of the axis angles
                                                      # (default 0); either > 0: the
                                                      # filter carries their effect
    [sensor]       noise_sigma_mps2 = [...] or x      # per sample, m/s^2
                   turn_on_bias_mps2 = [...] or x     # 1-sigma, m/s^2
                   bias_rw_mps2_rts = [...] or x      # m/s^2 per root s
                   range_mps2 = x                     # saturation level
    [reference]    lat_deg, lon_deg, alt_m            # NED origin, WGS-84
    [gps]          antenna_b_m = [x, y, z]            # FRD, m
    [initial]      alignment = "static"|"config", static_s, roll_deg, pitch_deg,
                   yaw_deg, tilt_sigma_deg, heading_source = "config"|"gps",
                   heading_sigma_deg, rate_dps = [x, y, z], rate_sigma_dps
    [filter]       rate_hz, fusion_lag_s
    [compensation] method, forecast_correction
    [vehicle]      kind = "free"|"fixed-wing", lift_k_m, lift_k_sigma_m, liftoff_speed_mps,
                   aoa_walk_deg_rts, body_velocity_error, remainder_updates,
                   attitude_remainder_updates, coast_remainder_updates
    [rest]         rate_sigma_dps
                   (the last four optional; each setting's unit and default in
                   :mod:`ngnav.settings`)
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ngnav.config import read_toml_file
from ngnav.layout import ArrayLayout
from ngnav.mounting import MountingErrors
from ngnav.settings import (
    COMPENSATIONS,
    CompensationSettings,
    FilterSettings,
    RestSettings,
    VehicleSettings,
    migrate_legacy,
)

__all__ = [
    "COMPENSATIONS",
    "CompensationSettings",
    "FilterSettings",
    "InitialSettings",
    "RestSettings",
    "RunConfig",
    "VehicleSettings",
    "read_run_config",
    "read_run_config_text",
    "run_config_text",
    "write_run_config",
]


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
    scale_sigma: np.ndarray | float = 0.0
    axis_error_sigma_rad: np.ndarray | float = 0.0
    initial: InitialSettings = field(default_factory=InitialSettings)
    filter: FilterSettings = field(default_factory=FilterSettings)
    compensation: CompensationSettings = field(default_factory=CompensationSettings)
    vehicle: VehicleSettings = field(default_factory=VehicleSettings)
    rest: RestSettings = field(default_factory=RestSettings)

    def __post_init__(self) -> None:
        n = self.layout.n_sensors
        for name in (
            "scale",
            "offset_mps2",
            "noise_sigma_mps2",
            "turn_on_bias_mps2",
            "bias_rw_mps2_rts",
            "scale_sigma",
        ):
            a = np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (n,)).copy()
            if not np.all(np.isfinite(a)):
                raise ValueError(f"config: {name} must be finite")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        try:
            sa = np.asarray(self.axis_error_sigma_rad, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(
                f"config: calibration.axis_error_sigma_rad must be numbers, "
                f"got {self.axis_error_sigma_rad!r}"
            ) from None
        if sa.ndim:
            if sa.shape != (n, 2):
                raise ValueError(
                    f"config: calibration.axis_error_sigma_rad must have shape ({n}, 2) or be "
                    f"one number, got {sa.shape}"
                )
            sa = sa.copy()
        else:
            sa = np.full((n, 2), float(sa))
        if not np.all(np.isfinite(sa)) or np.any(sa < 0) or np.any(self.scale_sigma < 0):
            raise ValueError("config: calibration sigmas must be finite and >= 0")
        sa.setflags(write=False)
        object.__setattr__(self, "axis_error_sigma_rad", sa)
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

    @property
    def carries_calibration_error(self) -> bool:
        """Whether the calibration declares a scale or axis 1-sigma (the filter then
        carries the residual's effect, :class:`filters.state.StateLayout` ``cal``)."""
        return bool(np.any(self.scale_sigma > 0) or np.any(self.axis_error_sigma_rad > 0))


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


#: The keys of the sections read here by hand (the settings' sections check their own):
#: anything else in a ``config.toml`` is a misspelling, refused with the nearest name
#: (a misspelt ``[gps]`` silently put the antenna at the array).
_HARDWARE_KEYS = {
    "array": ("positions_b_m", "axes_b", "name", "lever_arm_m"),
    "calibration": (
        "position_error_b_m",
        "axis_error_rad",
        "scale",
        "offset_mps2",
        "position_sigma_m",
        "scale_sigma",
        "axis_error_sigma_rad",
    ),
    "sensor": ("noise_sigma_mps2", "turn_on_bias_mps2", "bias_rw_mps2_rts", "range_mps2"),
    "reference": ("lat_deg", "lon_deg", "alt_m"),
    "gps": ("antenna_b_m",),
}
_SETTINGS_SECTIONS = ("initial", "filter", "compensation", "vehicle", "rest")


def _refuse_unknown(data: dict, where: str) -> None:
    """An unknown section or hardware key: one error naming the nearest known one."""
    from ngnav.config import unknown_name

    sections = (*_HARDWARE_KEYS, *_SETTINGS_SECTIONS)
    for name, table in data.items():
        if not isinstance(table, dict):
            what = f"[{name}] must be a table" if name in sections else f"unknown key {name}"
            raise ValueError(f"{where}: {what}")
        if name not in sections:
            raise ValueError(
                f"{where}: {unknown_name('section', f'[{name}]', (f'[{s}]' for s in sections))}"
            )
        keys = _HARDWARE_KEYS.get(name)
        if keys is None:
            continue
        extra = sorted(set(table) - set(keys))
        if extra:
            known = (f"{name}.{k}" for k in keys)
            raise ValueError(f"{where}: {unknown_name('key', f'{name}.{extra[0]}', known)}")


def _settings(cls: type, table: Any, section: str, source: str) -> Any:
    from ngnav.config import build_section

    return build_section(cls, table if table is not None else {}, section, source)


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
    data = migrate_legacy(data, p)
    _refuse_unknown(data, p)
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
            scale_sigma=_vector(cal, "scale_sigma", n, f"{p} [calibration]", 0.0),
            axis_error_sigma_rad=cal.get("axis_error_sigma_rad", 0.0),
            initial=_settings(InitialSettings, data.get("initial"), "initial", p),
            filter=_settings(FilterSettings, data.get("filter"), "filter", p),
            compensation=_settings(
                CompensationSettings, data.get("compensation"), "compensation", p
            ),
            vehicle=_settings(VehicleSettings, data.get("vehicle"), "vehicle", p),
            rest=_settings(RestSettings, data.get("rest"), "rest", p),
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
        "compensation": asdict(cfg.compensation),
        "vehicle": asdict(cfg.vehicle),
        "rest": asdict(cfg.rest),
    }
    if cfg.carries_calibration_error:
        sections["calibration"]["scale_sigma"] = cfg.scale_sigma
        sections["calibration"]["axis_error_sigma_rad"] = cfg.axis_error_sigma_rad
    if cfg.layout.lever_arm_m is not None:
        sections["array"]["lever_arm_m"] = float(cfg.layout.lever_arm_m)
    for name, table in sections.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {_fmt(v)}" for k, v in table.items()]
        lines.append("")
    return "\n".join(lines)


@dataclass(frozen=True)
class ArrayConfig:
    """What a bench calibration needs of a ``config.toml``: ``[array]``, ``[sensor]`` and,
    when given, the drawings' ``[calibration] position_error_b_m`` and ``position_sigma_m``
    (carried into the calibration it writes; at rest positions do not show).
    """

    layout: ArrayLayout
    noise_sigma_mps2: np.ndarray
    bias_rw_mps2_rts: np.ndarray
    range_mps2: float
    position_error_b_m: np.ndarray
    position_sigma_m: float


def read_array_config(path: str | Path) -> ArrayConfig:
    """Read the array and sensor sections of a ``config.toml`` (no other section needed)."""
    p = Path(path)
    data = read_toml_file(p, f"{p}: no such file")
    _refuse_unknown(data, str(p))
    for section in ("array", "sensor"):
        if not isinstance(data.get(section), dict):
            raise ValueError(f"{p}: missing section [{section}]")
    arr, sen, cal = data["array"], data["sensor"], data.get("calibration", {})
    pos = _matrix(arr, "positions_b_m", (None, 3), f"{p} [array]")
    n = pos.shape[0]
    layout = ArrayLayout(
        pos,
        _matrix(arr, "axes_b", (n, 3), f"{p} [array]"),
        name=str(arr.get("name", "config")),
        lever_arm_m=arr.get("lever_arm_m"),
    )
    if "range_mps2" not in sen:
        raise ValueError(f"{p} [sensor]: missing key range_mps2")
    dr = (
        _matrix(cal, "position_error_b_m", (n, 3), f"{p} [calibration]")
        if "position_error_b_m" in cal
        else np.zeros((n, 3))
    )
    return ArrayConfig(
        layout=layout,
        noise_sigma_mps2=_vector(sen, "noise_sigma_mps2", n, f"{p} [sensor]"),
        bias_rw_mps2_rts=_vector(sen, "bias_rw_mps2_rts", n, f"{p} [sensor]", 0.0),
        range_mps2=float(sen["range_mps2"]),
        position_error_b_m=dr,
        position_sigma_m=float(cal.get("position_sigma_m", 0.0)),
    )
