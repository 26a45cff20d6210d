"""The paper's indexing-head experiment (section 5), simulated end to end.

One simulated cube (nominal nine-sensor layout, real mounting errors, real
channel errors) is calibrated from static positions, then turned on an
indexing head by each of Table 1's 16 angles. Each turn's outputs go through
the same chain as the paper's: channel calibration (scale), a zero taken at
rest, the array solve, integration of the angular acceleration into rate and
of the rate into a quaternion; the angle read from it is compared with the
platform angle. The chain runs once per method: no compensation (``none``)
and the paper's closed-loop compensation with each predictor (``gm11``,
``last``, ``line``, ``oracle``).

Randomness: the cube's hardware (mounting and scale errors) and its
calibration come from ``default_rng([seed, 0])``; turn i from
``default_rng([seed, 1, i])``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from importlib import resources

import numpy as np

from ngnav.calibration import (
    MultiPositionCalibration,
    calibrate_multiposition,
    eq27_axis_error,
    eq27_positions,
    multiposition_directions,
)
from ngnav.compensation import compensate
from ngnav.conventions import G0_MPS2
from ngnav.frontend import ArraySolver
from ngnav.layout import ArrayLayout, kinematic_features, layout_by_name
from ngnav.mounting import MountingErrors
from ngnav.predictors import GreyPredictor, LastValuePredictor, LinePredictor, OraclePredictor
from ngnav.records import ArraySamples, FlightTruth
from ngnav.sim.sensors import AccelerometerModel, ChannelErrors
from ngnav.sim.tilt_table import TiltTableScenario
from ngnav.sim.turntable import fixed_axis_turn
from ngnav.strapdown import integrate_rate, rotation_angle_about

#: Methods in the order they are reported.
METHODS: tuple[str, ...] = ("none", "gm11", "last", "line", "oracle")


@dataclass(frozen=True)
class PaperTable:
    """Table 1 of the paper: platform, measured and compensated angles (16,), deg."""

    platform_deg: np.ndarray
    measured_deg: np.ndarray
    compensated_deg: np.ndarray


def load_paper_table() -> PaperTable:
    """Table 1 as shipped in ``ngnav/data/paper_table1.csv``."""
    text = (resources.files("ngnav") / "data" / "paper_table1.csv").read_text(encoding="utf-8")
    rows = list(csv.DictReader(text.splitlines()))
    col = {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}
    return PaperTable(col["platform_deg"], col["measured_deg"], col["compensated_deg"])


@dataclass(frozen=True)
class Hardware:
    """One simulated cube: what it really is, and what its maker knows of it."""

    nominal: ArrayLayout
    true_errors: MountingErrors
    channel_scale_error: np.ndarray
    #: Mounting errors the compensation uses: designed offsets + calibrated axes.
    known_errors: MountingErrors
    calibration: MultiPositionCalibration
    #: Per-channel scale the outputs are divided by (from the calibration used).
    calibrated_scale: np.ndarray


def outward_directions(layout: ArrayLayout) -> np.ndarray:
    """Unit vectors (N, 3) from the centre of the sensors' bounding box through each sensor."""
    r = layout.positions_b_m
    centre = 0.5 * (r.min(axis=0) + r.max(axis=0))
    d = r - centre
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def draw_mounting_errors(
    nominal: ArrayLayout,
    outward_offset_m: float,
    position_scatter_m: float,
    axis_error_deg: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, MountingErrors]:
    """Draw a cube's real mounting errors.

    Returns the designed (known) position offsets (N, 3), m, outward from the
    cube centre, and the real errors: those offsets plus an unknown scatter,
    and axis errors, drawn in that order from ``rng``.
    """
    n = nominal.n_sensors
    designed = outward_offset_m * outward_directions(nominal)
    scatter = rng.normal(0.0, position_scatter_m, (n, 3))
    axes = rng.normal(0.0, np.deg2rad(axis_error_deg), (n, 2))
    return designed, MountingErrors(designed + scatter, axes)


