"""``estimates.csv``: the filter's output, one row per filter epoch.

Columns (the contract), then extras::

    t_s, lat_deg, lon_deg, alt_m, n_m, e_m, d_m, vn_mps, ve_mps, vd_mps,
    qw, qx, qy, qz, wx_radps, wy_radps, wz_radps,
    lat_deg_sigma, lon_deg_sigma, alt_m_sigma, n_m_sigma, e_m_sigma, d_m_sigma,
    vn_mps_sigma, ve_mps_sigma, vd_mps_sigma,
    att_n_rad_sigma, att_e_rad_sigma, att_d_rad_sigma,
    wx_radps_sigma, wy_radps_sigma, wz_radps_sigma,
    roll_deg, pitch_deg, yaw_deg, aoa_deg, aoa_deg_sigma, faulty_channels, valid

``aoa_deg`` and its 1-sigma are the angle-of-attack state (nose above the flight
path, deg), or empty (NaN) when the filter does not carry it. ``faulty_channels`` is
a bitmask, bit ``i`` for channel ``i + 1``: held in that epoch's block (non-finite or
saturated), excluded as failed or suspected by the parity (:mod:`filters.faults`); 0
on a healthy array. ``valid`` is 1, or 0 for the epochs after the filter started again
from a lost track until its attitude's 1-sigma is back (:mod:`filters.recovery`; no rows
are written while the track is lost). A file without these columns (an older one) reads
as 0 and 1.

The attitude's uncertainty is given as the 1-sigma of the NED rotation-vector
error (``q_true = exp(dtheta) * q_est``), not per quaternion component; for
small tilt ``att_n``, ``att_e``, ``att_d`` are roll, pitch and yaw.

Beside it ``ngnav run`` writes ``estimates.nis.csv`` (:func:`nis_path`), one row per
GPS fix the filter saw: ``t_s, nis_pos, nis_vel, pos_accepted, vel_accepted`` (the
innovations' NIS, 3 dof each, before the update; 1/0 whether each passed its gate), and
``estimates.npz`` (:func:`write_estimates_npz`): the same epochs with their full
navigation covariance, and the last epoch's whole error state.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ngnav.geodesy import WGS84_A_M, WGS84_E2, LocalTangentPlane
from ngnav.records import Estimates, GpsInnovations, NavEstimate, RunResult
from ngnav.rotation import euler_from_quat
from ngnav.runconfig import RunConfig
from ngnav.runio import NAV_COLUMNS, read_table

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
    "faulty_channels",
    "valid",
)
#: Columns a file must have (the faulty-channels and valid columns came later).
_REQUIRED_COLUMNS = ESTIMATE_COLUMNS[:-2]


#: The 1-sigma columns of the 12 navigation errors, in the state's order.
NAV_SIGMA_COLUMNS: tuple[str, ...] = ESTIMATE_COLUMNS[20:32]


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
    faulty = np.zeros(est.t_s.shape) if est.faulty_channels is None else est.faulty_channels
    valid = np.ones(est.t_s.shape) if est.valid is None else est.valid
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
            faulty,
            valid,
        ]
    )


def write_estimates_csv(path: str | Path, est: Estimates, cfg: RunConfig) -> None:
    """Write ``estimates.csv`` (see the module docstring)."""
    fmt = ["%.6f", "%.10f", "%.10f"] + ["%.6g"] * (len(ESTIMATE_COLUMNS) - 5) + ["%d", "%d"]
    np.savetxt(
        Path(path),
        estimates_table(est, cfg),
        delimiter=",",
        header=",".join(ESTIMATE_COLUMNS),
        comments="",
        fmt=fmt,
    )


def read_estimates_csv(path: str | Path) -> Estimates:
    """Read an ``estimates.csv`` back as :class:`Estimates`.

    The file keeps each block's 1-sigma, not its correlations: ``cov_nav`` is the
    diagonal ``sigma^2`` (position, velocity, NED attitude, rate). A missing column
    or a bad cell is a ``ValueError`` naming it.
    """
    header, data = read_table(Path(path), _REQUIRED_COLUMNS)
    col = {name: data[:, header.index(name)] for name in ESTIMATE_COLUMNS if name in header}
    if data.shape[0] == 0:
        raise ValueError(f"{path}: no estimates")

    def stack(*names: str) -> np.ndarray:
        return np.column_stack([col[n] for n in names])

    sig = stack(*NAV_SIGMA_COLUMNS)
    cov = np.zeros((data.shape[0], 12, 12))
    idx = np.arange(12)
    cov[:, idx, idx] = sig * sig
    aoa = col["aoa_deg"]
    has_aoa = bool(np.any(np.isfinite(aoa)))
    return Estimates(
        col["t_s"],
        stack("n_m", "e_m", "d_m"),
        stack("vn_mps", "ve_mps", "vd_mps"),
        stack("qw", "qx", "qy", "qz"),
        stack("wx_radps", "wy_radps", "wz_radps"),
        np.zeros((data.shape[0], 0)),
        cov,
        aoa_rad=np.deg2rad(aoa) if has_aoa else None,
        aoa_sigma_rad=np.deg2rad(col["aoa_deg_sigma"]) if has_aoa else None,
        faulty_channels=col.get("faulty_channels", np.zeros(data.shape[0])).astype(np.int64),
        valid=col.get("valid", np.ones(data.shape[0])) != 0,
    )


#: Columns of ``estimates.nis.csv``.
NIS_COLUMNS: tuple[str, ...] = ("t_s", "nis_pos", "nis_vel", "pos_accepted", "vel_accepted")


def nis_path(estimates_path: str | Path) -> Path:
    """Where the GPS fixes' NIS go beside an estimates file: ``NAME.nis.csv``."""
    p = Path(estimates_path)
    return p.with_name(p.stem + ".nis.csv")


