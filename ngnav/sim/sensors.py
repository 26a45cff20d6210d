"""Accelerometer channel error models: millivolts at the edge, m/s^2 inside.

A channel's output voltage is ``v = bias + s_nom (1 + scale_err) a / g0 +
noise``, clipped to the range and quantised by the ADC; with oversampling the
ADC converts ``oversampling`` times per output sample (each conversion with
its own noise, which dithers the quantiser) and the output is their mean, as a
DSP's decimation filter does. ``measure``
returns what a user gets after dividing by the *nominal* sensitivity: m/s^2
with the channel errors still in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.conventions import G0_MPS2
from ngnav.records import ArraySamples


@dataclass(frozen=True)
class AccelerometerModel:
    """Error model of one kind of single-axis accelerometer channel.

    Parameters
    ----------
    sensitivity_mv_per_g : float
        Nominal sensitivity, mV per g.
    range_g : float
        Full scale, +- g; outputs beyond it saturate.
    noise_mv : float
        White noise per conversion at the ADC input, mV rms.
    bias_mv : float
        Turn-on zero offset, 1-sigma over channels and runs, mV.
    scale_error : float
        Sensitivity error, 1-sigma, relative (0.005 = 0.5 %).
    adc_bits : int or None
        ADC resolution over +-range; None for no quantisation.
    oversampling : int
        ADC conversions averaged into one output sample (1: none).
    """

    sensitivity_mv_per_g: float = 100.0
    range_g: float = 2.5
    noise_mv: float = 0.05
    bias_mv: float = 5.0
    scale_error: float = 0.005
    adc_bits: int | None = 12
    oversampling: int = 1

    def __post_init__(self) -> None:
        for name in ("sensitivity_mv_per_g", "range_g"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be positive, got {v}")
        for name in ("noise_mv", "bias_mv", "scale_error"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be non-negative, got {v}")
        if self.adc_bits is not None and not (1 <= self.adc_bits <= 32):
            raise ValueError(f"adc_bits must be in 1..32 or None, got {self.adc_bits}")
        if self.oversampling < 1:
            raise ValueError(f"oversampling must be >= 1, got {self.oversampling}")

    @property
    def lsb_mv(self) -> float | None:
        """ADC step, mV (None without quantisation)."""
        if self.adc_bits is None:
            return None
        return 2.0 * self.range_g * self.sensitivity_mv_per_g / 2**self.adc_bits

    @property
    def output_noise_mv(self) -> float:
        """White noise per output sample, mV rms, with dithered quantisation (LSB^2/12)."""
        q2 = 0.0 if self.lsb_mv is None else self.lsb_mv**2 / 12.0
        return float(np.sqrt((self.noise_mv**2 + q2) / self.oversampling))

    @property
    def output_noise_mps2(self) -> float:
        """White noise per output sample, m/s^2 rms (see :attr:`output_noise_mv`)."""
        return self.output_noise_mv / self.sensitivity_mv_per_g * G0_MPS2

    def draw_channel_errors(self, n_channels: int, rng: np.random.Generator) -> ChannelErrors:
        """Draw turn-on bias and scale error for ``n_channels`` channels."""
        return ChannelErrors(
            bias_mv=rng.normal(0.0, self.bias_mv, n_channels),
            scale_error=rng.normal(0.0, self.scale_error, n_channels),
        )

    def volts(
        self, accel_true_mps2: np.ndarray, errors: ChannelErrors, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """Output voltages (T, N), mV, and a saturation mask (T, N)."""
        a = np.asarray(accel_true_mps2, dtype=float)
        s = self.sensitivity_mv_per_g
        clean = errors.bias_mv + s * (1.0 + errors.scale_error) * a / G0_MPS2
        full = self.range_g * s
        os = self.oversampling
        v = clean[..., None] + rng.normal(0.0, self.noise_mv, (*a.shape, os))
        saturated = np.any(np.abs(v) >= full, axis=-1)
        v = np.clip(v, -full, full)
        lsb = self.lsb_mv
        if lsb is not None:
            v = np.round(v / lsb) * lsb
        return v.mean(axis=-1), saturated

    def measure(
        self,
        t_s: np.ndarray,
        accel_true_mps2: np.ndarray,
        errors: ChannelErrors,
        rng: np.random.Generator,
    ) -> ArraySamples:
        """Simulated array samples, m/s^2 by the nominal sensitivity."""
        v, _ = self.volts(accel_true_mps2, errors, rng)
        return ArraySamples(t_s, v / self.sensitivity_mv_per_g * G0_MPS2)


@dataclass(frozen=True)
class ChannelErrors:
    """Per-channel turn-on errors drawn for one run: ``bias_mv`` (N,), ``scale_error`` (N,)."""

    bias_mv: np.ndarray
    scale_error: np.ndarray


@dataclass(frozen=True)
class AccelerometerSpec:
    """Error model of an accelerometer channel in SI, for simulated flights.

    A channel reads ``a_out = (1 + k) a + b(t) + n``, clipped to the range and
    quantised; ``b(t)`` is a turn-on value plus a random walk, ``n`` white noise
    band-limited to the Nyquist frequency (per-sample sigma
    ``noise_density * sqrt(rate / 2)``).

    Parameters
    ----------
    name : str
        Preset name or "custom".
    noise_density_ug_rthz : float
        White-noise density, micro-g per root hertz.
    turn_on_bias_mg : float
        Run-to-run bias, 1-sigma per channel, milli-g: what is left after the
        bench calibration, so the filter must estimate it.
    bias_rw_ug_rts : float
        In-run bias random walk, micro-g per root second.
    scale_error : float
        Sensitivity error, 1-sigma, relative, before calibration.
    range_g : float
        Full scale, +- g.
    adc_bits : int or None
        Resolution over +-range; None for none.
    sources : tuple of str
        Where each number comes from (one line per parameter).
    """

    name: str
    noise_density_ug_rthz: float
    turn_on_bias_mg: float
    bias_rw_ug_rts: float
    scale_error: float
    range_g: float
    adc_bits: int | None
    sources: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for key in ("noise_density_ug_rthz", "range_g"):
            v = getattr(self, key)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"sensor.{key} must be positive, got {v}")
        for key in ("turn_on_bias_mg", "bias_rw_ug_rts", "scale_error"):
            v = getattr(self, key)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"sensor.{key} must be non-negative, got {v}")
        if self.adc_bits is not None and not (4 <= self.adc_bits <= 32):
            raise ValueError(f"sensor.adc_bits must be in 4..32 or None, got {self.adc_bits}")

    def lsb_mps2(self) -> float | None:
        """Quantisation step, m/s^2 (None without an ADC model)."""
        if self.adc_bits is None:
            return None
        return 2.0 * self.range_g * G0_MPS2 / 2**self.adc_bits

    def sample_sigma_mps2(self, rate_hz: float) -> float:
        """White noise per sample at ``rate_hz``, m/s^2, with quantisation (LSB^2/12)."""
        white = self.noise_density_ug_rthz * 1e-6 * G0_MPS2 * np.sqrt(rate_hz / 2.0)
        q = self.lsb_mps2()
        return float(np.sqrt(white**2 + (0.0 if q is None else q * q / 12.0)))

    def turn_on_bias_mps2(self) -> float:
        """Turn-on bias 1-sigma, m/s^2."""
        return self.turn_on_bias_mg * 1e-3 * G0_MPS2

    def bias_rw_mps2_rts(self) -> float:
        """Bias random-walk density, m/s^2 per root second."""
        return self.bias_rw_ug_rts * 1e-6 * G0_MPS2

    def simulate(
        self,
        accel_true_mps2: np.ndarray,
        rate_hz: float,
        scale_error: np.ndarray,
        rng: np.random.Generator,
        bias0_mps2: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Outputs of the channels for true accelerations (T, N).

        ``bias0_mps2`` (N,) continues a session whose biases stood there (no turn-on draw).

        Returns
        -------
        accel_mps2 : array (T, N)
            Channel outputs, m/s^2 (nominal sensitivity).
        saturated : array (T, N) of bool
            Samples clipped at the range.
        bias_mps2 : array (T, N)
            The bias each channel had (turn-on plus random walk), for truth.
        """
        a = np.asarray(accel_true_mps2, dtype=float)
        t_n, n = a.shape
        dt = 1.0 / rate_hz
        if bias0_mps2 is None:
            b0 = rng.normal(0.0, self.turn_on_bias_mps2(), n)
        else:
            b0 = np.asarray(bias0_mps2, dtype=float)
        steps = rng.normal(0.0, self.bias_rw_mps2_rts() * np.sqrt(dt), (t_n, n))
        steps[0] = 0.0
        bias = b0 + np.cumsum(steps, axis=0)
        white = self.noise_density_ug_rthz * 1e-6 * G0_MPS2 * np.sqrt(rate_hz / 2.0)
        out = (1.0 + scale_error) * a + bias + rng.normal(0.0, white, a.shape)
        full = self.range_g * G0_MPS2
        saturated = np.abs(out) >= full
        out = np.clip(out, -full, full)
        q = self.lsb_mps2()
        if q is not None:
            out = np.round(out / q) * q
        return out, saturated, bias


