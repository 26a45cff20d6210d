"""Which kind of filter step leaves a component's error larger than its variance says.

A consistent filter keeps ``E[e^2] = P`` for every component at every step: a propagation
grows the squared error by as much as it grows the variance, an update shrinks the squared
error by as much as it shrinks the variance. So ``d(e^2) - dP`` over one step has zero mean
over runs whatever the step, and where a campaign reads a block over-sure
(``ngnav consistency``) the steps whose difference is positive are the ones that made it so.

This study runs flights with the filter's steps observed (``NavFilter.propagate``,
``remove_feature_residual`` and ``_apply``, wrapped for the run only), records the chosen
components' errors against the truth and their variances before and after each step, and sorts
the steps by kind: the propagation, the rate products, the GPS position, the GPS velocity, a
vehicle model, the zero rate at rest, and the static alignment's biases. Per run and window it
sums each kind's ``(d(e^2) - dP) / P_before``; the table gives the mean over runs and its
standard error, in units of the variance (positive: the steps left the error that many
variances larger than they said). Changes made outside those steps (a heading set from the GPS
course, a reset onto a fix, a start again) are not counted.

The errors are the truth's less the estimate's, as ``filters.evaluate.run_errors`` takes them:
the attitude the NED rotation vector of ``q_true q_est^-1``, the rate body-frame (FRD), the
velocity and position NED (with the body-frame velocity error its variance is that error's,
which agrees with the NED one to first order); the biases of the solved angular acceleration
and force the solve's image ``S beta`` of the true channel biases (calibrated by the scale the
filter is told) less the filter's estimate.

Run from the repository root: ``python -m studies.accounting --scenario ground --runs 24
--window 12 --component heading``.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial

import numpy as np

from filters.ekf import NavFilter
from filters.pipeline import run_filter
from filters.state import ATT, B_F, B_WDOT, POS, RATE, VEL
from filters.updates import Measurement
from ngnav.frontend import ArraySolver
from ngnav.records import FlightTruth
from ngnav.rotation import quat_conjugate, quat_multiply, quat_to_rotvec
from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.simulate import simulate_flight

#: The components a run can follow: (the error's kind, its axis).
COMPONENTS: dict[str, tuple[str, int]] = {
    "tilt_n": ("att", 0),
    "tilt_e": ("att", 1),
    "heading": ("att", 2),
    "roll_rate": ("rate", 0),
    "pitch_rate": ("rate", 1),
    "yaw_rate": ("rate", 2),
    "vel_n": ("vel", 0),
    "vel_e": ("vel", 1),
    "vel_d": ("vel", 2),
    "pos_n": ("pos", 0),
    "pos_e": ("pos", 1),
    "pos_d": ("pos", 2),
    "wdot_bias_x": ("b_wdot", 0),
    "wdot_bias_y": ("b_wdot", 1),
    "wdot_bias_z": ("b_wdot", 2),
    "f_bias_x": ("b_f", 0),
    "f_bias_y": ("b_f", 1),
    "f_bias_z": ("b_f", 2),
}
_STATE = {"att": ATT, "rate": RATE, "vel": VEL, "pos": POS, "b_wdot": B_WDOT, "b_f": B_F}
#: The kinds of step, in the table's order.
KINDS = (
    "propagation",
    "rate products",
    "GPS position",
    "GPS velocity",
    "vehicle model",
    "zero rate",
    "static biases",
)


def step_kind(meas: Measurement, bias: slice) -> int:
    """The kind (index into :data:`KINDS`) of an update, from its Jacobian's columns.

    The rate products read their own biases (the bias states after the angular
    acceleration's and the force's six; at zero rate nothing else); the static alignment
    the first six; the GPS position the position; the GPS velocity (two or three rows) and
    a vehicle model (one row) the velocity; the zero rate at rest the rate alone.
    """
    on = np.any(meas.H != 0.0, axis=0)
    on_bias = on[bias]
    if on[POS].any():
        return KINDS.index("GPS position")
    if on_bias[6:].any():
        return KINDS.index("rate products")
    if on_bias[:6].any():
        return KINDS.index("static biases")
    if on[VEL].any():
        return KINDS.index("GPS velocity" if meas.H.shape[0] > 1 else "vehicle model")
    return KINDS.index("zero rate")


@dataclass(frozen=True)
class StepLog:
    """One run's observed steps.

    Attributes
    ----------
    t_s : array (S,)
        The filter's time at each step, s.
    kind : array (S,) of int
        Each step's kind (:data:`KINDS`).
    err_before, err_after : arrays (S, C)
        The components' errors before and after the step (rad, rad/s, m/s, m).
    var_before, var_after : arrays (S, C)
        Their variances before and after.
    """

    t_s: np.ndarray
    kind: np.ndarray
    err_before: np.ndarray
    err_after: np.ndarray
    var_before: np.ndarray
    var_after: np.ndarray


class _Observer:
    """Errors and variances of the chosen components at the filter's current state."""

    def __init__(
        self, truth: FlightTruth, components: tuple[str, ...], bias_true: np.ndarray
    ) -> None:
        self.truth = truth
        self.bias_true = bias_true
        self.t0 = float(truth.t_s[0])
        self.dt = float(np.median(np.diff(truth.t_s)))
        self.parts = [COMPONENTS[c] for c in components]
        self.idx = np.array([_STATE[k].start + a for k, a in self.parts])
        self.rows: list[tuple] = []

    def state(self, nf: NavFilter) -> tuple[np.ndarray, np.ndarray]:
        tr = self.truth
        j = min(max(round((nf.t_s - self.t0) / self.dt), 0), tr.t_s.shape[0] - 1)
        errs = {
            "att": quat_to_rotvec(quat_multiply(tr.q_nb[j], quat_conjugate(nf.q))),
            "rate": tr.omega_b_rps[j] - nf.w,
            "vel": tr.vel_ned_mps[j] - nf.vel,
            "pos": tr.pos_ned_m[j] - nf.pos,
            "b_wdot": self.bias_true[j, 0:3] - nf.bias[0:3],
            "b_f": self.bias_true[j, 3:6] - nf.bias[3:6],
        }
        e = np.array([errs[k][a] for k, a in self.parts])
        return e, nf.P[self.idx, self.idx].copy()

    def log(self) -> StepLog:
        if not self.rows:
            raise ValueError("the filter made no step to observe")
        t, k, e0, e1, p0, p1 = zip(*self.rows, strict=True)
        return StepLog(
            np.array(t), np.array(k), np.array(e0), np.array(e1), np.array(p0), np.array(p1)
        )


