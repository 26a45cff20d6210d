"""Static calibration of accelerometer channels (paper eq. 27 and multi-position LS).

Both methods use gravity only: at rest with body direction ``up_b`` pointing
up, the specific force is ``f_b = +g0 up_b`` and a channel with real axis
``u``, sensitivity ``s (1 + k)`` and zero ``b`` reads ``v = b + s (1 + k) u . up_b``
(in mV, ``s`` in mV per g).

- :func:`eq27_axis_error` is the paper's eq. 27: ``delta = arccos(|(V2 - V1)/s|)``
  from a reading with the axis horizontal (V1) and vertical (V2), with the
  sign from the change of the reading as the axis passes vertical. It assumes
  the zero equals V1 and the sensitivity is exact; near ``delta = 0`` the
  arccos has infinite slope, so the method is badly conditioned: a 1 deg axis
  error changes the reading by ``s (1 - cos 1 deg) = 0.015 mV`` and a 0.1 mV
  reading error alone reads as ``arccos(1 - 0.001) = 2.6 deg``.
- :func:`calibrate_multiposition` fits ``v = b + m . up_b`` per channel by
  least squares over K >= 4 static orientations (``m = s (1 + k) u``), giving
  bias, scale, two axis-error angles and their standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.layout import ArrayLayout
from ngnav.mounting import perpendicular_basis


def eq27_axis_error(
    v_horizontal_mv: np.ndarray,
    v_vertical_mv: np.ndarray,
    slope_sign: np.ndarray,
    sensitivity_mv_per_g: float = 100.0,
) -> np.ndarray:
    """Axis error (rad) by the paper's eq. 27, per channel.

    Parameters
    ----------
    v_horizontal_mv : array (N,)
        V1: output with the sensing axis horizontal, mV.
    v_vertical_mv : array (N,)
        V2: output with the sensing axis vertical (pointing up), mV.
    slope_sign : array (N,)
        Sign of the change of the output as the axis is tilted through vertical
        in the positive (right-hand) sense; gives the sign of the angle.
    sensitivity_mv_per_g : float
        Nominal sensitivity (the paper's 100 mV per g).

    Returns
    -------
    array (N,)
        Signed axis error, rad. A ratio above 1 (scale error, noise) reads as 0.
    """
    ratio = np.abs((np.asarray(v_vertical_mv) - np.asarray(v_horizontal_mv)) / sensitivity_mv_per_g)
    return np.sign(slope_sign) * np.arccos(np.clip(ratio, 0.0, 1.0))


def eq27_positions(layout: ArrayLayout, tilt_rad: float = np.deg2rad(1.0)) -> np.ndarray:
    """The static ``up_b`` directions eq. 27 needs per channel, shape (N, 4, 3).

    For channel i: axis horizontal (up = e1), axis vertical (up = theta),
    and tilted by +-``tilt_rad`` from vertical towards e1 (the sign reading).
    """
    t = layout.axes_b
    e1, _ = perpendicular_basis(t)
    c, s = np.cos(tilt_rad), np.sin(tilt_rad)
    return np.stack([e1, t, c * t + s * e1, c * t - s * e1], axis=1)


def multiposition_directions() -> np.ndarray:
    """18 static ``up_b`` directions: the 6 faces and 12 edges of a cube, shape (18, 3).

    Faces alone (6 positions) determine the 4 unknowns per channel; the edge
    positions add redundancy and excite each pair of axes together.
    """
    faces = np.vstack([np.eye(3), -np.eye(3)])
    edges = []
    for i in range(3):
        for j in range(i + 1, 3):
            for si in (1.0, -1.0):
                for sj in (1.0, -1.0):
                    v = np.zeros(3)
                    v[i], v[j] = si, sj
                    edges.append(v / np.sqrt(2.0))
    return np.vstack([faces, np.array(edges)])


@dataclass(frozen=True)
class MultiPositionCalibration:
    """Result of :func:`calibrate_multiposition`, per channel (N,).

    Attributes
    ----------
    bias_mv : array (N,)
        Zero-g output, mV.
    scale : array (N,)
        Real over nominal sensitivity (1 + k).
    axis_error_rad : array (N, 2)
        Axis-error angles towards e1 and e2 (see :class:`ngnav.mounting.MountingErrors`).
    axis_error_sigma_rad : array (N, 2)
        1-sigma of those angles: the fit's, with the noise from its residuals (the
        standard deviation of a Student t's error, ``s^2 dof / (dof - 2)``).
    bias_sigma_mv, scale_sigma : array (N,)
        1-sigma of bias and scale.
    residual_rms_mv : array (N,)
        RMS fit residual, mV.
    """

    bias_mv: np.ndarray
    scale: np.ndarray
    axis_error_rad: np.ndarray
    axis_error_sigma_rad: np.ndarray
    bias_sigma_mv: np.ndarray
    scale_sigma: np.ndarray
    residual_rms_mv: np.ndarray


def calibrate_multiposition(
    up_b: np.ndarray,
    readings_mv: np.ndarray,
    layout: ArrayLayout,
    sensitivity_mv_per_g: float = 100.0,
) -> MultiPositionCalibration:
    """Least-squares calibration of every channel from K static orientations.

    Parameters
    ----------
    up_b : array (K, 3)
        The body direction pointing up in each orientation (unit vectors).
    readings_mv : array (K, N)
        Mean output of each channel in each orientation, mV.
    layout : ArrayLayout
        Nominal layout (for the nominal axes).
    sensitivity_mv_per_g : float
        Nominal sensitivity, mV per g.

    Raises
    ------
    ValueError
        Fewer than 7 orientations (too few residuals to estimate the noise from),
        orientations that do not span 3-D, or non-finite readings.
    """
    up = np.asarray(up_b, dtype=float)
    v = np.asarray(readings_mv, dtype=float)
    n = layout.n_sensors
    if up.ndim != 2 or up.shape[1] != 3:
        raise ValueError(f"up_b must have shape (K, 3), got {up.shape}")
    k = up.shape[0]
    if v.shape != (k, n):
        raise ValueError(f"readings_mv must have shape ({k}, {n}), got {v.shape}")
    if k < 7:
        raise ValueError(
            f"multi-position calibration needs at least 7 orientations (the noise is "
            f"estimated from the residuals, with 3 of them at least), got {k}"
        )
    if not (np.all(np.isfinite(up)) and np.all(np.isfinite(v))):
        raise ValueError("orientations and readings must be finite")
    design = np.column_stack([np.ones(k), up])
    if np.linalg.matrix_rank(design) < 4:
        raise ValueError("the orientations do not span three dimensions plus a zero")
    sol, *_ = np.linalg.lstsq(design, v, rcond=None)  # (4, N)
    resid = v - design @ sol
    dof = k - 4
    # the noise is estimated from dof residuals, so an error over its estimate is a Student
    # t's, whose variance is s^2 dof / (dof - 2): given as a prior, s^2 alone read a NEES
    # dof / (dof - 2) too large (projectile: 31.5 for 27 dof over 40 runs at 18 poses)
    sigma2 = np.sum(resid**2, axis=0) / (dof - 2)  # (N,)
    cov_unit = np.linalg.inv(design.T @ design)  # (4, 4)
    bias = sol[0]
    m = sol[1:].T  # (N, 3)
    norm = np.linalg.norm(m, axis=1)
    u = m / norm[:, None]
    theta = layout.axes_b
    e1, e2 = perpendicular_basis(theta)
    angles = np.empty((n, 2))
    sig_angles = np.empty((n, 2))
    scale_sigma = np.empty(n)
    for i in range(n):
        cov_m = sigma2[i] * cov_unit[1:, 1:]
        mt = m[i] @ theta[i]
        for c, e in enumerate((e1[i], e2[i])):
            me = m[i] @ e
            angles[i, c] = np.arctan2(me, mt)
            grad = (e * mt - theta[i] * me) / (mt * mt + me * me)
            sig_angles[i, c] = np.sqrt(grad @ cov_m @ grad)
        gn = u[i] / sensitivity_mv_per_g
        scale_sigma[i] = np.sqrt(gn @ cov_m @ gn)
    return MultiPositionCalibration(
        bias_mv=bias,
        scale=norm / sensitivity_mv_per_g,
        axis_error_rad=angles,
        axis_error_sigma_rad=sig_angles,
        bias_sigma_mv=np.sqrt(sigma2 * cov_unit[0, 0]),
        scale_sigma=scale_sigma,
        residual_rms_mv=np.sqrt(np.mean(resid**2, axis=0)),
    )
