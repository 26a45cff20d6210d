"""The configurations side by side on one simulated flight (``ngnav evaluate``).

``evaluate_scenario`` runs one simulated flight (``default_rng([seed, i])``)
through five configurations (GM(1,1), no compensation, the oracle, the array
alone, GPS alone) and reports each one's errors, the bound and event checks and
the accuracy targets.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from filters.evaluate import ErrorSummary, RunErrors, bound_summary, run_errors, summarise
from filters.gps_only import run_gps_only
from filters.pipeline import run_filter
from ngnav.errors import CovarianceError
from ngnav.records import RunResult
from ngnav.sim.flight_scenario import FlightScenario
from ngnav.sim.simulate import SimulatedRun, simulate_flight

#: The configurations of ``ngnav evaluate``, in table order.
CONFIGURATIONS: tuple[str, ...] = ("gm11", "none", "oracle", "array-alone", "gps-alone")


@dataclass(frozen=True)
class EvaluationRow:
    """One configuration's errors; ``failure`` says why a run stopped (then all NaN)."""

    name: str
    summary: ErrorSummary
    bound: dict[str, float] | None
    counts: dict[str, int]
    failure: str | None = None

    @property
    def att_rms_deg(self) -> float:
        """Total attitude RMS: roll, pitch and yaw RMS added in quadrature."""
        s = self.summary
        return float(np.sqrt(s.roll_rms_deg**2 + s.pitch_rms_deg**2 + s.yaw_rms_deg**2))


def run_configuration(sim: SimulatedRun, name: str, bound: bool = False) -> RunResult | None:
    """Run one configuration of the table on a simulated run (None for GPS alone)."""
    if name == "gps-alone":
        return None
    method = "gm11" if name == "array-alone" else name
    return run_filter(
        sim.samples,
        sim.fixes,
        sim.config,
        compensation=method,
        use_gps=name != "array-alone",
        true_layout=sim.true_layout(),
        truth=sim.truth,
        bound=bound,
    )


def _gps_only_errors(sim: SimulatedRun, t_out: np.ndarray) -> RunErrors:
    cfg = sim.config
    p, v, _ = run_gps_only(sim.fixes, cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m, t_out)
    idx = np.rint((t_out - sim.truth.t_s[0]) / np.median(np.diff(sim.truth.t_s))).astype(int)
    nan3 = np.full((t_out.shape[0], 3), np.nan)
    # GPS alone locates the antenna; compare with the antenna's true position
    from ngnav.rotation import dcm_from_quat

    arm = dcm_from_quat(sim.truth.q_nb[idx]) @ cfg.antenna_b_m
    return RunErrors(
        t_out, sim.truth.pos_ned_m[idx] + arm - p, sim.truth.vel_ned_mps[idx] - v, nan3, nan3, nan3
    )


