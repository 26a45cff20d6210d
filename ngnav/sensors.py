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
