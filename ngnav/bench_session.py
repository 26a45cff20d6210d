"""A bench session read from its directory and calibrated (``ngnav calibrate``, ``api.calibrate``).

The directory holds the array's ``config.toml`` (``[array]``, ``[sensor]``, optionally
the drawings' ``[calibration]``), the static poses (``static/*.csv``, one per pose, or
one ``array.csv`` whose still stretches are the poses) and, optionally, rate-table poses
(``spin/*.csv`` with a ``.toml`` beside each). The result holds both fits and the
``[calibration]`` section a run's ``config.toml`` takes as it is.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ngnav.recordings import Poses, poses_from_files, poses_from_recording
from ngnav.runconfig import ArrayConfig, read_array_config
from ngnav.runio import read_array_csv
from ngnav.spin_calibration import (
    SpinCalibration,
    fit_spin_poses,
    offset_drift_var,
    read_spin_pose,
)
from ngnav.static_calibration import StaticCalibration, fit_static_poses


@dataclass(frozen=True)
class BenchCalibration:
    """A calibrated bench session.

    Attributes
    ----------
    config : ArrayConfig
        The directory's ``config.toml`` (layout, sensor noise, the drawings).
    poses, static : Poses, StaticCalibration
        The static poses found (and skipped, with reasons) and their fit.
    spin_poses, spin : Poses, SpinCalibration, or None
        The same for the rate-table poses, when there are any.
    source : str
        Where the static poses came from, for a report.
    section : str
        The ``[calibration]`` section (:func:`calibration_toml`).
    """

    config: ArrayConfig
    poses: Poses
    static: StaticCalibration
    spin_poses: Poses | None
    spin: SpinCalibration | None
    source: str
    section: str


def calibrate_bench(
    directory: str | Path, progress: Callable[[float], None] | None = None
) -> BenchCalibration:
    """Read a bench session's directory and fit it (see the module docstring).

    ``progress`` is called with the fraction of recordings read. Raises ValueError (one
    line) for a directory that is not a session, no usable pose, or poses that leave a
    parameter undetermined.
    """
    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"{d}: not a directory (config.toml, and static/*.csv or array.csv)")
    cfg = read_array_config(d / "config.toml")
    n = cfg.layout.n_sensors
    noise = (cfg.noise_sigma_mps2, cfg.bias_rw_mps2_rts, cfg.range_mps2)
    files = sorted((d / "static").glob("*.csv")) if (d / "static").is_dir() else []
    spin_files = sorted((d / "spin").glob("*.csv")) if (d / "spin").is_dir() else []
    if not files and not (d / "array.csv").is_file():
        raise ValueError(f"{d}: no recordings: give static/*.csv (one per pose) or array.csv")
    paths = (files or [d / "array.csv"]) + spin_files
    read = {}
    for j, p in enumerate(paths):
        read[p] = read_array_csv(p, n)[0]
        if progress is not None:
            progress((j + 1) / len(paths))
    if files:
        poses = poses_from_files([(p.name, read[p]) for p in files], *noise)
        source = f"{len(files)} files in {d / 'static'}"
    else:
        poses = poses_from_recording(read[d / "array.csv"], *noise)
        source = f"the still stretches of {d / 'array.csv'}"
    if poses.means_mps2.shape[0] == 0:
        first = f"; {poses.skipped[0]}" if poses.skipped else ""
        raise ValueError(f"{d}: no usable pose ({len(poses.skipped)} skipped{first})")
    static = fit_static_poses(poses.means_mps2, poses.sigma_mps2, cfg.layout)
    spin, spin_poses = None, None
    if spin_files:
        rates = {p.name: read_spin_pose(p) for p in spin_files}
        spin_poses = poses_from_files([(p.name, read[p]) for p in spin_files], *noise)
        # the offsets walked from the static session to the spin one (times on one clock)
        static_t = [read[p].t_s for p in paths if p not in spin_files]
        spin_t = [read[p].t_s for p in spin_files]
        drift = offset_drift_var(
            cfg.bias_rw_mps2_rts,
            (min(t[0] for t in static_t), max(t[-1] for t in static_t)),
            (min(t[0] for t in spin_t), max(t[-1] for t in spin_t)),
        )
        used = [lab.split(" ")[0] for lab in spin_poses.labels]
        spin = fit_spin_poses(
            spin_poses.means_mps2,
            spin_poses.sigma_mps2,
            np.array([rates[name] for name in used]).reshape(-1, 3),
            cfg.layout,
            cfg.position_error_b_m,
            static,
            drift,
        )
    n_spin = 0 if spin_poses is None else spin_poses.means_mps2.shape[0]
    section = calibration_toml(cfg, static, poses.means_mps2.shape[0], spin, n_spin)
    return BenchCalibration(cfg, poses, static, spin_poses, spin, source, section)


def calibration_toml(
    cfg: ArrayConfig,
    static: StaticCalibration,
    n_poses: int,
    spin: SpinCalibration | None = None,
    n_spin: int = 0,
) -> str:
    """The ``[calibration]`` section a run's ``config.toml`` takes as it is, with the fits'
    1-sigmas as comments (a run reads only the values). The offsets, scales and axes are
    the static fit's. With a spin fit the positions are the drawings' corrected by it, and
    ``position_sigma_m`` covers what is left: the largest fitted 1-sigma and the drawings'
    common translation, which no spin shows (``sigma_drawings / sqrt(N)``)."""

    def fmt(a) -> str:
        return repr(np.asarray(a, dtype=float).tolist())

    dr, dr_sigma, lines = cfg.position_error_b_m, cfg.position_sigma_m, []
    if spin is not None:
        n = cfg.layout.n_sensors
        dr = cfg.position_error_b_m + spin.position_correction_b_m
        dr_sigma = float(
            np.sqrt(np.max(spin.position_sigma_b_m) ** 2 + cfg.position_sigma_m**2 / n)
        )
        lines = [
            f"# {n_spin} spin poses, chi-square per dof {spin.chi2_per_dof:.3f} "
            f"({spin.dof} dof); position_error_b_m: the drawings' corrected by them",
            f"# 1-sigma: position_error_b_m {fmt(spin.position_sigma_b_m)}",
        ]
    return "\n".join(
        [
            f"# ngnav calibrate: {n_poses} static poses, chi-square per dof "
            f"{static.chi2_per_dof:.3f} ({static.dof} dof)",
            *lines,
            "# a channel reads (raw - offset_mps2) / scale along its calibrated axis: the",
            "# nominal axis tilted by axis_error_rad (rad) towards e1 and e2",
            f"# 1-sigma (static): offset_mps2 {fmt(static.offset_sigma_mps2)}",
            "# scale_sigma and axis_error_sigma_rad (1-sigma): a run carries what they leave",
            "# as 3N states, which a load of tens of g needs; at a few g it is below the",
            "# bias walk, and without the two keys the run is faster",
            "[calibration]",
            f"position_error_b_m = {fmt(dr)}",
            f"axis_error_rad = {fmt(static.axis_error_rad)}",
            f"scale = {fmt(static.scale)}",
            f"offset_mps2 = {fmt(static.offset_mps2)}",
            f"position_sigma_m = {dr_sigma!r}",
            f"scale_sigma = {fmt(static.scale_sigma)}",
            f"axis_error_sigma_rad = {fmt(static.axis_error_sigma_rad)}",
            "",
        ]
    )
