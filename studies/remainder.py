"""How long the vehicle model's second-order remainders persist, against a truth.

The sideslip update (:meth:`filters.ekf.NavFilter.update_sideslip`) linearises the
body-lateral velocity ``e_y . C^T v`` at the nominal state (the angle-of-attack update
the velocity along the wind-normal axis ``n_b(alpha)`` in the same way) and adds the
variance of what the linearisation leaves out (the remainder, second order in the
attitude, velocity and angle-of-attack errors) to R, counted
``filter.remainder_updates`` times and its attitude-product part
``filter.attitude_remainder_updates`` times (the whole ``filter.coast_remainder_updates``
times in a GPS coast): the number of consecutive updates that share one value of
it. Those counts are properties of a flight, not of the filter; this module
measures them on simulated flights.

At every such update of a run (:class:`filters.vehicle_model.BodyVelocityRecord`) the truth
gives the remainder actually left (:func:`realized_remainder`; the lateral model's
shown),

``r = e_y . C_true^T v_true - (v_lat + h_vel . dv + h_att . dtheta)``

with ``dtheta`` the NED attitude error (``q_true = exp(dtheta) q``) and ``dv =
v_true - v``, and its attitude-product part ``r_att = dtheta^T A dtheta / 2``
(:meth:`filters.ekf.NavFilter.body_velocity_second_order`). Standardised by the
model's mean and variance, ``z = (r - mean) / sqrt(var)``, a model that describes
the remainder gives ``E z^2 = 1``; the lag-1 correlation ``rho`` of ``z`` over
consecutive updates gives, for an AR(1) sequence, the integrated autocorrelation
``(1 + rho) / (1 - rho)``: the number of updates one value counts for, which is
what the count in R stands for. A remainder with a slow part beside a fast one
lasts longer than its lag-1 correlation says, so the integrated autocorrelation
``tau = 1 + 2 sum_k rho_k`` is also summed directly (:func:`integrated_autocorrelation`,
Sokal's window).

With ``filter.body_velocity_error`` the models are exactly linear at the update and
there is no such remainder to measure: the study runs the NED error's filter whatever
the scenario sets.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from filters.evaluate import truth_aoa_rad, truth_indices
from filters.pipeline import run_filter
from filters.vehicle_model import (
    LATERAL,
    VERTICAL,
    BodyVelocityRecord,
    attitude_product_matrix,
    constraint_axes,
)
from ngnav.errors import CovarianceError
from ngnav.records import FlightTruth
from ngnav.rotation import dcm_from_quat, quat_conjugate, quat_multiply, quat_to_rotvec, skew
from ngnav.sim.flight_scenario import FlightScenario

#: Lag-1 correlations are clipped to this before ``(1 + rho) / (1 - rho)``: a
#: remainder constant over a window would otherwise count infinitely often.
RHO_MAX = 0.999


@dataclass(frozen=True)
class RealizedRemainders:
    """One run's updates of one vehicle model with the remainders the truth shows.

    Attributes
    ----------
    t_s : array (U,)
        Update times, s.
    r_mps, r_att_mps : arrays (U,)
        The remainder actually left and its attitude-product part, m/s.
    mean_mps, var_m2ps2 : arrays (U,)
        The model's mean (m/s) and variance (m^2/s^2) of the remainder.
    mean_att_mps, var_att_m2ps2 : arrays (U,)
        The same for the attitude-product part.
    r_m2ps2 : array (U,) or None
        The R each update used (the sigma's variance plus the remainder as counted),
        m^2/s^2.
    """

    t_s: np.ndarray
    r_mps: np.ndarray
    r_att_mps: np.ndarray
    mean_mps: np.ndarray
    var_m2ps2: np.ndarray
    mean_att_mps: np.ndarray
    var_att_m2ps2: np.ndarray
    r_m2ps2: np.ndarray | None = None

    def z(self) -> np.ndarray:
        """The remainder standardised by the model, (U,)."""
        return (self.r_mps - self.mean_mps) / np.sqrt(self.var_m2ps2)

    def z_att(self) -> np.ndarray:
        """The attitude-product part standardised by the model, (U,)."""
        return (self.r_att_mps - self.mean_att_mps) / np.sqrt(self.var_att_m2ps2)


@dataclass(frozen=True)
class WindowPersistence:
    """The remainder over one time window, over runs.

    ``z2`` and ``z2_att``: mean squared standardised remainder (1 when the model's
    variance is right); ``rho`` and ``rho_att``: median over runs of the lag-1
    correlation of consecutive updates; ``count`` and ``count_att``: ``(1 + rho) /
    (1 - rho)`` at that median (1 for ``rho <= 0``), the updates one value counts for;
    ``tau`` and ``tau_att``: the same counted without the AR(1) assumption
    (:func:`integrated_autocorrelation` of the runs' standardised remainders pooled);
    ``r_ratio``: the updates' R summed over the squares of the realized remainder less
    the model's mean (the part the update's prediction leaves) summed: how much wider
    R is than the remainder it stands for; NaN without R.
    """

    t0_s: float
    t1_s: float
    updates: int
    z2: float
    z2_att: float
    rho: float
    rho_att: float
    count: float
    count_att: float
    tau: float
    tau_att: float
    r_ratio: float = float("nan")


def rotvec_between(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """NED rotation vector ``dtheta`` with ``q_true = exp(dtheta) q_est`` (rad, (3,))."""
    d = quat_multiply(q_true, quat_conjugate(q_est))
    return quat_to_rotvec(-d if d[0] < 0.0 else d)


def realized_remainder(
    rec: BodyVelocityRecord,
    q_true_nb: np.ndarray,
    vel_true_ned_mps: np.ndarray,
    aoa_true_rad: float = 0.0,
) -> tuple[float, float]:
    """The remainder a vehicle-model update left, and its attitude-product part (m/s).

    ``r`` is the true velocity along the true constraint axis (``n_b(alpha_true)`` for
    the vertical model, ``e_y`` for the lateral) minus the update's linear prediction
    of it from the true errors, ``v_axis + a . dv + a^T [v]x dtheta + dv_daoa
    (alpha_true - alpha)`` with ``a = C n_b(alpha)`` at the nominal state (the
    constraint's geometric Jacobian; the vertical update's own ``h_vel`` also carries
    the lift law's dependence on the speed). The angle-of-attack term takes the true angle's
    error itself, so what the lift law leaves out of the angle is not counted as the
    constraint's remainder. ``r_att = dtheta^T A dtheta / 2``, ``A = (a v^T + v a^T) / 2
    - (a . v) I`` (the quadratic form
    :meth:`filters.ekf.NavFilter.body_velocity_second_order` takes the moments of).
    ``aoa_true_rad`` is ignored for the lateral model.
    """
    dth = rotvec_between(q_true_nb, rec.q_nb)
    v = rec.vel_ned_mps
    dv = np.asarray(vel_true_ned_mps, dtype=float) - v
    n_true, _ = constraint_axes(rec.axis, aoa_true_rad if rec.axis == VERTICAL else 0.0)
    true_val = float((dcm_from_quat(q_true_nb) @ n_true) @ vel_true_ned_mps)
    n_b, _ = constraint_axes(rec.axis, rec.aoa_rad)
    a = dcm_from_quat(rec.q_nb) @ n_b
    lin = rec.v_axis_mps + float(a @ dv) + float(a @ skew(v) @ dth)
    if rec.axis == VERTICAL:
        lin += rec.dv_daoa_mps * (aoa_true_rad - rec.aoa_rad)
    return true_val - lin, 0.5 * float(dth @ attitude_product_matrix(a, v) @ dth)


def realized_remainders(
    records: list[BodyVelocityRecord], truth: FlightTruth
) -> RealizedRemainders:
    """:func:`realized_remainder` at every update, the truth taken at the update's time.

    The records must be of one model (axis); the vertical model's true angle of
    attack is the body x-z angle of the true velocity
    (:func:`filters.evaluate.truth_aoa_rad`).

    Raises
    ------
    ValueError
        If there are no records, they mix the two models, or an update's time is not a
        truth sample time (:func:`filters.evaluate.truth_indices`).
    """
    if not records:
        raise ValueError("no vehicle-model updates recorded (is filter.sideslip_sigma_deg > 0?)")
    if len({r.axis for r in records}) != 1:
        raise ValueError("records of the lateral and vertical models must be measured apart")
    t = np.array([r.t_s for r in records])
    try:
        k = truth_indices(truth, t)
    except ValueError as exc:
        raise ValueError(f"vehicle-model updates against the truth: {exc}") from None
    aoa = truth_aoa_rad(truth, k) if records[0].axis == VERTICAL else np.zeros(k.shape[0])
    rr = np.array(
        [
            realized_remainder(rec, truth.q_nb[j], truth.vel_ned_mps[j], float(al))
            for rec, j, al in zip(records, k.tolist(), aoa.tolist(), strict=True)
        ]
    )
    rem = np.array([rec.remainder for rec in records])  # mean, var, var_att, mean_att
    r_used = np.array([rec.r_m2ps2 for rec in records])
    return RealizedRemainders(
        t, rr[:, 0], rr[:, 1], rem[:, 0], rem[:, 1], rem[:, 3], rem[:, 2], r_used
    )


def lag1_correlation(x: np.ndarray) -> float:
    """Correlation of consecutive values of ``x`` (NaN for fewer than 3 values)."""
    x = np.asarray(x, dtype=float)
    if x.shape[0] < 3:
        return float("nan")
    a, b = x[:-1] - x[:-1].mean(), x[1:] - x[1:].mean()
    den = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b) / den if den > 0 else float("nan")


def updates_per_value(rho: float) -> float:
    """Integrated autocorrelation ``(1 + rho) / (1 - rho)`` of an AR(1) sequence.

    1 for ``rho <= 0`` (no persistence to count); ``rho`` is clipped to
    :data:`RHO_MAX`. NaN stays NaN.
    """
    if not np.isfinite(rho):
        return float("nan")
    rho = min(float(rho), RHO_MAX)
    return 1.0 if rho <= 0.0 else (1.0 + rho) / (1.0 - rho)


def integrated_autocorrelation(series: list[np.ndarray], c: float = 5.0) -> float:
    """Integrated autocorrelation ``tau = 1 + 2 sum_{k=1..M} rho_k`` of runs of one process.

    ``rho_k`` pools every run's lag-``k`` products about the pooled mean (runs are
    not joined end to end); the window ``M`` is the smallest with ``M >= c tau(M)``
    (Sokal's automatic window, c = 5: the sum stops where noise would dominate it).
    When no lag satisfies it the sum over every lag is returned, a lower bound.
    NaN for fewer than 3 values in all or no spread.

    Parameters
    ----------
    series : list of arrays (n_i,)
        One sequence per run, consecutive in time.
    c : float
        The window's factor.
    """
    xs = [np.asarray(x, dtype=float) for x in series if np.asarray(x).shape[0] > 0]
    n = sum(x.shape[0] for x in xs)
    if n < 3:
        return float("nan")
    m = np.concatenate(xs).mean()
    xs = [x - m for x in xs]
    c0 = sum(float(x @ x) for x in xs) / n
    if c0 <= 0.0:
        return float("nan")
    k_max = max(x.shape[0] for x in xs) - 1
    tau = 1.0
    for k in range(1, k_max + 1):
        pairs = [(x[:-k], x[k:]) for x in xs if x.shape[0] > k]
        nk = sum(a.shape[0] for a, _ in pairs)
        tau += 2.0 * sum(float(a @ b) for a, b in pairs) / nk / c0
        if k >= c * tau:
            break
    return max(tau, 1.0)


def _nanmedian(x: list[float]) -> float:
    """Median of the finite values; NaN (no warning) when there is none."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


def window_persistence(
    runs: list[RealizedRemainders], edges_s: np.ndarray
) -> list[WindowPersistence]:
    """Each window's :class:`WindowPersistence` over the runs (windows ``[e_i, e_i+1)``)."""
    out = []
    for t0, t1 in zip(edges_s[:-1].tolist(), edges_s[1:].tolist(), strict=True):
        z2, z2a, rho, rho_a, zs, zas, n = [], [], [], [], [], [], 0
        r_sum, r2_sum = 0.0, 0.0
        for run in runs:
            m = (run.t_s >= t0) & (run.t_s < t1)
            if not m.any():
                continue
            z, za = run.z()[m], run.z_att()[m]
            n += int(m.sum())
            z2.append(z * z)
            z2a.append(za * za)
            rho.append(lag1_correlation(z))
            rho_a.append(lag1_correlation(za))
            zs.append(z)
            zas.append(za)
            r_sum += float(run.r_m2ps2[m].sum()) if run.r_m2ps2 is not None else np.nan
            r2_sum += float(np.sum((run.r_mps[m] - run.mean_mps[m]) ** 2))
        if n == 0:
            continue
        r, ra = _nanmedian(rho), _nanmedian(rho_a)
        out.append(
            WindowPersistence(
                t0,
                t1,
                n,
                float(np.mean(np.concatenate(z2))),
                float(np.mean(np.concatenate(z2a))),
                r,
                ra,
                updates_per_value(r),
                updates_per_value(ra),
                integrated_autocorrelation(zs),
                integrated_autocorrelation(zas),
                r_sum / r2_sum if r2_sum > 0 else float("nan"),
            )
        )
    return out


#: The vehicle models by the name the study reports them under.
MODELS: dict[str, int] = {"lateral": LATERAL, "vertical": VERTICAL}


def _one_run(scn: FlightScenario, i: int) -> dict[str, RealizedRemainders] | str:
    from ngnav.sim.simulate import simulate_flight

    sim = simulate_flight(scn, i)
    log: list[BodyVelocityRecord] = []
    cfg = sim.config
    if cfg.vehicle.body_velocity_error:
        # the study measures the NED velocity error's remainder (realized_remainder);
        # the body-frame error has none at the update to measure
        cfg = replace(cfg, vehicle=replace(cfg.vehicle, body_velocity_error=False))
    try:
        run_filter(sim.samples, sim.fixes, cfg, body_velocity_log=log)
    except CovarianceError as exc:
        return f"run {i} diverged and is left out: {exc}"
    out = {}
    for name, axis in MODELS.items():
        recs = [r for r in log if r.axis == axis]
        if recs:
            out[name] = realized_remainders(recs, sim.truth)
    return out


def remainder_study(
    scn: FlightScenario, runs: int, window_s: float, workers: int = 2, progress: bool = False
) -> dict:
    """Measure the vehicle model's remainders' size and persistence over ``runs`` flights.

    Runs use ``default_rng([seed, i])`` (:func:`ngnav.sim.simulate.simulate_flight`) and
    execute with dask's process scheduler (``workers`` processes; 1: in this
    process). Returns the counts the filter used; under ``models``, for the lateral
    (sideslip) model and, when the scenario has it, the vertical (angle-of-attack)
    one: the windows (:func:`window_persistence` over ``window_s`` seconds, as dicts)
    and the same over the whole flight; and the runs left out (diverged).
    """
    import dask
    from tqdm import tqdm

    if runs < 1:
        raise ValueError(f"runs must be at least 1, got {runs}")
    if not (np.isfinite(window_s) and window_s > 0):
        raise ValueError(f"window must be a positive number of seconds, got {window_s}")
    if not scn.vehicle.fixed_wing:
        raise ValueError(
            f"scenario {scn.name!r} has no vehicle model (vehicle.kind is {scn.vehicle.kind!r})"
        )
    results: list[dict[str, RealizedRemainders] | str] = []
    bar = tqdm(total=runs, desc="remainder", disable=not progress, unit="run")
    chunk = max(1, workers)
    for start in range(0, runs, chunk):
        tasks = [dask.delayed(_one_run)(scn, i) for i in range(start, min(runs, start + chunk))]
        sched = (
            {"scheduler": "processes", "num_workers": workers}
            if workers > 1
            else {"scheduler": "synchronous"}
        )
        results += dask.compute(*tasks, **sched)
        bar.update(len(tasks))
    bar.close()
    left_out = [r for r in results if isinstance(r, str)]
    done = [r for r in results if not isinstance(r, str)]
    if not done:
        raise RuntimeError(f"every run diverged: {left_out}")
    models = {}
    for name in MODELS:
        runs_m = [r[name] for r in done if name in r]
        if not runs_m:
            continue
        t_end = max(float(r.t_s[-1]) for r in runs_m)
        edges = np.arange(0.0, t_end + window_s, window_s)
        whole = window_persistence(runs_m, np.array([0.0, t_end + 1.0]))[0]
        models[name] = {
            "whole": whole.__dict__,
            "windows": [w.__dict__ for w in window_persistence(runs_m, edges)],
        }
    return {
        "scenario": scn.name,
        "runs": len(done),
        "remainder_updates": scn.vehicle.remainder_updates,
        "attitude_remainder_updates": scn.vehicle.attitude_remainder_updates,
        "coast_remainder_updates": scn.vehicle.coast_remainder_updates,
        "models": models,
        "left_out": left_out,
    }


# ---------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> int:
    """``python -m studies.remainder [--scenario S] [--runs N] [--window S] [--json]``."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="python -m studies.remainder", description=__doc__)
    p.add_argument("--scenario", default="tactical", help="flight scenario or TOML path")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="K=V")
    p.add_argument("--runs", type=int, default=8)
    p.add_argument("--window", type=float, default=10.0, help="window length, s")
    p.add_argument("--workers", type=int, default=2, help="dask worker processes")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    try:
        return _report(args)
    except ValueError as exc:
        print(f"studies.remainder: error: {exc}", file=sys.stderr)
        return 2


def _report(args) -> int:
    import json

    from ngnav.sim.flight_scenario import load_flight

    out = remainder_study(
        load_flight(args.scenario, args.overrides),
        args.runs,
        args.window,
        args.workers,
        progress=not args.json,
    )
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(
        f"{out['scenario']}: the vehicle model's remainders over {out['runs']} runs, against the "
        f"truth (the filter counts it {out['remainder_updates']:g} times, its attitude part "
        f"{out['attitude_remainder_updates']:g} times, the whole in a coast "
        f"{out['coast_remainder_updates']:g} times)"
    )
    print(
        "  z2: mean squared remainder over the model's variance (1: the model's size); "
        "rho: median lag-1 correlation over runs; count: (1 + rho) / (1 - rho), the "
        "updates one value counts for as an AR(1); tau: the same summed over all lags "
        "(integrated autocorrelation); R/r2: the updates' R over the mean square of the "
        "realized remainder less the model's mean"
    )
    for name, m in out["models"].items():
        print(f"  {name} model ({'sideslip' if name == 'lateral' else 'angle of attack'}):")
        print(
            "    window s        updates      z2    rho  count    tau   att z2  att rho"
            "  att count  att tau     R/r2"
        )
        for w in [*m["windows"], m["whole"]]:
            label = "whole flight" if w is m["whole"] else f"{w['t0_s']:6.1f}-{w['t1_s']:6.1f}"
            print(
                f"    {label:13s} {w['updates']:8d} {w['z2']:7.2f} {w['rho']:6.2f} "
                f"{w['count']:6.1f} {w['tau']:6.1f} {w['z2_att']:8.2f} {w['rho_att']:8.2f} "
                f"{w['count_att']:10.1f} {w['tau_att']:8.1f} {w['r_ratio']:8.1f}"
            )
    for msg in out["left_out"]:
        print(f"  {msg}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