@contextmanager
def _observed(obs: _Observer):
    """``NavFilter.propagate``, ``remove_feature_residual`` (the propagation's last part:
    the forecast's error out of the block) and ``_apply`` wrapped to log each step, then
    put back as they were (the wrappers never stack across runs in one process)."""
    apply = NavFilter._apply
    inherited = ("propagate", "remove_feature_residual")

    def observed(method, kind):
        def step(self, *args, **kwargs):
            e0, p0 = obs.state(self)
            out = method(self, *args, **kwargs)
            e1, p1 = obs.state(self)
            k = step_kind(args[0], self.layout.bias) if kind is None else kind
            obs.rows.append((self.t_s, k, e0, e1, p0, p1))
            return out

        return step

    for name in inherited:
        setattr(NavFilter, name, observed(getattr(NavFilter, name), 0))
    NavFilter._apply = observed(apply, None)
    try:
        yield obs
    finally:
        for name in inherited:
            delattr(NavFilter, name)  # the mixin's method again
        NavFilter._apply = apply


def account_run(scn: FlightScenario, run: int, components: tuple[str, ...]) -> StepLog:
    """Run ``run`` of ``scn`` with its steps observed (:class:`StepLog`)."""
    unknown = [c for c in components if c not in COMPONENTS]
    if unknown:
        raise ValueError(f"unknown component {unknown[0]!r}; known: {', '.join(COMPONENTS)}")
    sim = simulate_flight(scn, run)
    cfg = sim.config
    smat = ArraySolver(cfg.layout, cfg.noise_sigma_mps2).solve_matrix
    bias_true = (sim.channel_bias_mps2 / cfg.scale) @ smat[0:6].T
    obs = _Observer(sim.truth, tuple(components), bias_true)
    with _observed(obs):
        run_filter(sim.samples, sim.fixes, sim.config)
    return obs.log()