def evaluate_scenario(
    scn: FlightScenario,
    run_index: int = 0,
    configurations: tuple[str, ...] = CONFIGURATIONS,
    progress: bool = False,
) -> dict:
    """Errors of each configuration on one simulated run, with the bound and event checks
    (``progress``: a bar over the configurations on stderr)."""
    from tqdm import tqdm

    sim = simulate_flight(scn, run_index)
    rows = []
    main = None
    t_ref = None
    # every configuration's errors, and the partial ones of a diverged configuration
    errors: dict[str, RunErrors] = {}
    for name in tqdm(configurations, desc="evaluate", unit="run", disable=not progress):
        if name == "gps-alone":
            continue
        try:
            res = run_configuration(sim, name, bound=name == "gm11")
        except CovarianceError as exc:
            # a diverging configuration (e.g. no compensation) is a result, not a crash
            nan = ErrorSummary(*([float("nan")] * len(ErrorSummary.__dataclass_fields__)))
            rows.append(EvaluationRow(name, nan, None, {}, f"diverged: {exc}"))
            if exc.partial is not None:
                errors[name] = run_errors(exc.partial.estimates, sim.truth)
            continue
        errs = run_errors(res.estimates, sim.truth)
        errors[name] = errs
        bnd = (
            bound_summary(res.estimates.bound_nav, q_nb=res.estimates.q_nb)
            if res.estimates.bound_nav is not None
            else None
        )
        rows.append(EvaluationRow(name, summarise(errs), bnd, res.counts))
        if name == "gm11":
            main = (res, errs)
        t_ref = res.estimates.t_s
    if "gps-alone" in configurations:
        if t_ref is None:
            # every filter configuration diverged: GPS alone still gets its row, on the
            # filter's block grid over the whole run
            step = max(1, round(scn.run.rate_hz / scn.filter.rate_hz))
            t_ref = sim.truth.t_s[::step]
        rows.append(EvaluationRow("gps-alone", summarise(_gps_only_errors(sim, t_ref)), None, {}))
    out = {
        "scenario": scn.name,
        "run_index": run_index,
        "sensor": scn.sensor.preset,
        "gps_rate_hz": scn.gps.rate_hz,
        "rows": rows,
    }
    if main is not None:
        out["events"] = _events(sim, scn, *main)
    raw = sim.fixes
    from ngnav.geodesy import LocalTangentPlane
    from ngnav.rotation import dcm_from_quat

    ltp = LocalTangentPlane(sim.config.lat0_deg, sim.config.lon0_deg, sim.config.alt0_m)
    idx = np.rint((raw.t_s - sim.truth.t_s[0]) / np.median(np.diff(sim.truth.t_s))).astype(int)
    ant = sim.truth.pos_ned_m[idx] + dcm_from_quat(sim.truth.q_nb[idx]) @ sim.config.antenna_b_m
    d = ltp.to_ned(raw.lat_deg, raw.lon_deg, raw.alt_m) - ant
    ok = ~sim.glitched
    out["raw_gps_horiz_rms_m"] = float(np.sqrt(np.mean(d[ok, 0] ** 2 + d[ok, 1] ** 2)))
    out["targets"] = _targets(rows, out["raw_gps_horiz_rms_m"])
    before = gap_before_divergence(rows, errors)
    if before is not None:
        out["targets"]["gm11_gap_closed_before_divergence"] = before
    outage = out.get("events", {}).get("outage")
    if outage is not None and "horiz_rms_over_raw_gps" in out["targets"]:
        out["targets"]["horiz_rms_over_raw_gps_outside_outage"] = (
            outage["horiz_rms_outside_outage_m"] / out["raw_gps_horiz_rms_m"]
        )
    return out


def _targets(rows: list[EvaluationRow], raw_gps_horiz_rms_m: float) -> dict:
    """The issue's accuracy figures from the table (NaN where a row is missing)."""
    by = {r.name: r for r in rows}
    out: dict = {}
    gm = by.get("gm11")
    if gm is None or gm.failure:
        return out
    out["horiz_rms_over_raw_gps"] = gm.summary.horiz_rms_m / raw_gps_horiz_rms_m
    out["roll_pitch_rms_deg"] = [gm.summary.roll_rms_deg, gm.summary.pitch_rms_deg]
    if gm.bound:
        out["att_rms_over_bound"] = gm.att_rms_deg / gm.bound["att_rms_deg"]
    none, oracle = by.get("none"), by.get("oracle")
    if none is not None and oracle is not None and not oracle.failure:
        if none.failure or not np.isfinite(none.att_rms_deg):
            out["gm11_gap_closed"] = "no compensation diverged: no finite gap to close"
        else:
            gap = none.att_rms_deg - oracle.att_rms_deg
            out["gm11_gap_closed"] = (none.att_rms_deg - gm.att_rms_deg) / gap
    return out