def _static_mean_mv(
    sensor: AccelerometerModel,
    real: ArrayLayout,
    errors: ChannelErrors,
    up_b: np.ndarray,
    samples: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Mean output (K, N), mV, over ``samples`` samples at rest with ``up_b[k]`` (K, 3) up."""
    zeros = np.zeros((up_b.shape[0], 3))
    a = real.outputs(zeros, G0_MPS2 * up_b, zeros)  # at rest f = +g along the up direction
    v, _ = sensor.volts(np.repeat(a[:, None, :], samples, axis=1), errors, rng)
    return v.mean(axis=1)


def static_readings_mv(
    sensor: AccelerometerModel,
    real: ArrayLayout,
    scale_error: np.ndarray,
    up_b: np.ndarray,
    samples: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Mean output (K, N), mV, of each channel at rest with ``up_b[k]`` (K, 3) pointing up.

    The bias is common to all orientations of a calibration session (drawn once here).
    """
    bias = rng.normal(0.0, sensor.bias_mv, real.n_sensors)
    errors = ChannelErrors(bias_mv=bias, scale_error=scale_error)
    return _static_mean_mv(sensor, real, errors, up_b, samples, rng)


def build_hardware(scn: TiltTableScenario, rng: np.random.Generator) -> Hardware:
    """Draw the cube's real errors and calibrate it as the scenario says."""
    nominal = layout_by_name(scn.array.layout, scn.array.lever_arm_m)
    n = nominal.n_sensors
    m = scn.mounting
    designed, true_errors = draw_mounting_errors(
        nominal, m.outward_offset_m, m.position_scatter_m, m.axis_error_deg, rng
    )
    scale_error = rng.normal(0.0, scn.sensor.scale_error, n)
    real = true_errors.real_layout(nominal)
    s = scn.sensor.sensitivity_mv_per_g
    spp = scn.calibration.samples_per_position
    up = multiposition_directions()
    cal = calibrate_multiposition(
        up, static_readings_mv(scn.sensor, real, scale_error, up, spp, rng), nominal, s
    )
    if scn.calibration.method == "multiposition":
        known_axes = cal.axis_error_rad
        scale = cal.scale
    else:
        known_axes = np.zeros((n, 2))
        known_axes[:, 0] = eq27_calibrate(scn.sensor, nominal, real, scale_error, spp, rng)
        scale = np.ones(n)  # eq. 27 presets 100 mV per g
    known = MountingErrors(designed, known_axes)
    return Hardware(nominal, true_errors, scale_error, known, cal, scale)


def eq27_calibrate(
    sensor: AccelerometerModel,
    nominal: ArrayLayout,
    real: ArrayLayout,
    scale_error: np.ndarray,
    samples: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Axis error towards e1 (N,), rad, by eq. 27 from simulated static readings."""
    positions = eq27_positions(nominal)  # (N, 4, 3)
    out = np.empty(nominal.n_sensors)
    bias = rng.normal(0.0, sensor.bias_mv, nominal.n_sensors)
    errors = ChannelErrors(bias_mv=bias, scale_error=scale_error)
    for i in range(nominal.n_sensors):
        v = _static_mean_mv(sensor, real, errors, positions[i], samples, rng)[:, i]
        out[i] = eq27_axis_error(v[0], v[1], np.sign(v[2] - v[3]), sensor.sensitivity_mv_per_g)
    return out


def turn_axis_b(scn: TiltTableScenario) -> np.ndarray:
    """The indexing head's axis in the body frame: z (vertical) or x (horizontal)."""
    return np.array([0.0, 0.0, 1.0]) if scn.test.plane == "horizontal" else np.array([1.0, 0, 0])


def turn_truth(scn: TiltTableScenario, angle_rad: float) -> FlightTruth:
    """Exact kinematics of one indexing-head turn of the scenario."""
    axis = turn_axis_b(scn)
    return fixed_axis_turn(
        angle_rad,
        duration_s=scn.test.turn_duration_s,
        rest_before_s=scn.test.rest_before_s,
        rest_after_s=scn.test.rest_after_s,
        rate_hz=scn.run.rate_hz,
        axis_b=axis,
        pivot_b_m=np.array(scn.test.pivot_b_m),
    )


def loop_channel_ranges(scn: TiltTableScenario) -> np.ndarray:
    """Full-scale range (9,) of the loop channels: rate, angular acceleration, specific force."""
    f_range = scn.sensor.range_g * G0_MPS2
    rate = np.deg2rad(scn.compensation.rate_range_dps)
    return np.repeat([rate, f_range / scn.array.lever_arm_m, f_range], 3)


def grey_shift(scn: TiltTableScenario) -> str | np.ndarray:
    """The GM(1,1) shift the scenario asks for: "auto" or the channel ranges."""
    return "auto" if scn.compensation.grey_shift == "auto" else loop_channel_ranges(scn)


@dataclass(frozen=True)
class TurnResult:
    """Angles read by each method for one turn, deg, and loop counters."""

    platform_deg: float
    angle_deg: dict[str, float]
    n_fallbacks: dict[str, int]


def measure_turn(
    scn: TiltTableScenario,
    hw: Hardware,
    angle_deg: float,
    rng: np.random.Generator,
    methods: tuple[str, ...] = METHODS,
) -> TurnResult:
    """Simulate one turn and read its angle with each method."""
    truth = turn_truth(scn, np.deg2rad(angle_deg))
    real = hw.true_errors.real_layout(hw.nominal)
    a_true = real.outputs(truth.omega_dot_b_rps2, truth.f_b_mps2, truth.omega_b_rps)
    errors = ChannelErrors(
        bias_mv=rng.normal(0.0, scn.sensor.bias_mv, hw.nominal.n_sensors),
        scale_error=hw.channel_scale_error,
    )
    raw = scn.sensor.measure(truth.t_s, a_true, errors, rng).accel_mps2
    scaled = raw / hw.calibrated_scale
    # Zero at rest: every channel reads its nominal rest value over the rest window.
    n_rest = max(1, int(scn.test.rest_before_s * scn.run.rate_hz))
    zero3 = np.zeros(3)
    f_rest = truth.f_b_mps2[0]  # the zero assumes the known rest attitude (level)
    phi_rest = kinematic_features(zero3, f_rest, zero3)
    nominal_rest = hw.nominal.design @ phi_rest
    zeroed = scaled - (scaled[:n_rest].mean(axis=0) - nominal_rest)
    samples = ArraySamples(truth.t_s, zeroed)
    solver = ArraySolver(hw.nominal)
    e_known = hw.known_errors.error_matrix(hw.nominal)
    window = scn.compensation.window
    predictors = {
        "none": LastValuePredictor(),
        "gm11": GreyPredictor(window=window, shift=grey_shift(scn)),
        "last": LastValuePredictor(),
        "line": LinePredictor(window=window),
        "oracle": OraclePredictor(truth.loop_state()),
    }
    axis = turn_axis_b(scn)
    angles, fallbacks = {}, {}
    for name in methods:
        out = compensate(
            samples,
            solver,
            None if name == "none" else e_known,
            predictors[name],
            reference_features=phi_rest,
        )
        q = integrate_rate(out.omega_b_rps, truth.t_s)
        angles[name] = float(np.rad2deg(rotation_angle_about(q, axis)[-1]))
        fallbacks[name] = out.n_fallbacks
    return TurnResult(float(angle_deg), angles, fallbacks)


@dataclass(frozen=True)
class MethodSummary:
    mean_abs_deg: float
    rms_deg: float
    max_abs_deg: float
    beyond_60_mean_abs_deg: float


def summarise(errors_deg: np.ndarray, platform_deg: np.ndarray) -> MethodSummary:
    """Mean absolute, RMS and worst error, and mean absolute beyond +-60 deg."""
    e = np.asarray(errors_deg, dtype=float)
    far = np.abs(platform_deg) > 60.0
    return MethodSummary(
        mean_abs_deg=float(np.mean(np.abs(e))),
        rms_deg=float(np.sqrt(np.mean(e**2))),
        max_abs_deg=float(np.max(np.abs(e))),
        beyond_60_mean_abs_deg=float(np.mean(np.abs(e[far]))) if np.any(far) else float("nan"),
    )


@dataclass(frozen=True)
class PaperResult:
    """Everything ``ngnav paper`` prints."""

    scenario: TiltTableScenario
    turns: tuple[TurnResult, ...]
    summary: dict[str, MethodSummary]
    paper: PaperTable
    paper_summary: dict[str, MethodSummary]
    hardware: Hardware


def run_paper(
    scn: TiltTableScenario,
    angles_deg: np.ndarray | None = None,
    methods: tuple[str, ...] = METHODS,
    progress=None,
) -> PaperResult:
    """Run the experiment at Table 1's angles (or ``angles_deg``)."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r}; choose from {', '.join(METHODS)}")
    paper = load_paper_table()
    angles = paper.platform_deg if angles_deg is None else np.asarray(angles_deg, dtype=float)
    hw = build_hardware(scn, np.random.default_rng([scn.run.seed, 0]))
    turns = []
    for i, ang in enumerate(angles):
        turns.append(
            measure_turn(scn, hw, ang, np.random.default_rng([scn.run.seed, 1, i]), methods)
        )
        if progress is not None:
            progress(i + 1, len(angles))
    summary = {
        m: summarise(np.array([t.angle_deg[m] - t.platform_deg for t in turns]), angles)
        for m in methods
    }
    paper_summary = {
        "measured": summarise(paper.measured_deg - paper.platform_deg, paper.platform_deg),
        "compensated": summarise(paper.compensated_deg - paper.platform_deg, paper.platform_deg),
    }
    return PaperResult(scn, tuple(turns), summary, paper, paper_summary, hw)