def write_nis_csv(path: str | Path, inn: GpsInnovations) -> None:
    """Write the GPS fixes' NIS and gate decisions (see the module docstring)."""
    rows = np.column_stack(
        [inn.t_s, inn.nis_pos, inn.nis_vel, inn.pos_accepted, inn.vel_accepted]
    ).reshape(-1, len(NIS_COLUMNS))
    np.savetxt(
        Path(path),
        rows,
        delimiter=",",
        header=",".join(NIS_COLUMNS),
        comments="",
        fmt=["%.6f", "%.6g", "%.6g", "%d", "%d"],
    )


def read_nis_csv(path: str | Path) -> GpsInnovations:
    """Read ``estimates.nis.csv`` back as :class:`GpsInnovations`."""
    header, data = read_table(Path(path), NIS_COLUMNS)
    col = {name: data[:, header.index(name)] for name in NIS_COLUMNS}
    return GpsInnovations(
        col["t_s"],
        col["nis_pos"],
        col["nis_vel"],
        col["pos_accepted"] > 0.5,
        col["vel_accepted"] > 0.5,
    )


#: Format version of ``estimates.npz`` (bumped when a key changes meaning).
NPZ_VERSION = 1


def npz_path(estimates_path: str | Path) -> Path:
    """Where the binary estimates go beside an estimates file: ``NAME.npz``."""
    return Path(estimates_path).with_suffix(".npz")


def write_estimates_npz(path: str | Path, res: RunResult) -> None:
    """Write ``estimates.npz``: every epoch with its full 12 x 12 navigation covariance,
    and the last epoch's whole error state with its covariance (compressed numpy arrays).

    Keys: ``t_s`` (E,), ``pos_ned_m``, ``vel_ned_mps``, ``omega_b_rps`` (E, 3),
    ``q_nb`` (E, 4), ``bias`` (E, k), ``cov_nav`` (E, 12, 12) (position m, velocity m/s,
    NED attitude rad, rate rad/s, with their correlations), ``aoa_rad`` and
    ``aoa_sigma_rad`` (E,) when carried; ``faulty_channels`` and ``valid`` (E,) when kept; the last
    epoch's ``final_cov`` (n, n) in the order of ``final_blocks`` (names) and
    ``final_dofs``, with ``final_dr_m``, ``final_axis_error_b`` and ``final_aoa_states``
    when carried;
    ``version``. Read it with :func:`read_estimates_npz`.
    """
    est = res.estimates
    arrays = {
        "version": np.array(NPZ_VERSION),
        "t_s": est.t_s,
        "pos_ned_m": est.pos_ned_m,
        "vel_ned_mps": est.vel_ned_mps,
        "q_nb": est.q_nb,
        "omega_b_rps": est.omega_b_rps,
        "bias": est.bias,
        "cov_nav": est.cov_nav,
    }
    if est.aoa_rad is not None:
        arrays["aoa_rad"] = est.aoa_rad
        arrays["aoa_sigma_rad"] = est.aoa_sigma_rad
    if est.faulty_channels is not None:
        arrays["faulty_channels"] = est.faulty_channels
    if est.valid is not None:
        arrays["valid"] = est.valid
    fin = res.final
    if fin is not None:
        arrays["final_cov"] = fin.cov
        arrays["final_blocks"] = np.array([name for name, _ in fin.state_blocks])
        arrays["final_dofs"] = np.array([dof for _, dof in fin.state_blocks])
        for key, value in (
            ("final_dr_m", fin.dr_m),
            ("final_axis_error_b", fin.axis_error_b),
            ("final_aoa_states", fin.aoa_states),
        ):
            if value is not None:
                arrays[key] = value
    np.savez_compressed(Path(path), **arrays)


def read_estimates_npz(path: str | Path) -> tuple[Estimates, NavEstimate | None]:
    """Read ``estimates.npz`` (:func:`write_estimates_npz`): the epochs as
    :class:`Estimates` (full navigation covariance), and the last epoch as a
    :class:`NavEstimate` with the whole state's covariance (None if the file has none)."""
    p = Path(path)
    try:
        data = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: not an estimates file ({exc})") from None
    with data:
        if "version" not in data.files or int(data["version"]) != NPZ_VERSION:
            raise ValueError(f"{p}: not an ngnav estimates file of version {NPZ_VERSION}")
        get = {k: data[k] for k in data.files}
    est = Estimates(
        get["t_s"],
        get["pos_ned_m"],
        get["vel_ned_mps"],
        get["q_nb"],
        get["omega_b_rps"],
        get["bias"],
        get["cov_nav"],
        aoa_rad=get.get("aoa_rad"),
        aoa_sigma_rad=get.get("aoa_sigma_rad"),
        faulty_channels=get.get("faulty_channels"),
        valid=get.get("valid"),
    )
    if "final_cov" not in get:
        return est, None
    blocks = tuple(
        (str(n), int(d)) for n, d in zip(get["final_blocks"], get["final_dofs"], strict=True)
    )
    aoa = None if est.aoa_rad is None else (float(est.aoa_rad[-1]), float(est.aoa_sigma_rad[-1]))
    final = NavEstimate(
        float(est.t_s[-1]),
        est.pos_ned_m[-1],
        est.vel_ned_mps[-1],
        est.q_nb[-1],
        est.omega_b_rps[-1],
        est.bias[-1],
        get["final_cov"],
        aoa_rad=None if aoa is None else aoa[0],
        aoa_sigma_rad=None if aoa is None else aoa[1],
        state_blocks=blocks,
        dr_m=get.get("final_dr_m"),
        axis_error_b=get.get("final_axis_error_b"),
        aoa_states=get.get("final_aoa_states"),
    )
    return est, final
