"""Eq. 27 against multi-position least squares, on the same simulated cubes.

For each Monte Carlo cube (``default_rng([seed, i])``) the true axis errors,
scale errors and biases are drawn as the scenario says; both calibrations read
the same sensor model. Reported: RMS error of the recovered cone angle
(total misalignment, what eq. 27 measures) and, for the least squares, of the
two signed angles and how often their 2-sigma interval holds the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.calibration import calibrate_multiposition, multiposition_directions
from ngnav.layout import layout_by_name
from ngnav.mounting import MountingErrors
from ngnav.paper import eq27_calibrate, static_readings_mv
from ngnav.sim.tilt_table import TiltTableScenario


@dataclass(frozen=True)
class CalibrationStudy:
    runs: int
    eq27_cone_rms_deg: float
    multipos_cone_rms_deg: float
    multipos_angle_rms_deg: float
    multipos_within_2sigma: float
    multipos_scale_rms: float
    true_cone_rms_deg: float


def cone_angle(axis_error_rad: np.ndarray) -> np.ndarray:
    """Total misalignment (rad) from the two axis-error angles (N, 2)."""
    t = np.tan(axis_error_rad)
    return np.arctan(np.sqrt(np.sum(t * t, axis=-1)))


def run_calibration_study(scn: TiltTableScenario, runs: int = 50) -> CalibrationStudy:
    """Calibrate ``runs`` simulated cubes by both methods; errors against the truth."""
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    nominal = layout_by_name(scn.array.layout, scn.array.lever_arm_m)
    n = nominal.n_sensors
    spp = scn.calibration.samples_per_position
    s = scn.sensor.sensitivity_mv_per_g
    up = multiposition_directions()
    e27, emp, eang, inside, escale, cones = [], [], [], [], [], []
    for i in range(runs):
        rng = np.random.default_rng([scn.run.seed, 7, i])
        axes = rng.normal(0.0, np.deg2rad(scn.mounting.axis_error_deg), (n, 2))
        scale_err = rng.normal(0.0, scn.sensor.scale_error, n)
        real = MountingErrors(np.zeros((n, 3)), axes).real_layout(nominal)
        cone = cone_angle(axes)
        est27 = np.abs(eq27_calibrate(scn.sensor, nominal, real, scale_err, spp, rng))
        cal = calibrate_multiposition(
            up, static_readings_mv(scn.sensor, real, scale_err, up, spp, rng), nominal, s
        )
        e27.append(est27 - cone)
        emp.append(cone_angle(cal.axis_error_rad) - cone)
        eang.append(cal.axis_error_rad - axes)
        inside.append(np.abs(cal.axis_error_rad - axes) <= 2 * cal.axis_error_sigma_rad)
        escale.append(cal.scale - (1 + scale_err))
        cones.append(cone)

    def rms_deg(x: list) -> float:
        return float(np.rad2deg(np.sqrt(np.mean(np.concatenate([np.ravel(v) for v in x]) ** 2))))

    return CalibrationStudy(
        runs=runs,
        eq27_cone_rms_deg=rms_deg(e27),
        multipos_cone_rms_deg=rms_deg(emp),
        multipos_angle_rms_deg=rms_deg(eang),
        multipos_within_2sigma=float(np.mean(np.concatenate([np.ravel(v) for v in inside]))),
        multipos_scale_rms=float(np.sqrt(np.mean(np.concatenate(escale) ** 2))),
        true_cone_rms_deg=rms_deg(cones),
    )


# ---------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> int:
    """``python -m studies.calibration [--scenario S] [--set K=V] [--runs N]``."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m studies.calibration", description=__doc__)
    p.add_argument("--scenario", default="tilt-table", help="tilt-table scenario or TOML path")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="K=V")
    p.add_argument("--runs", type=int, default=50, help="simulated cubes (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        return _report(args)
    except ValueError as exc:
        print(f"studies.calibration: error: {exc}", file=sys.stderr)
        return 2


def _report(args) -> int:
    from ngnav.sim.tilt_table import load_tilt_table

    scn = load_tilt_table(args.scenario, args.overrides)
    st = run_calibration_study(scn, args.runs)
    s = scn.sensor.sensitivity_mv_per_g
    print(f"axis-error calibration, {st.runs} simulated cubes x 9 channels ({scn.name})")
    print(f"  true misalignment (cone angle), RMS        {st.true_cone_rms_deg:8.3f} deg")
    print(f"  eq. 27 cone-angle error, RMS              {st.eq27_cone_rms_deg:8.3f} deg")
    print(f"  multi-position cone-angle error, RMS      {st.multipos_cone_rms_deg:8.3f} deg")
    print(f"  multi-position signed-angle error, RMS    {st.multipos_angle_rms_deg:8.3f} deg")
    print(f"  multi-position |error| <= 2 sigma         {100 * st.multipos_within_2sigma:8.1f} %")
    print(f"  multi-position scale error, RMS           {st.multipos_scale_rms:8.5f}")
    print("eq. 27 conditioning at this sensitivity:")
    print(
        f"  a 1 deg axis error changes V2 by          {s * (1 - np.cos(np.deg2rad(1.0))):8.4f} mV"
    )
    print(
        f"  a 0.1 mV reading error alone reads as     {np.rad2deg(np.arccos(1 - 0.1 / s)):8.3f} deg"
    )
    better = (
        "multi-position least squares"
        if st.multipos_cone_rms_deg < st.eq27_cone_rms_deg
        else "eq. 27"
    )
    print(f"use: {better}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
