"""``ngnav calibrate DIR``: an array's offsets, scales and axis errors from static poses,
and its sensor positions from rate-table poses (:mod:`ngnav.bench_session`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ngnav.bench_session import calibrate_bench
    from ngnav.cli import FractionBar

    with FractionBar("read recordings") as bar:
        got = calibrate_bench(args.dir, progress=bar)
    cal, spin, poses, spin_poses = got.static, got.spin, got.poses, got.spin_poses
    n = got.config.layout.n_sensors
    out = Path(args.out) if args.out else Path(args.dir) / "calibration.toml"
    out.write_text(got.section, encoding="utf-8")
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
    print(f"ngnav calibrate: {poses.means_mps2.shape[0]} poses from {got.source}")
    for why in poses.skipped:
        print(f"  skipped {why}")
    if spin_poses is not None:
        print(f"  and {spin_poses.means_mps2.shape[0]} spin poses from {Path(args.dir) / 'spin'}")
        for why in spin_poses.skipped:
            print(f"  skipped spin {why}")
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
