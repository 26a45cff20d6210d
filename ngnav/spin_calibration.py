"""Sensor positions from a rate table: poses spun at known constant rates.

At rest no channel sees where its sensitive element sits. Spun at a constant rate
``w`` (body frame) about a vertical table axis ``a``, a channel with axis ``u_i`` at
position ``r_i`` reads ``o_i + s_i u_i . (f + M r_i)``, ``M = w w^T - |w|^2 I``: the
centripetal term carries the position. The specific force at the array's reference point
is ``f = g0 a + M d``: gravity along the table's axis, and the reference point's own
centripetal term (``d`` its offset from the axis, never known, fitted per pose). The
axis is the given one turned by one rotation common to every pose (the calibration
frame's turn from the mechanical frame the axes are given in) and tilted by the fixture's
small tolerance per pose (:data:`SPIN_AXIS_SIGMA_RAD`); its rate is known.
``M u_i = -|w|^2 (u_i - a (a . u_i))``: an axis across ``u_i`` shows ``r_i`` along
``u_i``; the components across it need axes oblique to it, so a set such as the three
body axes and the six face diagonals determines every sensor's position. (With ``f``
free per pose instead, the sensors sharing an axis could move together unseen: only
they read ``f`` along it.)

A common translation of every sensor moves the reference point, which reads the same as a
change of each pose's ``d``: it is not observable, and the fitted corrections carry none
(their mean is zero; the drawings keep the reference point). The offsets, scales and axis
errors enter through the static fit's result and its full covariance, as a prior (the
calibration keeps the static fit's values and sigmas).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ngnav.conventions import G0_MPS2
from ngnav.layout import ArrayLayout
from ngnav.mounting import perpendicular_basis
from ngnav.static_calibration import MAX_CONDITION, StaticCalibration, _axes, gauge_basis

_AXES = "xyz"
#: Prior 1-sigma of each spin pose's table axis about the given direction, rad, beyond one
#: rotation common to every pose (the calibration frame's turn from the mechanical frame
#: the axes are given in, fitted freely): the fixture's tolerance, 0.06 deg. The readings
#: alone hardly split a pose's own tilt from the reference point's offset from the axis
#: (both move the force across the axis): left free, that split wandered a degree and
#: more, and the positions' covariance, linear about it, came out 2-3 times too small.
SPIN_AXIS_SIGMA_RAD = 0.001
#: Prior 1-sigma of the reference point's offset from the table's axis, m, per direction
#: (a loose bound: a fixture keeps the array within centimetres of the axis).
SPIN_OFFSET_SIGMA_M = 0.05


@dataclass(frozen=True)
class SpinCalibration:
    """Result of :func:`fit_spin_poses` (N sensors, K spin poses), with 1-sigmas.

    Attributes
    ----------
    position_correction_b_m, position_sigma_b_m : arrays (N, 3)
        Each sensitive element's position minus the one given (nominal plus the
        drawings' ``position_error_b_m``), body FRD, m; zero mean over the sensors.
    position_cov_m2 : array (3N, 3N)
        Their covariance (sensor-major), rank 3N - 3 (no common translation).
    force_b_mps2 : array (K, 3)
        Each pose's fitted specific force at the reference point, m/s^2.
    chi2_per_dof : float
        As for the static fit; the sigmas grow with its square root above 1.
    dof : int
        Spin readings less the parameters only they determine.
    """

    position_correction_b_m: np.ndarray
    position_sigma_b_m: np.ndarray
    position_cov_m2: np.ndarray
    force_b_mps2: np.ndarray
    chi2_per_dof: float
    dof: int


def offset_drift_var(
    bias_rw_mps2_rts: np.ndarray, static_t_s: tuple[float, float], spin_t_s: tuple[float, float]
) -> np.ndarray:
    """The offsets' walk between a static session and a spin session (first and last times
    of each, s, on one clock): ``q^2 dt``, ``dt`` between their middles."""
    dt = abs(0.5 * (spin_t_s[0] + spin_t_s[1]) - 0.5 * (static_t_s[0] + static_t_s[1]))
    return np.asarray(bias_rw_mps2_rts, dtype=float) ** 2 * dt


def read_spin_pose(csv_path) -> np.ndarray:
    """A spin recording's rate vector (3,), body frame, rad/s, from the TOML beside it.

    ``NAME.toml`` holds ``axis_b`` (the table's axis in the array's body frame, FRD; any
    length) and ``rate_dps`` (signed, right-handed about ``axis_b``); without
    ``rate_dps`` the rate is read from a file name ending ``_<rate>dps``.
    """
    import re
    from pathlib import Path

    from ngnav.config import read_toml_file

    p = Path(csv_path)
    meta = p.with_suffix(".toml")
    data = read_toml_file(meta, f"{p}: no {meta.name} beside it (axis_b, rate_dps)")
    try:
        axis = np.asarray(data.get("axis_b", []), dtype=float)
    except (TypeError, ValueError):
        axis = np.zeros(0)
    if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
        raise ValueError(f"{meta}: axis_b must be 3 finite numbers, not all zero")
    rate = data.get("rate_dps")
    if rate is None:
        m = re.search(r"_(-?[0-9.]+)dps$", p.stem)
        if m is None:
            raise ValueError(f"{meta}: missing rate_dps (or a file name ending _<rate>dps)")
        rate = float(m.group(1))
    try:
        rate = float(rate)
    except (TypeError, ValueError):
        rate = float("nan")
    if not np.isfinite(rate) or rate == 0:
        raise ValueError(f"{meta}: rate_dps must be a non-zero number, got {rate}")
    return np.deg2rad(rate) * axis / np.linalg.norm(axis)


def translation_free_basis(n: int) -> np.ndarray:
    """Orthonormal basis (3N, 3N - 3) of position corrections with no common translation."""
    t = np.tile(np.eye(3), (n, 1))  # (3N, 3): every sensor moved by the same vector
    u, _, _ = np.linalg.svd(t, full_matrices=True)
    return u[:, 3:]


def fit_spin_poses(
    means_mps2: np.ndarray,
    sigma_mps2: np.ndarray,
    rate_b_rps: np.ndarray,
    layout: ArrayLayout,
    position_error_b_m: np.ndarray,
    static: StaticCalibration,
    offset_drift_var_mps2: np.ndarray | float = 0.0,
) -> SpinCalibration:
    """Fit each sensor's position correction to the mean readings of K spin poses.

    Parameters
    ----------
    means_mps2, sigma_mps2 : arrays (K, N)
        Each pose's mean channel outputs and their 1-sigma, m/s^2.
    rate_b_rps : array (K, 3)
        Each pose's constant rate vector in the array's body frame, rad/s.
    layout : ArrayLayout
        The nominal layout.
    position_error_b_m : array (N, 3)
        The drawings' offsets from the nominal positions (the positions given), m.
    static : StaticCalibration
        The static fit (:func:`ngnav.static_calibration.fit_static_poses`): its values
        and covariance are the prior of the offsets, scales and axis errors.
    offset_drift_var_mps2 : array (N,) or float
        What the offsets walked between the static poses and the spin poses, (m/s^2)^2
        (``q^2 dt``, ``dt`` between the two sessions' middles; :func:`offset_drift_var`):
        one change per channel, common to every spin pose, added to the offsets' prior.

    Raises
    ------
    ValueError
        Too few readings, or spin axes that leave a sensor's position undetermined
        (named, with what would determine it).
    """
    v = np.asarray(means_mps2, dtype=float)
    sig = np.asarray(sigma_mps2, dtype=float)
    w = np.asarray(rate_b_rps, dtype=float).reshape(-1, 3)
    k, n = v.shape
    if n != layout.n_sensors or sig.shape != v.shape or w.shape[0] != k:
        raise ValueError(
            f"spin means and sigmas must be (K, {layout.n_sensors}) with K rate vectors, got "
            f"{v.shape}, {sig.shape}, {w.shape}"
        )
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(sig)) and np.all(sig > 0)):
        raise ValueError("spin pose means must be finite and their sigmas positive")
    if np.any(np.linalg.norm(w, axis=1) <= 0):
        raise ValueError("every spin pose needs a non-zero rate")
    q = gauge_basis(layout)
    n_z = q.shape[1]
    n_s = 2 * n + n_z  # the static parameters: offset, scale, axis errors (gauge basis)
    b = translation_free_basis(n)
    n_p = b.shape[1]
    dof = k * n - n_p - 2 * k - 3
    if dof <= 0:
        raise ValueError(
            f"{k} spin poses give {k * n} readings for {n_p + 2 * k + 3} position, axis and "
            f"offset-from-the-axis parameters: at least {(n_p + 3) // (n - 2) + 1} poses are "
            "needed"
        )
    s0 = np.concatenate(
        [static.offset_mps2, static.scale, np.linalg.lstsq(q, static.axis_error_rad.ravel())[0]]
    )
    # the prior's whitening: L^-1 (x_s - s0) with the static covariance L L^T
    prior = static.cov.copy()
    prior[:n, :n] += np.diag(np.broadcast_to(offset_drift_var_mps2, (n,)))
    lw = np.linalg.inv(np.linalg.cholesky(prior))
    r_given = layout.positions_b_m + np.asarray(position_error_b_m, dtype=float)
    rate = np.linalg.norm(w, axis=1)
    axis0 = w / rate[:, None]
    e1, e2 = perpendicular_basis(axis0)

    def table(rot: np.ndarray, t: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # each pose's M = w w^T - |w|^2 I and f = g0 a + M d, its axis turned by the common
        # rotation rot (3,) and tilted by t (K, 2), the reference point d (K, 2) off it
        ax = axis0 + np.cross(rot, axis0) + t[:, :1] * e1 + t[:, 1:] * e2
        ax /= np.linalg.norm(ax, axis=1, keepdims=True)
        wv = rate[:, None] * ax
        mw = np.einsum("ki,kj->kij", wv, wv) - (rate**2)[:, None, None] * np.eye(3)
        f = G0_MPS2 * ax + np.einsum("kab,kb->ka", mw, d[:, :1] * e1 + d[:, 1:] * e2)
        return mw, f

    n_f = n_s + n_p

    def unpack(x):
        off, sc = x[:n], x[n : 2 * n]
        a = (q @ x[2 * n : n_s]).reshape(n, 2)
        dr = (b @ x[n_s:n_f]).reshape(n, 3)
        rot = x[n_f : n_f + 3]
        t = x[n_f + 3 : n_f + 3 + 2 * k].reshape(k, 2)
        return off, sc, a, dr, rot, t, x[n_f + 3 + 2 * k :].reshape(k, 2)

    def residuals(x):
        off, sc, a, dr, rot, t, d = unpack(x)
        u = _axes(layout, a)  # (N, 3)
        mw, f = table(rot, t, d)
        acc = f[:, None, :] + np.einsum("kab,nb->kna", mw, r_given + dr)  # (K, N, 3)
        model = off + sc * np.einsum("kna,na->kn", acc, u)
        return np.concatenate(
            [
                ((model - v) / sig).ravel(),
                lw @ (x[:n_s] - s0),
                t.ravel() / SPIN_AXIS_SIGMA_RAD,
                d.ravel() / SPIN_OFFSET_SIGMA_M,
            ]
        )

    x0 = np.concatenate([s0, np.zeros(n_p + 3 + 4 * k)])
    sol = least_squares(
        residuals, x0, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    jtj = sol.jac.T @ sol.jac
    ev, vecs = np.linalg.eigh(jtj / np.sqrt(np.outer(np.diag(jtj), np.diag(jtj))))
    if ev[0] <= ev[-1] / MAX_CONDITION:
        mix = b @ vecs[n_s : n_s + n_p, 0]
        i = int(np.argmax(np.abs(mix)))
        raise ValueError(
            f"the spin poses leave sensor {i // 3 + 1}'s position along body {_AXES[i % 3]} "
            "undetermined: add spin axes oblique to its sensing axis (e.g. the face diagonals)"
        )
    r = sol.fun[: k * n]
    chi2_dof = float(r @ r / dof)
    # inverted at unit diagonal: the parameters' scales span ten decades
    sd = 1.0 / np.sqrt(np.diag(jtj))
    cov = sd[:, None] * np.linalg.inv(sd[:, None] * jtj * sd) * sd * max(1.0, chi2_dof)
    _, _, _, dr, rot, t, d = unpack(sol.x)
    cov_dr = b @ cov[n_s : n_s + n_p, n_s : n_s + n_p] @ b.T
    return SpinCalibration(
        position_correction_b_m=dr,
        position_sigma_b_m=np.sqrt(np.diag(cov_dr)).reshape(n, 3),
        position_cov_m2=cov_dr,
        force_b_mps2=table(rot, t, d)[1],
        chi2_per_dof=chi2_dof,
        dof=dof,
    )
