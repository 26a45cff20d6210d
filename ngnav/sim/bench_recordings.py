"""A simulated bench calibration session: the scenario's array held still in 18 poses.

The array is the one run ``i`` of the flight scenario flies (the same draws, in the same
order, from ``default_rng([seed, i])``), so a calibration of these recordings can be flown
with that run. The poses are the multi-position set (six faces, twelve edges,
:func:`ngnav.calibration.multiposition_directions`); their orientations are not written:
``ngnav calibrate`` finds them. With ``continuous`` the session is one recording with
minimum-jerk turns between the poses, for the still-segment detector.

A rate-table session follows (:data:`SPIN_AXES`): the array mounted with each axis up on
a vertical table spinning at a constant rate, the reference point a few millimetres off
the table's axis, one recording per pose with its axis and rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ngnav.calibration import multiposition_directions
from ngnav.conventions import G0_MPS2
from ngnav.motion import min_jerk_step
from ngnav.records import ArraySamples
from ngnav.runio import write_array_csv
from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.simulate import draw_array
from ngnav.static_calibration import calibration_frame

#: The spin poses' table axes in the body frame: the three body axes and the six face
#: diagonals (an axis across a sensor shows its position along its axis; the diagonals,
#: oblique to every axis, show the rest: :mod:`ngnav.spin_calibration`).
_SPIN = np.array(
    [
        [1, 0, 0],
        [0, 1, 0],
        [0, 0, 1],
        [1, 1, 0],
        [1, -1, 0],
        [1, 0, 1],
        [1, 0, -1],
        [0, 1, 1],
        [0, 1, -1],
    ],
    dtype=float,
)
SPIN_AXES = _SPIN / np.linalg.norm(_SPIN, axis=1, keepdims=True)
#: The table's rate, deg/s, unless the sensors' range needs less (half the range at most).
SPIN_RATE_DPS = 720.0
#: The reference point's distance from the table's axis, m (a fixture's tolerance).
SPIN_OFFSET_M = 0.005
#: Each pose's table axis off the direction given for it, 1-sigma per direction, rad (the
#: fixture's tolerance: ngnav.spin_calibration.SPIN_AXIS_SIGMA_RAD).
SPIN_AXIS_ERROR_RAD = 0.001


@dataclass(frozen=True)
class BenchSession:
    """Recordings of a simulated bench session and the truth they hold.

    Attributes
    ----------
    recordings : list of (str, ArraySamples)
        One per pose (``pose_01`` ...), or one ``array`` with the turns between them.
    config_text : str
        The ``config.toml`` a calibration reads: ``[array]``, ``[sensor]`` and the
        drawings' ``[calibration] position_error_b_m`` and ``position_sigma_m``.
    offset_mps2, scale : arrays (N,)
        True zero offsets (the bias's mean over the poses) and real/nominal sensitivities.
    axis_error_rad : array (N, 2)
        True axis errors in the frame a static calibration defines.
    spins : list of (str, ArraySamples, array (3,))
        The rate-table poses: name, recording, rate vector (body, rad/s).
    position_error_b_m : array (N, 3)
        True positions, in the frame a static calibration defines, minus the nominal ones, m.
    """

    recordings: list[tuple[str, ArraySamples]]
    config_text: str
    offset_mps2: np.ndarray
    scale: np.ndarray
    axis_error_rad: np.ndarray
    spins: list[tuple[str, ArraySamples, np.ndarray]]
    position_error_b_m: np.ndarray


def _turn(up_a: np.ndarray, up_b: np.ndarray, n_s: int, dt: float):
    """Body rate, its derivative and the up direction (each (n_s, 3)) of a minimum-jerk turn
    about one body axis that takes the up direction from ``up_a`` to ``up_b``."""
    axis = np.cross(up_b, up_a)
    angle = float(np.arctan2(np.linalg.norm(axis), up_a @ up_b))
    if np.linalg.norm(axis) < 1e-9:  # opposite poses: any axis across them
        axis = np.cross(up_a, np.eye(3)[np.argmin(np.abs(up_a))])
    axis /= np.linalg.norm(axis)
    duration = n_s * dt
    tau = (np.arange(n_s) + 1) * dt / duration
    s, ds, d2s = min_jerk_step(tau)
    th = angle * s
    w = np.outer(angle * ds / duration, axis)
    wd = np.outer(angle * d2s / duration**2, axis)
    # the body turns by th about `axis`: up_b = exp(-th [axis]x) up_a (Rodrigues)
    c, sn = np.cos(th)[:, None], np.sin(th)[:, None]
    k_up = np.cross(axis, up_a)
    up = up_a * c - k_up * sn + np.outer(1.0 - np.cos(th), axis * (axis @ up_a))
    return w, wd, up


def bench_session(
    scn: FlightScenario,
    run_index: int = 0,
    seconds_per_pose: float = 2.0,
    continuous: bool = False,
    turn_s: float = 1.5,
) -> BenchSession:
    """Simulate the bench session of run ``run_index``'s array (see the module docstring)."""
    if seconds_per_pose <= 0 or turn_s <= 0:
        raise ValueError("seconds_per_pose and turn_s must be positive")
    rng = np.random.default_rng([scn.run.seed, run_index])
    rate = scn.run.rate_hz
    dt = 1.0 / rate
    arr = draw_array(scn, rng)  # the flight's own array (ngnav.sim.simulate.draw_array)
    spec, nominal, real, scale_error = arr.spec, arr.nominal, arr.real, arr.scale_error
    designed, m = arr.designed, scn.mounting
    ups = multiposition_directions()
    n_hold = round(seconds_per_pose * rate)
    n_turn = round(turn_s * rate)
    w_parts, wd_parts, up_parts, pose_of = [], [], [], []
    for k, up in enumerate(ups):
        if continuous and k > 0:
            w, wd, upt = _turn(ups[k - 1], up, n_turn, dt)
            w_parts.append(w)
            wd_parts.append(wd)
            up_parts.append(upt)
            pose_of.append(np.full(n_turn, -1))
        w_parts.append(np.zeros((n_hold, 3)))
        wd_parts.append(np.zeros((n_hold, 3)))
        up_parts.append(np.tile(up, (n_hold, 1)))
        pose_of.append(np.full(n_hold, k))
    w, wd, up_b = np.vstack(w_parts), np.vstack(wd_parts), np.vstack(up_parts)
    pose = np.concatenate(pose_of)
    clean = real.outputs(wd, G0_MPS2 * up_b, w)  # at rest the specific force is +g0 up
    out, _, bias = spec.simulate(clean, rate, scale_error, rng)
    t = np.arange(out.shape[0]) * dt
    # then the rate table: each axis up in turn, spun; the reference point off its axis
    r_max = float(np.max(np.linalg.norm(real.positions_b_m, axis=1))) + SPIN_OFFSET_M
    room = 0.5 * spec.range_g * G0_MPS2 - G0_MPS2
    omega = min(np.deg2rad(SPIN_RATE_DPS), np.sqrt(max(room, 0.0) / r_max))
    n_spin = round(2 * seconds_per_pose * rate)
    spin_rates, f_spin = [], []
    for given in SPIN_AXES:
        axis = given + np.cross(rng.normal(0.0, SPIN_AXIS_ERROR_RAD, 3), given)
        axis /= np.linalg.norm(axis)
        wv = omega * axis
        d = np.cross(axis, rng.standard_normal(3))
        d *= SPIN_OFFSET_M / np.linalg.norm(d)
        spin_rates.append((wv, omega * given))
        f_spin.append(G0_MPS2 * axis + np.cross(wv, np.cross(wv, d)))
    w_s = np.repeat(np.array([true for true, _ in spin_rates]), n_spin, axis=0)
    f_s = np.repeat(np.array(f_spin), n_spin, axis=0)
    out_s, _, _ = spec.simulate(
        real.outputs(np.zeros_like(w_s), f_s, w_s), rate, scale_error, rng, bias0_mps2=bias[-1]
    )
    t_s = t[-1] + (np.arange(out_s.shape[0]) + 1) * dt
    cut = [slice(j * n_spin, (j + 1) * n_spin) for j in range(len(spin_rates))]
    spins = [  # each with the rate vector as given (the table's nominal axis)
        (f"spin_{j + 1:02d}", ArraySamples(t_s[c], out_s[c]), given)
        for j, (c, (_, given)) in enumerate(zip(cut, spin_rates, strict=True))
    ]
    if continuous:
        recordings = [("array", ArraySamples(t, out))]
    else:
        recordings = [
            (f"pose_{k + 1:02d}", ArraySamples(t[pose == k], out[pose == k]))
            for k in range(ups.shape[0])
        ]
    config = "\n".join(
        [
            f"# simulated bench session: {scn.name} run {run_index}'s array, before calibration",
            "[array]",
            f'name = "{nominal.name}"',
            f"positions_b_m = {nominal.positions_b_m.tolist()!r}",
            f"axes_b = {nominal.axes_b.tolist()!r}",
            "[sensor]",
            f"noise_sigma_mps2 = {spec.sample_sigma_mps2(rate)!r}",
            f"turn_on_bias_mps2 = {spec.turn_on_bias_mps2()!r}",
            f"bias_rw_mps2_rts = {spec.bias_rw_mps2_rts()!r}",
            f"range_mps2 = {spec.range_g * G0_MPS2!r}",
            "[calibration]",
            "# the sensitive elements' offsets from the drawings (not seen at rest)",
            f"position_error_b_m = {designed.tolist()!r}",
            f"position_sigma_m = {m.position_scatter_m!r}",
            "",
        ]
    )
    phi, a_cal = calibration_frame(real.axes_b, nominal)
    return BenchSession(
        recordings,
        config,
        offset_mps2=bias[pose >= 0].mean(axis=0),
        scale=1.0 + scale_error,
        axis_error_rad=a_cal,
        spins=spins,
        position_error_b_m=Rotation.from_rotvec(phi).apply(np.array(real.positions_b_m))
        - nominal.positions_b_m,
    )


def write_bench_session(session: BenchSession, out_dir: str | Path) -> Path:
    """Write ``config.toml``, the recordings (``static/pose_NN.csv``, or ``array.csv``),
    the rate-table poses (``spin/spin_NN.csv`` with ``spin_NN.toml``: ``axis_b``,
    ``rate_dps``) and ``truth_calibration.toml`` (the true offsets, scales, axis errors
    and position errors)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.toml").write_text(session.config_text, encoding="utf-8")
    for name, samples in session.recordings:
        if name == "array":
            write_array_csv(out / "array.csv", samples)
        else:
            (out / "static").mkdir(exist_ok=True)
            write_array_csv(out / "static" / f"{name}.csv", samples)
    (out / "spin").mkdir(exist_ok=True)
    for name, samples, wv in session.spins:
        write_array_csv(out / "spin" / f"{name}.csv", samples)
        rate = float(np.linalg.norm(wv))
        (out / "spin" / f"{name}.toml").write_text(
            f"axis_b = {(wv / rate).tolist()!r}\nrate_dps = {float(np.rad2deg(rate))!r}\n",
            encoding="utf-8",
        )
    (out / "truth_calibration.toml").write_text(
        "\n".join(
            [
                "# the simulated array's truth, in the frame a static calibration defines",
                f"offset_mps2 = {session.offset_mps2.tolist()!r}",
                f"scale = {session.scale.tolist()!r}",
                f"axis_error_rad = {session.axis_error_rad.tolist()!r}",
                "# the sensitive elements' true positions (in that frame) minus the nominal, m",
                f"position_error_b_m = {session.position_error_b_m.tolist()!r}",
                "",
            ]
        ),
        encoding="utf-8",
    )
    return out
