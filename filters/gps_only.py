"""GPS alone: a constant-velocity Kalman filter on the fixes (the no-array baseline).

Per axis position and velocity, white acceleration of ``accel_sigma_mps2``
(spectral density ``sigma^2`` per second); filterpy's predict/update at the
fix times. No attitude or rate: GPS alone cannot give them.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update

from ngnav.geodesy import LocalTangentPlane
from ngnav.records import GpsFixes


def run_gps_only(
    fixes: GpsFixes,
    lat0_deg: float,
    lon0_deg: float,
    alt0_m: float,
    t_out_s: np.ndarray,
    accel_sigma_mps2: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position (E, 3) and velocity (E, 3), NED, and their variances (E, 6) at ``t_out_s``.

    Between fixes the last estimate is predicted forward to each output time.
    Antenna position is taken as the vehicle's (no attitude to move it).
    """
    if len(fixes) == 0:
        raise ValueError("GPS alone needs at least one fix")
    ltp = LocalTangentPlane(lat0_deg, lon0_deg, alt0_m)
    z_pos = ltp.to_ned(fixes.lat_deg, fixes.lon_deg, fixes.alt_m)
    x = np.concatenate([z_pos[0], fixes.vel_ned_mps[0]])
    p = np.diag(
        np.concatenate(
            [[fixes.h_acc_m[0] ** 2] * 2, [fixes.v_acc_m[0] ** 2], [fixes.vel_acc_mps[0] ** 2] * 3]
        )
    )
    t_state = fixes.t_s[0]
    q_psd = accel_sigma_mps2**2
    h = np.eye(6)

    def step(x, p, dt):
        f = np.eye(6)
        f[0:3, 3:6] = np.eye(3) * dt
        q = np.zeros((6, 6))
        q[0:3, 0:3] = np.eye(3) * q_psd * dt**3 / 3
        q[0:3, 3:6] = q[3:6, 0:3] = np.eye(3) * q_psd * dt**2 / 2
        q[3:6, 3:6] = np.eye(3) * q_psd * dt
        return kf_predict(x, p, f, q)

    out_p = np.empty((t_out_s.shape[0], 3))
    out_v = np.empty((t_out_s.shape[0], 3))
    out_var = np.empty((t_out_s.shape[0], 6))
    m = 1
    for e, te in enumerate(t_out_s):
        while m < len(fixes) and fixes.t_s[m] <= te:
            x, p = step(x, p, fixes.t_s[m] - t_state)
            t_state = fixes.t_s[m]
            r = np.diag(
                np.concatenate(
                    [
                        [fixes.h_acc_m[m] ** 2] * 2,
                        [fixes.v_acc_m[m] ** 2],
                        [fixes.vel_acc_mps[m] ** 2] * 3,
                    ]
                )
            )
            z = np.concatenate([z_pos[m], fixes.vel_ned_mps[m]])
            x, p = kf_update(x, p, z, r, h)
            m += 1
        xo, po = step(x, p, te - t_state) if te > t_state else (x, p)
        out_p[e], out_v[e], out_var[e] = xo[0:3], xo[3:6], np.diag(po)
    return out_p, out_v, out_var
