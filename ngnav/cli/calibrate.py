"""``ngnav calibrate DIR``: an array's offsets, scales and axis errors from static poses."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def calibration_toml(cfg, cal, n_poses: int, spin=None, n_spin: int = 0) -> str:
    """The ``[calibration]`` section a run's ``config.toml`` takes as it is, with the fit's
    1-sigmas as comments (a run reads only the values). With a spin fit the positions are
    the drawings' corrected by it, and ``position_sigma_m`` covers what is left: the
    largest fitted 1-sigma and the drawings' common translation, which no spin shows
    (``sigma_drawings / sqrt(N)``)."""

    def fmt(a) -> str:
        return repr(np.asarray(a, dtype=float).tolist())

    static = cal  # the offsets, scales and axes are the static fit's, with its sigmas
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
            f"# 1-sigma (static): scale {fmt(static.scale_sigma)}",
            f"# 1-sigma (static): axis_error_rad {fmt(static.axis_error_sigma_rad)}",
            "[calibration]",
            f"position_error_b_m = {fmt(dr)}",
            f"axis_error_rad = {fmt(cal.axis_error_rad)}",
            f"scale = {fmt(cal.scale)}",
            f"offset_mps2 = {fmt(cal.offset_mps2)}",
            f"position_sigma_m = {dr_sigma!r}",
            "",
        ]
    )


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ngnav.cli import FractionBar
    from ngnav.recordings import poses_from_files, poses_from_recording
    from ngnav.runconfig import read_array_config
    from ngnav.runio import read_array_csv
    from ngnav.spin_calibration import fit_spin_poses, offset_drift_var, read_spin_pose
    from ngnav.static_calibration import fit_static_poses

    d = Path(args.dir)
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
    with FractionBar("read recordings") as bar:
        read = {}
        for j, p in enumerate(paths):
            read[p] = read_array_csv(p, n)[0]
            bar((j + 1) / len(paths))
    if files:
        poses = poses_from_files([(p.name, read[p]) for p in files], *noise)
        source = f"{len(files)} files in {d / 'static'}"
    else:
        poses = poses_from_recording(read[d / "array.csv"], *noise)
        source = f"the still stretches of {d / 'array.csv'}"
    k = poses.means_mps2.shape[0]
    if not args.json:
        print(f"ngnav calibrate: {k} poses from {source}")
        for why in poses.skipped:
            print(f"  skipped {why}")
    if k == 0:
        raise ValueError(f"{d}: no usable pose ({len(poses.skipped)} skipped)")
    cal = fit_static_poses(poses.means_mps2, poses.sigma_mps2, cfg.layout)
    spin, spin_poses = None, None
    if spin_files:
        rates = {p.name: read_spin_pose(p) for p in spin_files}
        spin_poses = poses_from_files([(p.name, read[p]) for p in spin_files], *noise)
        if not args.json:
            print(f"  and {spin_poses.means_mps2.shape[0]} spin poses from {d / 'spin'}")
            for why in spin_poses.skipped:
                print(f"  skipped spin {why}")
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
            cal,
            drift,
        )
    out = Path(args.out) if args.out else d / "calibration.toml"
    n_spin = 0 if spin_poses is None else spin_poses.means_mps2.shape[0]
    out.write_text(calibration_toml(cfg, cal, k, spin, n_spin), encoding="utf-8")
    if args.json:
        print(
            json.dumps(
                {
                    "poses": list(poses.labels),
                    "skipped": list(poses.skipped),
                    "chi2_per_dof": cal.chi2_per_dof,
                    "dof": cal.dof,
                    "offset_mps2": cal.offset_mps2.tolist(),
                    "offset_sigma_mps2": cal.offset_sigma_mps2.tolist(),
                    "scale": cal.scale.tolist(),
                    "scale_sigma": cal.scale_sigma.tolist(),
                    "axis_error_rad": cal.axis_error_rad.tolist(),
                    "axis_error_sigma_rad": cal.axis_error_sigma_rad.tolist(),
                    "up_b": cal.up_b.tolist(),
                    **_spin_json(spin, spin_poses),
                    "written": str(out),
                },
                indent=2,
            )
        )
        return 0
    print(
        f"  fit: chi-square per dof {cal.chi2_per_dof:.3f} over {cal.dof} dof "
        "(about 1 when the configured noise is right; the sigmas grow with it above 1)"
    )
    print(
        f"  {'channel':>7} {'offset mg':>10} {'+-':>6} {'scale - 1 ppm':>14} {'+-':>6} "
        f"{'axis 1 mrad':>12} {'+-':>6} {'axis 2 mrad':>12} {'+-':>6}"
    )
    mg = 1e3 / 9.80665
    for i in range(n):
        a, sa = cal.axis_error_rad[i] * 1e3, cal.axis_error_sigma_rad[i] * 1e3
        print(
            f"  {i + 1:>7} {cal.offset_mps2[i] * mg:10.3f} {cal.offset_sigma_mps2[i] * mg:6.3f} "
            f"{(cal.scale[i] - 1) * 1e6:14.0f} {cal.scale_sigma[i] * 1e6:6.0f} "
            f"{a[0]:12.3f} {sa[0]:6.3f} {a[1]:12.3f} {sa[1]:6.3f}"
        )
    if spin is not None:
        print(
            f"  spin fit: chi-square per dof {spin.chi2_per_dof:.3f} over {spin.dof} dof; "
            "each sensor's position minus the drawings', mm (zero mean: the reference point "
            "stays the drawings')"
        )
        print(f"  {'sensor':>7} {'x':>8} {'+-':>6} {'y':>8} {'+-':>6} {'z':>8} {'+-':>6}")
        for i in range(n):
            c, sc = spin.position_correction_b_m[i] * 1e3, spin.position_sigma_b_m[i] * 1e3
            print(
                f"  {i + 1:>7} {c[0]:8.3f} {sc[0]:6.3f} {c[1]:8.3f} {sc[1]:6.3f} "
                f"{c[2]:8.3f} {sc[2]:6.3f}"
            )
    print(f"  -> {out}: its [calibration] section goes into a run's config.toml as it is")
    return 0


def _spin_json(spin, poses) -> dict:
    """The spin fit's part of ``--json`` (nothing without spin poses)."""
    if spin is None:
        return {}
    return {
        "spin_poses": list(poses.labels),
        "spin_skipped": list(poses.skipped),
        "spin_chi2_per_dof": spin.chi2_per_dof,
        "spin_dof": spin.dof,
        "position_correction_b_m": spin.position_correction_b_m.tolist(),
        "position_sigma_b_m": spin.position_sigma_b_m.tolist(),
    }


def add_parsers(sub) -> None:
    """Register ``ngnav calibrate``."""
    what = (
        "an array's offsets, scales and axis errors from static poses "
        "(DIR: config.toml and static/*.csv or array.csv)"
    )
    p = sub.add_parser("calibrate", help=what, description=what[0].upper() + what[1:] + ".")
    p.add_argument("dir", help="directory with config.toml and static/*.csv or array.csv")
    p.add_argument("--out", help="where to write (default: DIR/calibration.toml)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_calibrate)
