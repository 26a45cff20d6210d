"""Simulated runs: a flight scenario turned into array samples, GPS fixes and truth.

Everything random in one run comes from ``numpy.random.default_rng([seed, i])``
(``i`` the run index), in a fixed order: mounting errors, scale errors, the
bench calibration, the aircraft's own lift law (with ``[flight] lift_scatter``),
the flight's channel noise and biases, the GPS errors, the
initial heading and attitude the filter is told, and for a hand-over its initial
rate. The same seed and index give
the same run, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ngnav.calibration import calibrate_multiposition, multiposition_directions
from ngnav.conventions import G0_MPS2
from ngnav.geodesy import LocalTangentPlane
from ngnav.layout import ArrayLayout, layout_by_name
from ngnav.mounting import MountingErrors
from ngnav.paper import draw_mounting_errors
from ngnav.records import ArraySamples, FlightTruth, GpsFixes
from ngnav.rotation import euler_from_quat
from ngnav.runconfig import InitialSettings, RunConfig
from ngnav.sim.faults import ChannelFault, inject_faults
from ngnav.sim.flight import fly
from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.gps import GpsReceiverModel
from ngnav.sim.rocking import rock
from ngnav.sim.sensors import AccelerometerSpec


@dataclass(frozen=True)
class SimulatedRun:
    """One simulated run: the inputs a filter sees, what it is told, and the truth.

    Attributes
    ----------
    truth : FlightTruth
    samples : ArraySamples
        Channel outputs (T, N), m/s^2.
    saturated : array (T, N) of bool
    channel_bias_mps2 : array (T, N)
        True channel biases.
    fixes : GpsFixes
    glitched : array (M,) of bool
        Fixes given a position jump.
    config : RunConfig
        What the filter is told (calibrated geometry, noise, initial heading).
    true_errors : MountingErrors
        The real mounting errors (for the oracle geometry).
    true_scale : array (N,)
        Real over nominal sensitivity.
    faults : tuple of ChannelFault
        The channel faults injected (the scenario's ``[faults]``).
    """

    truth: FlightTruth
    samples: ArraySamples
    saturated: np.ndarray
    channel_bias_mps2: np.ndarray
    fixes: GpsFixes
    glitched: np.ndarray
    config: RunConfig
    true_errors: MountingErrors
    true_scale: np.ndarray
    faults: tuple[ChannelFault, ...] = ()

    def true_layout(self) -> ArrayLayout:
        """The array as really built."""
        return self.true_errors.real_layout(self.config.layout)

    def unknown_position_error_mps2(self) -> np.ndarray:
        """Channel errors (T, N), m/s^2, that the sensor positions left unknown cause.

        ``theta_i . (wdot x dr_i + w x (w x dr_i))`` over the truth's motion, with
        ``dr_i`` the real position minus the calibrated one (the scatter the
        filter's ``DR`` states model) and ``theta_i`` the real sensing axis. Set
        beside the channel noise and bias it says whether a flight makes the
        scatter visible (the filter carries it as states whenever it is declared).
        """
        nominal = self.config.layout
        dr = self.true_errors.position_error_b_m - self.config.known_errors.position_error_b_m
        axes = self.true_errors.real_axes(nominal)
        tr = self.truth
        out = np.empty((tr.omega_b_rps.shape[0], dr.shape[0]))
        for i in range(dr.shape[0]):
            lever = np.cross(tr.omega_dot_b_rps2, dr[i])
            lever += np.cross(tr.omega_b_rps, np.cross(tr.omega_b_rps, dr[i]))
            out[:, i] = lever @ axes[i]
        return out

    def calibration_residual_error_mps2(self) -> np.ndarray:
        """Channel errors (T, N), m/s^2, that the bench calibration's scale and axis
        residual causes, less their value at the first sample (what a bias holds).

        ``dg_i . a_i``: ``dg_i`` the real sensing axis times the real over the calibrated
        scale, less the calibrated axis (the filter's ``CAL`` states, when declared), and
        ``a_i`` the truth's specific force at the sensor.
        """
        cfg = self.config
        nominal = cfg.layout
        dg = (self.true_scale / cfg.scale)[:, None] * self.true_errors.real_axes(
            nominal
        ) - cfg.known_errors.real_axes(nominal)
        tr = self.truth
        out = np.empty((tr.omega_b_rps.shape[0], dg.shape[0]))
        for i, r in enumerate(cfg.known_errors.real_layout(nominal).positions_b_m):
            load = tr.f_b_mps2 + np.cross(tr.omega_dot_b_rps2, r)
            load += np.cross(tr.omega_b_rps, np.cross(tr.omega_b_rps, r))
            out[:, i] = load @ dg[i]
        return out - out[0]


def bench_calibration(
    spec: AccelerometerSpec,
    real: ArrayLayout,
    nominal: ArrayLayout,
    scale_error: np.ndarray,
    samples: int,
    rate_hz: float,
    rng: np.random.Generator,
):
    """Multi-position calibration from simulated static readings (18 orientations).

    Readings are means of ``samples`` noisy samples with a bench-session bias;
    returns :class:`ngnav.calibration.MultiPositionCalibration` (its "mV" are
    milli-g here: sensitivity 1000 per g).
    """
    up = multiposition_directions()
    zeros = np.zeros((up.shape[0], 3))
    a = real.outputs(zeros, G0_MPS2 * up, zeros)  # (K, N) at rest, f = +g along up
    n = real.n_sensors
    bias = rng.normal(0.0, spec.turn_on_bias_mps2(), n)
    sigma = spec.sample_sigma_mps2(rate_hz) / np.sqrt(samples)
    readings = (1.0 + scale_error) * a + bias + rng.normal(0.0, sigma, a.shape)
    return calibrate_multiposition(up, readings / G0_MPS2 * 1000.0, nominal, 1000.0)


@dataclass(frozen=True)
class DrawnArray:
    """Run ``i``'s array as built: the first draws of ``default_rng([seed, i])``, in this
    order, so the flight and its bench session (:mod:`ngnav.sim.bench_recordings`) share it.

    ``designed`` (N, 3) are the drawings' offsets (known), ``true_errors`` the real
    positions and axes, ``scale_error`` (N,) the real sensitivity over nominal minus 1.
    """

    spec: AccelerometerSpec
    nominal: ArrayLayout
    designed: np.ndarray
    true_errors: MountingErrors
    scale_error: np.ndarray
    real: ArrayLayout


def draw_array(scn: FlightScenario, rng: np.random.Generator) -> DrawnArray:
    """Draw the scenario's array from ``rng`` (the run's first draws; see :class:`DrawnArray`)."""
    spec = scn.sensor.spec()
    nominal = layout_by_name(scn.array.layout, scn.array.lever_arm_m)
    m = scn.mounting
    designed, true_errors = draw_mounting_errors(
        nominal, m.outward_offset_m, m.position_scatter_m, m.axis_error_deg, rng
    )
    scale_error = rng.normal(0.0, spec.scale_error, nominal.n_sensors)
    real = true_errors.real_layout(nominal)
    return DrawnArray(spec, nominal, designed, true_errors, scale_error, real)


def simulate_flight(
    scn: FlightScenario, run_index: int = 0, progress: Callable[[float], None] | None = None
) -> SimulatedRun:
    """Simulate run ``run_index`` of a flight scenario (see module docstring).

    ``progress``, optional, is called with the fraction done (0-1) after each stage
    (the bench calibration, the flight, the sensors, the GPS receiver).
    """
    done = progress or (lambda fraction: None)
    rng = np.random.default_rng([scn.run.seed, run_index])
    rate = scn.run.rate_hz
    arr = draw_array(scn, rng)
    spec, nominal, real, scale_error = arr.spec, arr.nominal, arr.real, arr.scale_error
    designed, true_errors = arr.designed, arr.true_errors
    n = nominal.n_sensors
    m = scn.mounting
    cal = bench_calibration(spec, real, nominal, scale_error, m.calibration_samples, rate, rng)
    done(0.1)
    known = MountingErrors(designed, cal.axis_error_rad)

    plan = scn.plan()
    if plan.lift is not None and scn.lift_scatter is not None:
        # this run's aircraft: the type's lift law with its own rigging and loading
        plan = replace(plan, lift=plan.lift.drawn(*scn.lift_scatter, rng))
    truth = fly(plan, rate)
    if scn.rocking_rate_dps > 0:
        # its own stream: the run's other draws stay those of the still body
        rocking_rng = np.random.default_rng([scn.run.seed, run_index, 2])
        truth = rock(truth, float(np.deg2rad(scn.rocking_rate_dps)), rocking_rng)
    done(0.5)
    clean = real.outputs(truth.omega_dot_b_rps2, truth.f_b_mps2, truth.omega_b_rps)
    out, saturated, bias = spec.simulate(clean, rate, scale_error, rng)
    if scn.faults:
        # their own stream: the run's other draws stay those of the healthy run
        out = inject_faults(
            truth.t_s,
            out,
            scn.faults,
            spec.sample_sigma_mps2(rate),
            spec.range_g * G0_MPS2,
            np.random.default_rng([scn.run.seed, run_index, 1]),
        )
    done(0.8)
    samples = ArraySamples(truth.t_s, out)

    g = scn.gps
    outages = ((g.outage_start_s, g.outage_s),) if g.outage_s > 0 else ()
    receiver = GpsReceiverModel(
        rate_hz=g.rate_hz,
        h_acc_m=g.h_acc_m,
        v_acc_m=g.v_acc_m,
        vel_acc_mps=g.vel_acc_mps,
        latency_s=g.latency_s,
        antenna_b_m=g.antenna_b_m,
        outages=outages,
        glitch_times_s=g.glitch_times_s,
        glitch_m=g.glitch_m,
    )
    ltp = LocalTangentPlane(scn.reference.lat_deg, scn.reference.lon_deg, scn.reference.alt_m)
    fixes, glitched = receiver.simulate(truth, ltp, rng)
    done(1.0)

    ini = scn.initial
    rpy0 = np.rad2deg(euler_from_quat(truth.q_nb[0]))
    tilt_err = rng.normal(0.0, ini.tilt_sigma_deg, 2)
    yaw_err = rng.normal(0.0, ini.heading_sigma_deg)
    rate0 = np.zeros(3)
    if ini.alignment == "config":
        # a hand-over: the launcher's rate reading, as uncertain as the filter is told
        rate0 = np.rad2deg(truth.omega_b_rps[0]) + rng.normal(0.0, ini.rate_sigma_dps, 3)
    initial = InitialSettings(
        alignment=ini.alignment,
        static_s=ini.static_s,
        roll_deg=float(rpy0[0] + tilt_err[0]),
        pitch_deg=float(rpy0[1] + tilt_err[1]),
        yaw_deg=float(rpy0[2] + yaw_err),
        tilt_sigma_deg=ini.tilt_sigma_deg,
        heading_source=ini.heading_source,
        heading_sigma_deg=ini.heading_sigma_deg,
        rate_dps=(float(rate0[0]), float(rate0[1]), float(rate0[2])),
        rate_sigma_dps=ini.rate_sigma_dps,
    )
    config = RunConfig(
        layout=nominal,
        known_errors=known,
        scale=cal.scale,
        offset_mps2=np.zeros(n),
        noise_sigma_mps2=np.full(n, spec.sample_sigma_mps2(rate)),
        turn_on_bias_mps2=np.full(n, spec.turn_on_bias_mps2()),
        bias_rw_mps2_rts=np.full(n, spec.bias_rw_mps2_rts()),
        range_mps2=spec.range_g * G0_MPS2,
        lat0_deg=scn.reference.lat_deg,
        lon0_deg=scn.reference.lon_deg,
        alt0_m=scn.reference.alt_m,
        antenna_b_m=np.asarray(g.antenna_b_m),
        position_sigma_m=m.position_scatter_m,
        scale_sigma=cal.scale_sigma if m.declare_calibration_sigmas else 0.0,
        axis_error_sigma_rad=cal.axis_error_sigma_rad if m.declare_calibration_sigmas else 0.0,
        initial=initial,
        filter=scn.filter,
        compensation=scn.compensation,
        vehicle=scn.vehicle,
        rest=scn.rest,
    )
    return SimulatedRun(
        truth,
        samples,
        saturated,
        bias,
        fixes,
        glitched,
        config,
        true_errors,
        1.0 + scale_error,
        scn.faults,
    )