def _ic3022() -> AccelerometerSpec:
    return AccelerometerSpec(
        name="ic3022",
        # 1 mV rms per 100 Hz sample at 100 mV/g = 10 mg per sample; density 10 mg / sqrt(50 Hz).
        noise_density_ug_rthz=1e4 / np.sqrt(50.0),
        turn_on_bias_mg=1.0,
        bias_rw_ug_rts=10.0,
        scale_error=0.01,
        range_g=2.5,
        adc_bits=12,
        sources=(
            "noise: the paper's 'millivolt level' noise (section 5.3) at its 100 mV/g and 100 Hz "
            "(sections 5.2, 6): 1 mV = 10 mg per sample, SPEC section 7's 0.01 g per sample",
            "range +-2.5 g and 100 mV/g: the paper, sections 5.2 and 6",
            "adc_bits 12: as the tilt-table scenario (a DSP-integrated converter of the "
            "paper's time)",
            "turn_on_bias_mg 1.0: assumed residual after zeroing at rest (1 mg = 0.1 mV, about one "
            "12-bit step); not from a data sheet",
            "bias_rw_ug_rts 10: assumed; the paper gives no drift figure",
            "scale_error 0.01: assumed part tolerance before calibration (the multi-position "
            "calibration estimates it)",
        ),
    )


