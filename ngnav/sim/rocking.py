"""A still body's rocking: the micro-rotation that a bench or a waiting vehicle keeps making.

Without it a simulated rest is exact, and the zero-rate update at rest
(``rest.rate_sigma_dps``) declares a noise that the truth never realises: the smoothed
rate then reads far inside its sigma. With ``[flight] rocking_rate_dps`` the body turns
by a small rotation vector ``theta(t)`` whose rate is white at the array's sample rate
(each axis, each sample: independent, zero mean, that 1-sigma), so the rate the update
reads as zero is off by the declared sigma and independently from one block to the next,
as the update assumes.

``theta_dot`` is the trigonometric polynomial through those white samples (band-limited to
the array's Nyquist frequency, periodic over the flight, no mean); ``theta`` and
``theta_ddot`` are its exact integral and derivative (spectral). The body is turned by it,
``q_nb = q_nb' exp(theta)``, with rate, rate derivative and specific force to first order
in ``theta``:

    omega_b = C^T omega_b' + theta_dot
    omega_dot_b = C^T omega_dot_b' - theta_dot x (C^T omega_b') + theta_ddot
    f_b = C^T f_b'

(``C = exp([theta x])``). The neglected terms are of order ``|theta| |theta_dot|`` and
``|theta_dot|^2``: for ``static``'s 1e-4 deg/s, ``|theta|`` stays below 1e-6 rad (4e-7 on
run 0), and the neglected terms below 1e-11 rad/s and rad/s^2. The body rotates about its
origin, so position and velocity are unchanged.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ngnav.records import FlightTruth
from ngnav.rotation import cross_rows, dcm_from_quat, quat_from_rotvec, quat_multiply


def rocking_angles(
    n: int, rate_hz: float, sigma_rps: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rocking's rotation vector, rate and rate derivative at ``n`` samples.

    Parameters
    ----------
    n : int
        Samples, at ``rate_hz``.
    rate_hz : float
        Sample rate, Hz.
    sigma_rps : float
        1-sigma of the rate per axis and sample, rad/s.
    rng : numpy.random.Generator
        Draws the white rate samples.

    Returns
    -------
    theta_rad, theta_dot_rps, theta_ddot_rps2 : ndarray, shape (n, 3)
        The rotation vector (rad), its rate (rad/s) and its rate's derivative (rad/s^2),
        exact derivatives of one trigonometric polynomial.
    """
    spectrum = np.fft.rfft(rng.normal(0.0, sigma_rps, (n, 3)), axis=0)
    spectrum[0] = 0.0  # no mean rate: the body stays where it stands
    if n % 2 == 0:
        spectrum[-1] = 0.0  # the Nyquist term's derivative vanishes on the samples
    omega = 2j * np.pi * np.fft.rfftfreq(n, 1.0 / rate_hz)[:, None]
    theta = np.fft.irfft(spectrum / np.where(omega == 0.0, 1.0, omega), n, axis=0)
    return theta, np.fft.irfft(spectrum, n, axis=0), np.fft.irfft(spectrum * omega, n, axis=0)


def turn_body(
    truth: FlightTruth,
    theta_rad: np.ndarray,
    theta_dot_rps: np.ndarray,
    theta_ddot_rps2: np.ndarray,
) -> FlightTruth:
    """``truth`` with its body turned by the small rotation vectors ``theta_rad`` (T, 3).

    ``q_nb = q_nb' exp(theta)``; rate, rate derivative and specific force to first order in
    ``theta`` (the module docstring), from its rate (rad/s) and rate derivative (rad/s^2).
    """
    c_t = np.swapaxes(dcm_from_quat(quat_from_rotvec(theta_rad)), -1, -2)
    w_turned = np.einsum("tij,tj->ti", c_t, truth.omega_b_rps)
    return replace(
        truth,
        q_nb=quat_multiply(truth.q_nb, quat_from_rotvec(theta_rad)),
        omega_b_rps=w_turned + theta_dot_rps,
        omega_dot_b_rps2=np.einsum("tij,tj->ti", c_t, truth.omega_dot_b_rps2)
        - cross_rows(theta_dot_rps, w_turned)
        + theta_ddot_rps2,
        f_b_mps2=np.einsum("tij,tj->ti", c_t, truth.f_b_mps2),
    )


def rock(truth: FlightTruth, sigma_rps: float, rng: np.random.Generator) -> FlightTruth:
    """``truth`` with the body rocking at ``sigma_rps`` (rad/s, 1-sigma per axis and sample).

    The sample rate is that of ``truth`` (uniform samples assumed).
    """
    n = truth.t_s.size
    rate_hz = (n - 1) / (truth.t_s[-1] - truth.t_s[0])
    return turn_body(truth, *rocking_angles(n, rate_hz, sigma_rps, rng))
