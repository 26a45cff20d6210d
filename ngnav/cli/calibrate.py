"""``ngnav calibrate DIR``: an array's offsets, scales and axis errors from static poses."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def calibration_toml(cfg, cal, n_poses: int) -> str:
    """The ``[calibration]`` section a run's ``config.toml`` takes as it is, with the fit's
    1-sigmas as comments (a run reads only the values)."""

    def fmt(a) -> str:
        return repr(np.asarray(a, dtype=float).tolist())

    return "\n".join(
        [
            f"# ngnav calibrate: {n_poses} static poses, chi-square per dof "
            f"{cal.chi2_per_dof:.3f} ({cal.dof} dof)",
            "# a channel reads (raw - offset_mps2) / scale along its calibrated axis: the",
            "# nominal axis tilted by axis_error_rad (rad) towards e1 and e2",
            f"# 1-sigma: offset_mps2 {fmt(cal.offset_sigma_mps2)}",
            f"# 1-sigma: scale {fmt(cal.scale_sigma)}",
            f"# 1-sigma: axis_error_rad {fmt(cal.axis_error_sigma_rad)}",
            "[calibration]",
            f"position_error_b_m = {fmt(cfg.position_error_b_m)}",
            f"axis_error_rad = {fmt(cal.axis_error_rad)}",
            f"scale = {fmt(cal.scale)}",
            f"offset_mps2 = {fmt(cal.offset_mps2)}",
            f"position_sigma_m = {cfg.position_sigma_m!r}",
            "",
        ]
    )


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ngnav.recordings import poses_from_files, poses_from_recording
    from ngnav.runconfig import read_array_config
    from ngnav.runio import read_array_csv
    from ngnav.static_calibration import fit_static_poses

    d = Path(args.dir)
    if not d.is_dir():
        raise ValueError(f"{d}: not a directory (config.toml, and static/*.csv or array.csv)")
    cfg = read_array_config(d / "config.toml")
    n = cfg.layout.n_sensors
    noise = (cfg.noise_sigma_mps2, cfg.bias_rw_mps2_rts, cfg.range_mps2)
    files = sorted((d / "static").glob("*.csv")) if (d / "static").is_dir() else []
    if files:
        recs = [(p.name, read_array_csv(p, n)[0]) for p in files]
        poses = poses_from_files(recs, *noise)
        source = f"{len(files)} files in {d / 'static'}"
    elif (d / "array.csv").is_file():
        samples, _ = read_array_csv(d / "array.csv", n)
        poses = poses_from_recording(samples, *noise)
        source = f"the still stretches of {d / 'array.csv'}"
    else:
        raise ValueError(f"{d}: no recordings: give static/*.csv (one per pose) or array.csv")
    k = poses.means_mps2.shape[0]
    if not args.json:
        print(f"ngnav calibrate: {k} poses from {source}")
        for why in poses.skipped:
            print(f"  skipped {why}")
    if k == 0:
        raise ValueError(f"{d}: no usable pose ({len(poses.skipped)} skipped)")
    cal = fit_static_poses(poses.means_mps2, poses.sigma_mps2, cfg.layout)
    out = Path(args.out) if args.out else d / "calibration.toml"
    out.write_text(calibration_toml(cfg, cal, k), encoding="utf-8")
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
    print(f"  -> {out}: its [calibration] section goes into a run's config.toml as it is")
    return 0


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
