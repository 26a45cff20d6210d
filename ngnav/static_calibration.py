"""Calibration of an array's channels from static poses whose orientations are unknown.

At rest a channel with real axis ``u_i``, scale ``s_i`` and zero offset ``o_i`` reads
``v_ik = o_i + s_i g0 (u_i . up_k)`` in pose ``k`` (``up_k`` the body direction pointing
up; specific force ``+g0 up``). Nobody knows ``up_k`` on a user's bench, so each pose's
direction is fitted with the channels: offset, scale and two axis-error angles per
channel (``u_i`` as :meth:`ngnav.mounting.MountingErrors.real_axes` tilts it), two
angles per pose, by weighted least squares over the poses' mean readings.

A common rotation of every axis and every pose changes no reading, so the body frame is
fixed by the array itself: the axis errors carry no common rotation (they are orthogonal
to it, :func:`gauge_basis`), which makes the calibrated frame the one that best fits the
nominal axes to the real ones. Sensor positions do not show at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ngnav.conventions import G0_MPS2
from ngnav.layout import ArrayLayout
from ngnav.mounting import perpendicular_basis

#: The fit's condition limit: above it a parameter combination is taken as unobservable
#: (the poses leave it undetermined), and the fit is refused naming it.
MAX_CONDITION = 1e10


@dataclass(frozen=True)
class StaticCalibration:
    """Per-channel result of :func:`fit_static_poses` (N channels, K poses), with 1-sigmas.

    Attributes
    ----------
    offset_mps2, offset_sigma_mps2 : arrays (N,)
        Zero output, m/s^2: the run's ``[calibration] offset_mps2``.
    scale, scale_sigma : arrays (N,)
        Real over nominal sensitivity: ``[calibration] scale``.
    axis_error_rad, axis_error_sigma_rad : arrays (N, 2)
        Axis-error angles towards ``e1`` and ``e2`` (:func:`ngnav.mounting.perpendicular_basis`):
        ``[calibration] axis_error_rad``.
    cov : array (4N - 3, 4N - 3)
        Covariance of ``[offset, scale, z]`` (``z`` the axis errors in :func:`gauge_basis`).
    up_b : array (K, 3)
        Each pose's fitted up direction, body frame.
    residual_rms_mps2 : array (N,)
        RMS of each channel's residual over the poses, m/s^2.
    chi2_per_dof : float
        Weighted residual sum over its degrees of freedom: about 1 when the readings'
        noise is as the configuration says; the sigmas are scaled by its square root
        when it is above 1.
    dof : int
        Readings minus fitted parameters.
    """

    offset_mps2: np.ndarray
    offset_sigma_mps2: np.ndarray
    scale: np.ndarray
    scale_sigma: np.ndarray
    axis_error_rad: np.ndarray
    axis_error_sigma_rad: np.ndarray
    cov: np.ndarray
    up_b: np.ndarray
    residual_rms_mps2: np.ndarray
    chi2_per_dof: float
    dof: int


def gauge_basis(layout: ArrayLayout) -> np.ndarray:
    """Orthonormal basis (2N, 2N - 3) of the axis-error vectors with no common rotation.

    A small rotation ``phi`` of the whole array moves sensor ``i``'s angles by
    ``(e2_i . phi, -e1_i . phi)``; those 3 directions are what the static poses cannot
    see. Axis errors are ``a = Q z`` (``a`` flattened per channel, ``[a1, a2]``).
    """
    u, _, _ = np.linalg.svd(_gauge_directions(layout), full_matrices=True)
    return u[:, 3:]


def _gauge_directions(layout: ArrayLayout) -> np.ndarray:
    """(2N, 3): how a small common rotation ``phi`` moves the flattened axis angles."""
    e1, e2 = perpendicular_basis(layout.axes_b)
    g = np.empty((2 * layout.n_sensors, 3))
    g[0::2], g[1::2] = e2, -e1
    return g


def calibration_frame(
    real_axes_b: np.ndarray, layout: ArrayLayout
) -> tuple[np.ndarray, np.ndarray]:
    """The frame a static calibration defines for real sensing axes: the array turned by
    the common rotation that leaves the axis-error angles none.

    What a static calibration recovers of a known array (a simulation's truth): the
    common rotation is unobservable at rest and belongs to the body frame, not to the axes.

    Returns
    -------
    phi : array (3,)
        The rotation vector (rad) taking body-frame vectors to the calibration frame.
    a : array (N, 2)
        The axis-error angles in that frame.
    """
    from scipy.spatial.transform import Rotation

    u = np.array(real_axes_b, dtype=float)  # a writable copy (scipy's Rotation needs one)
    theta = layout.axes_b
    e1, e2 = perpendicular_basis(theta)
    g = _gauge_directions(layout)
    step = np.linalg.solve(g.T @ g, g.T)
    phi = np.zeros(3)
    for _ in range(8):  # Newton on G^T a(R(phi) u) = 0; the Jacobian is G^T G to first order
        ur = Rotation.from_rotvec(phi).apply(u)
        ut = np.sum(ur * theta, axis=1)
        a = np.column_stack(
            [np.arctan2(np.sum(ur * e1, axis=1), ut), np.arctan2(np.sum(ur * e2, axis=1), ut)]
        )
        phi = phi - step @ a.ravel()
    return phi, a


def _axes(layout: ArrayLayout, a: np.ndarray) -> np.ndarray:
    e1, e2 = perpendicular_basis(layout.axes_b)
    u = layout.axes_b + np.tan(a[:, :1]) * e1 + np.tan(a[:, 1:]) * e2
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _poses(up0: np.ndarray, t: np.ndarray) -> np.ndarray:
    p1, p2 = perpendicular_basis(up0)
    up = up0 + t[:, :1] * p1 + t[:, 1:] * p2
    return up / np.linalg.norm(up, axis=1, keepdims=True)


def _names(n: int, k: int) -> list[str]:
    names = [f"offset of channel {i + 1}" for i in range(n)]
    names += [f"scale of channel {i + 1}" for i in range(n)]
    names += [f"axis angle {c + 1} of channel {i + 1}" for i in range(n) for c in range(2)]
    names += [f"pose {j + 1}'s tilt {c + 1}" for j in range(k) for c in range(2)]
    return names


def fit_static_poses(
    means_mps2: np.ndarray, sigma_mps2: np.ndarray, layout: ArrayLayout
) -> StaticCalibration:
    """Fit offsets, scales and axis errors to the mean readings of K static poses.

    Parameters
    ----------
    means_mps2 : array (K, N)
        Each pose's mean output of each channel, m/s^2 (nominal sensitivity).
    sigma_mps2 : array (K, N)
        1-sigma of those means (the sample noise over the square root of the samples).
    layout : ArrayLayout
        The nominal layout (sensing axes; positions do not enter at rest).

    Raises
    ------
    ValueError
        Too few readings for the parameters, or poses that leave some parameter
        combination undetermined (named, with the parameters it mixes).
    """
    v = np.asarray(means_mps2, dtype=float)
    sig = np.asarray(sigma_mps2, dtype=float)
    k, n = v.shape
    if n != layout.n_sensors or sig.shape != v.shape:
        raise ValueError(
            f"means and sigmas must be (K, {layout.n_sensors}), got {v.shape}, {sig.shape}"
        )
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(sig)) and np.all(sig > 0)):
        raise ValueError("pose means must be finite and their sigmas positive")
    q = gauge_basis(layout)
    n_z = q.shape[1]
    n_par = 2 * n + n_z + 2 * k
    if k * n <= n_par:
        raise ValueError(
            f"{k} poses give {k * n} readings for {n_par} parameters: "
            f"at least {int(np.ceil((2 * n + n_z) / (n - 2)))} poses are needed"
        )
    # each pose's up direction from the nominal axes (the array's own force estimate)
    f0, *_ = np.linalg.lstsq(layout.axes_b, v.T, rcond=None)
    up0 = (f0 / np.linalg.norm(f0, axis=0)).T

    def unpack(x):
        off, sc = x[:n], x[n : 2 * n]
        a = (q @ x[2 * n : 2 * n + n_z]).reshape(n, 2)
        return off, sc, a, _poses(up0, x[2 * n + n_z :].reshape(k, 2))

    def residuals(x):
        off, sc, a, up = unpack(x)
        model = off + sc * G0_MPS2 * (up @ _axes(layout, a).T)
        return ((model - v) / sig).ravel()

    x0 = np.concatenate([np.zeros(n), np.ones(n), np.zeros(n_z + 2 * k)])
    sol = least_squares(residuals, x0, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    jac = sol.jac
    jtj = jac.T @ jac
    w, vecs = np.linalg.eigh(jtj)
    if w[0] <= w[-1] / MAX_CONDITION:
        mix = vecs[:, 0].copy()
        # report the axis errors per channel, not in the gauge basis
        names = _names(n, k)
        weights = np.concatenate([mix[: 2 * n], q @ mix[2 * n : 2 * n + n_z], mix[2 * n + n_z :]])
        # every parameter within half of the largest weight, in the parameters' order: a
        # tilt trading with three axis angles weighs all four alike, so a top-3 by size
        # named a different three from one machine's rounding to the next
        big = np.flatnonzero(np.abs(weights) >= 0.5 * np.abs(weights).max())
        raise ValueError(
            f"the poses leave a combination of {', '.join(names[i] for i in big)} undetermined: "
            "add poses whose up directions differ (at least six, spanning all three axes)"
        )
    r = sol.fun
    dof = r.size - n_par
    chi2_dof = float(r @ r / dof)
    cov = np.linalg.inv(jtj) * max(1.0, chi2_dof)
    off, sc, a, up = unpack(sol.x)
    cov_x = cov[: 2 * n + n_z, : 2 * n + n_z]
    cov_a = q @ cov_x[2 * n :, 2 * n :] @ q.T
    resid = (r.reshape(k, n)) * sig
    return StaticCalibration(
        offset_mps2=off,
        offset_sigma_mps2=np.sqrt(np.diag(cov_x)[:n]),
        scale=sc,
        scale_sigma=np.sqrt(np.diag(cov_x)[n : 2 * n]),
        axis_error_rad=a,
        axis_error_sigma_rad=np.sqrt(np.diag(cov_a)).reshape(n, 2),
        cov=cov_x,
        up_b=up,
        residual_rms_mps2=np.sqrt(np.mean(resid**2, axis=0)),
        chi2_per_dof=chi2_dof,
        dof=dof,
    )