def window_excess(logs: list[StepLog], window_s: float, component: int = 0) -> list[dict]:
    """Per window: each kind's ``(d(e^2) - dP) / P_before`` summed per run, its mean over the
    runs and the mean's standard error, with the window's mean variance and the number of
    steps; ``component`` indexes the logs' components."""
    t_end = max(float(log.t_s.max()) for log in logs)
    out = []
    for t0 in np.arange(0.0, t_end + window_s, window_s):
        t1 = t0 + window_s
        sums = np.zeros((len(logs), len(KINDS)))
        steps = np.zeros(len(KINDS), dtype=int)
        var = []
        for r, log in enumerate(logs):
            m = (log.t_s >= t0) & (log.t_s < t1)
            if not m.any():
                continue
            e0, e1 = log.err_before[m, component], log.err_after[m, component]
            p0, p1 = log.var_before[m, component], log.var_after[m, component]
            x = ((e1 * e1 - e0 * e0) - (p1 - p0)) / p0
            sums[r] = np.bincount(log.kind[m], weights=x, minlength=len(KINDS))
            steps += np.bincount(log.kind[m], minlength=len(KINDS))
            var.append(float(np.mean(p1)))
        if not var:
            continue
        se = (
            sums.std(axis=0, ddof=1) / np.sqrt(len(logs))
            if len(logs) > 1
            else np.full(len(KINDS), np.nan)
        )
        out.append(
            {
                "t0_s": float(t0),
                "t1_s": float(t1),
                "mean_var": float(np.mean(var)),
                "kinds": {
                    k: {"excess": float(m_), "se": float(s_), "steps": int(n_)}
                    for k, m_, s_, n_ in zip(KINDS, sums.mean(axis=0), se, steps, strict=True)
                },
            }
        )
    return out


def accounting_study(
    scn: FlightScenario,
    runs: int,
    window_s: float,
    components: tuple[str, ...],
    workers: int = 2,
    first: int = 0,
    progress: bool = False,
) -> dict:
    """Runs ``first .. first + runs - 1`` observed (:func:`account_run`) and each component's
    windows (:func:`window_excess`)."""
    from ngnav.campaign import run_campaign

    if runs < 2 or window_s <= 0:
        raise ValueError("the study needs at least 2 runs and a positive window")
    logs: dict[int, StepLog] = {}
    failures = run_campaign(
        partial(account_run, scn, components=tuple(components)),
        range(first, first + runs),
        logs.__setitem__,
        workers=workers,
        progress=progress,
        desc="accounting",
    )
    done = [logs[i] for i in sorted(logs)]
    if len(done) < 2:
        raise ValueError(f"fewer than 2 runs finished: {[f.error for f in failures]}")
    return {
        "scenario": scn.name,
        "runs": len(done),
        "failed": [{"run": f.run, "reason": f.error} for f in failures],
        "window_s": window_s,
        "components": {c: window_excess(done, window_s, i) for i, c in enumerate(components)},
    }


# ---------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> int:
    """``python -m studies.accounting [--scenario S] [--runs N] [--first K] [--window S]
    [--component C ...] [--json]``."""
    import argparse
    import json
    import sys

    from ngnav.sim.flight_scenario import load_flight

    p = argparse.ArgumentParser(
        prog="python -m studies.accounting",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scenario", default="ground", help="flight scenario or TOML path")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="K=V")
    p.add_argument("--runs", type=int, default=24)
    p.add_argument("--first", type=int, default=0, help="index of the first run")
    p.add_argument("--window", type=float, default=12.0, help="window length, s")
    p.add_argument(
        "--component",
        action="append",
        choices=list(COMPONENTS),
        help="a component to follow (repeatable; default heading)",
    )
    p.add_argument("--workers", type=int, default=2, help="dask worker processes")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    try:
        out = accounting_study(
            load_flight(args.scenario, args.overrides),
            args.runs,
            args.window,
            tuple(args.component or ["heading"]),
            args.workers,
            args.first,
            progress=not args.json,
        )
    except ValueError as exc:
        print(f"studies.accounting: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(
        f"{out['scenario']}: runs {args.first}-{args.first + out['runs'] - 1}; per step kind, "
        "(d(e^2) - dP) / P summed over the window, mean over runs (standard error): "
        "positive, the steps left the error that many variances larger than they said"
    )
    for name, windows in out["components"].items():
        print(f"  {name}")
        print("    window s     " + "".join(f"{k:>16s}" for k in KINDS) + "   mean var")
        for w in windows:
            cells = "".join(
                f"{v['excess']:+9.2f} ({v['se']:4.2f})" if v["steps"] else f"{'':16s}"
                for v in w["kinds"].values()
            )
            print(f"    {w['t0_s']:6.1f}-{w['t1_s']:6.1f} {cells}   {w['mean_var']:.2e}")
    for f in out["failed"]:
        print(f"  run {f['run']} failed: {f['reason']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
