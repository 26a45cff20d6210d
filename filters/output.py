"""``estimates.csv``: the filter's output, one row per filter epoch.

Columns (the contract), then extras::

    t_s, lat_deg, lon_deg, alt_m, n_m, e_m, d_m, vn_mps, ve_mps, vd_mps,
    qw, qx, qy, qz, wx_radps, wy_radps, wz_radps,
    lat_deg_sigma, lon_deg_sigma, alt_m_sigma, n_m_sigma, e_m_sigma, d_m_sigma,
    vn_mps_sigma, ve_mps_sigma, vd_mps_sigma,
    att_n_rad_sigma, att_e_rad_sigma, att_d_rad_sigma,
    wx_radps_sigma, wy_radps_sigma, wz_radps_sigma,
    roll_deg, pitch_deg, yaw_deg, aoa_deg, aoa_deg_sigma

``aoa_deg`` and its 1-sigma are the angle-of-attack state (nose above the flight
path, deg), or empty (NaN) when the filter does not carry it.

The attitude's uncertainty is given as the 1-sigma of the NED rotation-vector
error (``q_true = exp(dtheta) * q_est``), not per quaternion component; for
small tilt ``att_n``, ``att_e``, ``att_d`` are roll, pitch and yaw.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ngnav.geodesy import WGS84_A_M, WGS84_E2, LocalTangentPlane
from ngnav.records import Estimates
from ngnav.rotation import euler_from_quat
from ngnav.runconfig import RunConfig
from ngnav.runio import NAV_COLUMNS

ESTIMATE_COLUMNS: tuple[str, ...] = (
    "t_s",
    "lat_deg",
    "lon_deg",
    "alt_m",
    *NAV_COLUMNS,
    "lat_deg_sigma",
    "lon_deg_sigma",
    "alt_m_sigma",
    "n_m_sigma",
    "e_m_sigma",
    "d_m_sigma",
    "vn_mps_sigma",
    "ve_mps_sigma",
    "vd_mps_sigma",
    "att_n_rad_sigma",
    "att_e_rad_sigma",
    "att_d_rad_sigma",
    "wx_radps_sigma",
    "wy_radps_sigma",
    "wz_radps_sigma",
    "roll_deg",
    "pitch_deg",
    "yaw_deg",
    "aoa_deg",
    "aoa_deg_sigma",
)


def estimates_table(est: Estimates, cfg: RunConfig) -> np.ndarray:
    """The rows (E, len(ESTIMATE_COLUMNS)) of ``estimates.csv``."""
    ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
    lat, lon, alt = ltp.to_geodetic(est.pos_ned_m)
    sig = np.sqrt(np.einsum("eii->ei", est.cov_nav))
    sl = np.sin(np.deg2rad(lat))
    rn = WGS84_A_M / np.sqrt(1 - WGS84_E2 * sl * sl)
    rm = rn * (1 - WGS84_E2) / (1 - WGS84_E2 * sl * sl)
    lat_sig = np.rad2deg(sig[:, 0] / (rm + alt))
    lon_sig = np.rad2deg(sig[:, 1] / ((rn + alt) * np.cos(np.deg2rad(lat))))
    rpy = np.rad2deg(euler_from_quat(est.q_nb))
    nan = np.full(est.t_s.shape, np.nan)
    aoa = (nan, nan) if est.aoa_rad is None else (est.aoa_rad, est.aoa_sigma_rad)
    return np.column_stack(
        [
            est.t_s,
            lat,
            lon,
            alt,
            est.pos_ned_m,
            est.vel_ned_mps,
            est.q_nb,
            est.omega_b_rps,
            lat_sig,
            lon_sig,
            sig[:, 2],
            sig[:, 0:3],
            sig[:, 3:6],
            sig[:, 6:9],
            sig[:, 9:12],
            rpy,
            np.rad2deg(aoa[0]),
            np.rad2deg(aoa[1]),
        ]
    )


def write_estimates_csv(path: str | Path, est: Estimates, cfg: RunConfig) -> None:
    """Write ``estimates.csv`` (see the module docstring)."""
    fmt = ["%.6f", "%.10f", "%.10f"] + ["%.6g"] * (len(ESTIMATE_COLUMNS) - 3)
    np.savetxt(
        Path(path),
        estimates_table(est, cfg),
        delimiter=",",
        header=",".join(ESTIMATE_COLUMNS),
        comments="",
        fmt=fmt,
    )