def gap_before_divergence(rows: list[EvaluationRow], errors: dict[str, RunErrors]) -> dict | None:
    """The GM(1,1) attitude gap over the time before no compensation diverged.

    When the uncompensated filter diverges its whole-run RMS is undefined, so
    the three configurations are compared over the epochs the diverged run
    did estimate (from the filter's start to its last recorded epoch before
    the failure): ``(none - gm11) / (none - oracle)`` of the attitude RMS
    (roll, pitch, yaw in quadrature). None when no compensation did not
    diverge or a configuration is missing.
    """
    by = {r.name: r for r in rows}
    none = by.get("none")
    if none is None or not none.failure or not {"none", "gm11", "oracle"} <= errors.keys():
        return None
    if by["gm11"].failure or by["oracle"].failure:
        return None
    t_end = float(errors["none"].t_s[-1])
    rms = {}
    for name in ("none", "gm11", "oracle"):
        e = errors[name]
        window = summarise(e, e.t_s <= t_end + 1e-9)
        rms[name] = EvaluationRow(name, window, None, {}).att_rms_deg
    gap = rms["none"] - rms["oracle"]
    return {
        "window_s": [float(errors["none"].t_s[0]), t_end],
        "att_rms_deg": rms,
        "closed": (rms["none"] - rms["gm11"]) / gap if gap > 0 else float("nan"),
    }


def _events(sim: SimulatedRun, scn: FlightScenario, res: RunResult, errs: RunErrors) -> dict:
    ev: dict = {}
    inn = res.innovations
    for tg in np.flatnonzero(sim.glitched):
        t_g = sim.fixes.t_s[tg]
        k = int(np.argmin(np.abs(inn.t_s - t_g)))
        e = int(np.searchsorted(res.estimates.t_s, t_g))
        before, after = res.estimates.pos_ned_m[e - 1], res.estimates.pos_ned_m[e]
        v = res.estimates.vel_ned_mps[e - 1]
        dt = res.estimates.t_s[e] - res.estimates.t_s[e - 1]
        moved = float(np.linalg.norm((after - before - v * dt)[:2]))
        sig = float(np.sqrt(np.trace(res.estimates.cov_nav[e - 1][0:2, 0:2])))
        ev[f"glitch at {t_g:.1f} s"] = {
            "rejected": bool(not inn.pos_accepted[k]),
            "nis": float(inn.nis_pos[k]),
            "moved_m": moved,
            "sigma_m": sig,
        }
    g = scn.gps
    if g.outage_s > 0:
        t_end = g.outage_start_s + g.outage_s
        m = errs.t_s >= t_end
        sig = np.sqrt(np.einsum("eii->ei", res.estimates.cov_nav[m][:, 0:6, 0:6]))
        inside = np.all(np.abs(errs.stacked()[m][:, 0:6]) <= 3 * sig, axis=1)
        # recovered: from then on inside for at least 5 s
        t = errs.t_s[m]
        rec = None
        for j in np.flatnonzero(inside):
            w = (t >= t[j]) & (t <= t[j] + 5.0)
            if np.all(inside[w]):
                rec = float(t[j] - t_end)
                break
        at_end = errs.t_s.searchsorted(t_end)
        # the horizontal RMS with GPS: outside the outage and the time it took to recover
        t_back = t_end + (rec if rec is not None else np.inf)
        aided = (errs.t_s < g.outage_start_s) | (errs.t_s >= t_back)
        ev["outage"] = {
            "end_s": t_end,
            "horiz_err_at_end_m": float(np.hypot(*errs.pos_ned_m[at_end, :2])),
            "recovered_within_3sigma_after_s": rec,
            "horiz_rms_outside_outage_m": summarise(errs, aided).horiz_rms_m,
        }
    return ev


def summary_dict(row: EvaluationRow) -> dict:
    """A JSON-ready view of an evaluation row."""
    return {
        "name": row.name,
        **asdict(row.summary),
        "att_rms_deg": row.att_rms_deg,
        "bound": row.bound,
        "counts": row.counts,
        "failure": row.failure,
    }