def _mems_consumer() -> AccelerometerSpec:
    return AccelerometerSpec(
        name="mems-consumer",
        noise_density_ug_rthz=400.0,
        turn_on_bias_mg=5.0,
        bias_rw_ug_rts=20.0,
        scale_error=0.03,
        range_g=8.0,
        adc_bits=16,
        sources=(
            "noise 400 ug/rtHz, range +-8 g (AFS_SEL=2), 16-bit ADC, sensitivity tolerance +-3 %: "
            "InvenSense MPU-6000/MPU-6050 Product Specification PS-MPU-6000A-00 rev. 3.4, "
            "section 6.2",
            "turn_on_bias_mg 5: zero-g change vs temperature +-35 mg over 0-70 C (same table), "
            "i.e. 0.5 mg/C, times an assumed 10 C between calibration and flight",
            "bias_rw_ug_rts 20: assumed; the data sheet gives no in-run bias stability",
        ),
    )


def _mems_tactical() -> AccelerometerSpec:
    return AccelerometerSpec(
        name="mems-tactical",
        noise_density_ug_rthz=22.5,
        turn_on_bias_mg=1.0,
        bias_rw_ug_rts=2.0,
        scale_error=0.005,
        range_g=4.096,
        adc_bits=20,
        sources=(
            "noise 22.5 ug/rtHz, range +-4.096 g, 20-bit ADC: Analog Devices ADXL355 data sheet "
            "(noise density as quoted from it on ADI EngineerZone, 2022)",
            "turn_on_bias_mg 1.0: assumed residual after a bench calibration; not from the data "
            "sheet",
            "bias_rw_ug_rts 2: assumed; not from the data sheet",
            "scale_error 0.005: assumed part tolerance before calibration",
        ),
    )


_PRESETS = {"ic3022": _ic3022, "mems-consumer": _mems_consumer, "mems-tactical": _mems_tactical}
#: Names of the shipped sensor presets.
PRESET_NAMES: tuple[str, ...] = tuple(_PRESETS)


def sensor_preset(name: str) -> AccelerometerSpec:
    """The shipped :class:`AccelerometerSpec` called ``name`` (see :data:`PRESET_NAMES`)."""
    try:
        return _PRESETS[name]()
    except KeyError:
        raise ValueError(
            f"unknown sensor preset {name!r}; presets: {', '.join(PRESET_NAMES)}"
        ) from None
