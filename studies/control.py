"""A control for the consistency criterion: an exactly modelled filter on the same fixes.

The 50-run criterion reads one draw of GPS noise. Position and velocity errors
held by GPS averaging stay put for tens of seconds, so one draw can sit below
(or above) the chi-square bounds for most of a flight with no fault in the filter.
The control separates the draw from the filter: a linear Kalman filter that
knows the trajectory's shape exactly (a perfect array: the acceleration is known,
so there is no process noise) and learns the antenna's position and velocity
from the run's own fixes, with their own stated accuracies.

Its inputs are known and its model linear, so its estimate error depends only on
the fixes' noise and can be computed from the noise alone: the filter runs on
``z = fix - truth`` (noise), its estimate is its error, and the error's NEES is
exactly chi-square with 3 degrees of freedom per block at every fix, for any
trajectory. Its share of epochs inside the bounds over the same runs is what
the criterion reads, on this very draw, for a filter consistent by construction.
Where the navigation filter's position or velocity block misses and the control
misses with it, the miss is the draw.

Per fix: state ``[dp_ned (3), dv_ned (3)]``, transition ``[[I, dt I], [0, I]]``,
measurement ``I`` (6) with ``R = diag(h_acc^2, h_acc^2, v_acc^2, vel_acc^2 (3))``,
flat prior (the first fix initialises it: ``x = z_0``, ``P = R_0``); filterpy's
predict/update. Glitched fixes are not fused (the navigation filter rejects them),
the epoch is still counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update

from ngnav.geodesy import LocalTangentPlane
from ngnav.records import FlightTruth, GpsFixes, freeze_fields
from ngnav.sim.gps import antenna_truth
from ngnav.sim.simulate import SimulatedRun


@dataclass(frozen=True)
class ControlNees:
    """The control's NEES at each fix (after its update).

    Attributes
    ----------
    t_s : array (M,)
        Fix times (of validity), s.
    nees_pos, nees_vel : array (M,)
        NEES of the antenna position (3 dof) and velocity (3 dof) blocks.
    """

    t_s: np.ndarray
    nees_pos: np.ndarray
    nees_vel: np.ndarray

    def __post_init__(self) -> None:
        freeze_fields(self, {"t_s": (), "nees_pos": (), "nees_vel": ()})


def fix_noise(
    fixes: GpsFixes,
    truth: FlightTruth,
    ltp: LocalTangentPlane,
    antenna_b_m: np.ndarray | tuple[float, float, float],
) -> np.ndarray:
    """The fixes' errors (M, 6): antenna position (NED, m) and velocity (NED, m/s).

    Fixes must lie on the truth's sample times (a simulated run's do).
    """
    idx = np.searchsorted(truth.t_s, fixes.t_s)
    idx = np.clip(idx, 0, truth.t_s.shape[0] - 1)
    if len(fixes) and not np.allclose(truth.t_s[idx], fixes.t_s, rtol=0.0, atol=1e-9):
        raise ValueError("the fixes are not on the truth's sample times: no exact control")
    pos, vel = antenna_truth(truth, idx, antenna_b_m)
    ned = ltp.to_ned(fixes.lat_deg, fixes.lon_deg, fixes.alt_m)
    return np.hstack([ned - pos, fixes.vel_ned_mps - vel])


def perfect_array_control(
    fixes: GpsFixes,
    noise: np.ndarray,
    skip: np.ndarray | None = None,
) -> ControlNees:
    """Run the control (module docstring) on the fixes' noise.

    Parameters
    ----------
    fixes : GpsFixes
        The run's M fixes (times and stated accuracies).
    noise : array (M, 6)
        Their errors, :func:`fix_noise`.
    skip : array (M,) of bool, optional
        Fixes not fused (glitches); their epochs carry the predicted NEES.
    """
    return process_noise_control(fixes, noise, None, 0.0, skip)


#: White-acceleration power spectral density of :func:`process_noise_control`'s own
#: truth, m^2/s^3: of the order of what a GPS-aided array leaves in the velocity. The
#: control's position sigma hardly depends on it (0.170-0.173 m vertical for any value
#: in 1e-5..3e-3 at 10 Hz, 3 m and 0.1 m/s): it is set by the fixes' noise.
CONTROL_ACCEL_PSD = 1e-3
#: Seed of the control's own truth (with the run index): reproducible.
CONTROL_SEED = 99


def process_noise_control(
    fixes: GpsFixes,
    noise: np.ndarray,
    rng: np.random.Generator | None,
    accel_psd_m2ps3: float = CONTROL_ACCEL_PSD,
    skip: np.ndarray | None = None,
) -> ControlNees:
    """The control with process noise: consistent by construction, with a filter's time course.

    :func:`perfect_array_control` has no process noise, so its errors average every fix
    so far and change ever more slowly; a GPS-aided navigation filter's position error
    is an average over a window (its position variance settles at ``sqrt(q r)``, ``q``
    and ``r`` the power spectral densities of the fixes' velocity and position noise).
    This control has that course: its own truth, per axis ``[p, v]``, is driven by white
    acceleration of PSD ``accel_psd_m2ps3`` (drawn from ``rng``), the fixes are that
    truth plus the run's own fix noise, and a Kalman filter with exactly that model
    (filterpy's predict/update) estimates it. Its NEES is chi-square with 3 degrees of
    freedom per block at every fix; beside a navigation filter on the same fixes it shows,
    window by window, what the draw of the fixes alone does to the position and velocity
    blocks. With ``accel_psd_m2ps3`` 0 it is :func:`perfect_array_control`.

    Parameters
    ----------
    fixes, noise, skip
        As for :func:`perfect_array_control`.
    rng : numpy.random.Generator or None
        The control's own truth (one draw per fix interval); None only with a zero PSD.
    accel_psd_m2ps3 : float
        White-acceleration PSD of that truth, per axis, m^2/s^3 (>= 0).
    """
    if not (np.isfinite(accel_psd_m2ps3) and accel_psd_m2ps3 >= 0.0):
        raise ValueError(f"accel_psd_m2ps3 must be a finite number >= 0, got {accel_psd_m2ps3}")
    if rng is None and accel_psd_m2ps3 > 0.0:
        raise ValueError("process_noise_control needs an rng for a nonzero accel_psd_m2ps3")
    m = len(fixes)
    noise = np.asarray(noise, dtype=float)
    if noise.shape != (m, 6):
        raise ValueError(f"noise has shape {noise.shape}, expected ({m}, 6)")
    skip = np.zeros(m, dtype=bool) if skip is None else np.asarray(skip, dtype=bool)
    nees_pos = np.full(m, np.nan)
    nees_vel = np.full(m, np.nan)
    truth = np.zeros(6)
    x: np.ndarray | None = None
    p = np.zeros((6, 6))
    f = np.eye(6)
    h = np.eye(6)
    eye3 = np.eye(3)
    for k in range(m):
        r = np.diag(
            [fixes.h_acc_m[k] ** 2] * 2 + [fixes.v_acc_m[k] ** 2] + [fixes.vel_acc_mps[k] ** 2] * 3
        )
        if k:
            dt = float(fixes.t_s[k] - fixes.t_s[k - 1])
            f[0:3, 3:6] = eye3 * dt
            q = np.zeros((6, 6))
            q[0:3, 0:3] = eye3 * (accel_psd_m2ps3 * dt**3 / 3.0)
            q[0:3, 3:6] = q[3:6, 0:3] = eye3 * (accel_psd_m2ps3 * dt**2 / 2.0)
            q[3:6, 3:6] = eye3 * (accel_psd_m2ps3 * dt)
            truth = f @ truth
            if rng is not None and accel_psd_m2ps3 > 0.0:
                truth = truth + np.linalg.cholesky(q) @ rng.standard_normal(6)
            if x is not None:
                x, p = kf_predict(x, p, f, q)
        if not skip[k]:
            z = truth + noise[k]
            if x is None:
                x, p = z.copy(), r
            else:
                x, p = kf_update(x, p, z, r, h)
        if x is None:
            continue
        e = x - truth
        nees_pos[k] = e[0:3] @ np.linalg.solve(p[0:3, 0:3], e[0:3])
        nees_vel[k] = e[3:6] @ np.linalg.solve(p[3:6, 3:6], e[3:6])
    return ControlNees(np.asarray(fixes.t_s, dtype=float), nees_pos, nees_vel)


def control_extras(sim: SimulatedRun, i: int) -> dict:
    """Both controls on run ``i``'s own fixes, as entries of its Monte Carlo record.

    The hook :func:`filters.consistency.monte_carlo_runs` adds to each run
    (``extras``): ``control_pos``, ``control_vel`` (:func:`perfect_array_control`,
    glitched fixes not fused), ``control_pos-pn``, ``control_vel-pn``
    (:func:`process_noise_control`, its own truth from ``default_rng([CONTROL_SEED,
    i])``) and ``control_t_s``, the fix times.
    """
    cfg = sim.config
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    fix_err = fix_noise(sim.fixes, sim.truth, ltp, cfg.antenna_b_m)
    control = perfect_array_control(sim.fixes, fix_err, sim.glitched)
    control_pn = process_noise_control(
        sim.fixes, fix_err, np.random.default_rng([CONTROL_SEED, i]), skip=sim.glitched
    )
    return {
        "control_pos": control.nees_pos,
        "control_vel": control.nees_vel,
        "control_t_s": control.t_s,
        "control_pos-pn": control_pn.nees_pos,
        "control_vel-pn": control_pn.nees_vel,
    }
